//! Time stepping: the reusable scratch space, one model step, rollouts and batched rollouts.

use std::any::Any;

use glam::{Vec3, Vec3A};
use rayon::prelude::*;

use crate::effects::{GroundContact, SubstepContext};
use crate::params::{DIVERGENCE_LIMIT, GROUND_STIFFNESS};
use crate::partition::SlabBuffers;
use crate::split::{self, Crew};
use crate::{
    ActionFrame, Actions, Backbone, Manipulation, Rollout, SimError, State, StepTape, kernels,
};

/// Reusable working memory of one rollout: internal state, per-spring buffers, the rollout's
/// current rest lengths and the effects' per-rollout state. Make one per rollout (or per
/// sequence of [`Backbone::step`] calls) with [`Backbone::scratch`]; stepping allocates nothing.
pub struct Scratch {
    /// Number of particles; the particle arrays below are padded to a power of two.
    n: usize,
    pub(crate) x: Vec<Vec3A>,
    pub(crate) v: Vec<Vec3A>,
    pub(crate) f: Vec<Vec3A>,
    pub(crate) dir: Vec<Vec3A>,
    pub(crate) rest: Vec<f32>,
    pub(crate) inv_m_eff: Vec<f32>,
    /// Dashpot sweep data for the current kinematic set (rebuilt when that set changes).
    pub(crate) damp: Vec<kernels::DampSpring>,
    /// Kinematic particle ids `damp` was built for (`None`: not built yet).
    damp_kin: Option<Vec<u32>>,
    /// Kinematic particles of the current step: (particle, gripper, position at step start).
    kin: Vec<(u32, u32, Vec3A)>,
    g_from: Vec<Vec3>,
    g_to: Vec<Vec3>,
    g_vel: Vec<Vec3>,
    g_now: Vec<Vec3>,
    g_closed: Vec<bool>,
    effect_states: Vec<Box<dyn Any + Send>>,
    /// Private copies of each slab's particles and springs when the rollout is split.
    pub(crate) slabs: Vec<SlabBuffers>,
    steps: usize,
}

impl std::fmt::Debug for Scratch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Scratch")
            .field("particles", &self.n)
            .field("springs", &self.rest.len())
            .field("steps", &self.steps)
            .finish_non_exhaustive()
    }
}

/// One job for [`rollout_batch`].
#[derive(Debug, Clone, Copy)]
pub struct RolloutJob<'a> {
    /// The model.
    pub backbone: &'a Backbone,
    /// Initial state.
    pub init: &'a State,
    /// Gripper actions, one frame per output state.
    pub actions: &'a Actions,
}

/// Run many rollouts in parallel on the current rayon pool. Each rollout is single-threaded, so
/// the results (in input order) are bit-identical for any thread count.
///
/// ```
/// use glam::Vec3;
/// use springs::{Actions, Backbone, RolloutJob, SimConfig, SpringParams, State, rollout_batch};
/// let x: Vec<Vec3> = (0..20).map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.05)).collect();
/// let init = State::at_rest(x.clone());
/// let actions = Actions::without_grippers(4);
/// // One backbone per candidate stiffness, as in a CMA-ES population.
/// let bbs: Vec<Backbone> = [1e3, 1e4]
///     .iter()
///     .map(|&k| Backbone::new(&x, &[], SpringParams { stiffness: k, ..SpringParams::reference_rope() }, SimConfig::default()))
///     .collect::<Result<_, _>>()?;
/// let jobs: Vec<RolloutJob<'_>> =
///     bbs.iter().map(|bb| RolloutJob { backbone: bb, init: &init, actions: &actions }).collect();
/// let out = rollout_batch(&jobs);
/// assert_eq!(out.len(), 2);
/// assert_eq!(out[1].as_ref().unwrap(), &bbs[1].rollout(&init, &actions)?);
/// # Ok::<(), springs::SimError>(())
/// ```
pub fn rollout_batch(jobs: &[RolloutJob<'_>]) -> Vec<Result<Rollout, SimError>> {
    jobs.par_iter()
        .map(|j| split::as_batch_job(|| j.backbone.rollout(j.init, j.actions)))
        .collect()
}

fn check_frame(f: &ActionFrame<'_>, g: usize) -> Result<(), SimError> {
    for (what, len) in [
        ("frame.positions", f.positions.len()),
        ("frame.closed", f.closed.len()),
    ] {
        if len != g {
            return Err(SimError::LengthMismatch {
                what,
                expected: g,
                got: len,
            });
        }
    }
    match f.positions.iter().position(|p| !p.is_finite()) {
        Some(index) => Err(SimError::NonFinite {
            what: "frame.positions",
            index,
        }),
        None => Ok(()),
    }
}

impl Backbone {
    /// Fresh scratch space for this backbone (rest lengths reset, effect states new).
    pub fn scratch(&self) -> Scratch {
        let (n, s) = (self.num_particles(), self.springs.len());
        let padded = n.next_power_of_two();
        let mut inv_m_eff = self.inv_mass.clone();
        inv_m_eff.resize(padded, 0.0);
        Scratch {
            n,
            x: vec![Vec3A::ZERO; padded],
            v: vec![Vec3A::ZERO; padded],
            f: vec![Vec3A::ZERO; padded],
            dir: vec![Vec3A::ZERO; s],
            rest: self.rest_lengths.clone(),
            inv_m_eff,
            damp: vec![kernels::DampSpring::default(); if self.has_damping { s } else { 0 }],
            damp_kin: None,
            kin: Vec::with_capacity(self.held_list.len()),
            g_from: Vec::new(),
            g_to: Vec::new(),
            g_vel: Vec::new(),
            g_now: Vec::new(),
            g_closed: Vec::new(),
            effect_states: self.effects.iter().map(|e| e.new_state(self)).collect(),
            slabs: self
                .partition
                .as_ref()
                .map_or_else(Vec::new, |p| p.buffers(self.has_damping)),
            steps: 0,
        }
    }

    fn check_held(&self, num_grippers: usize) -> Result<(), SimError> {
        if self.config.manipulation != Manipulation::Grasp {
            return Ok(());
        }
        match self
            .held_list
            .iter()
            .find(|&&(_, g)| g as usize >= num_grippers)
        {
            Some(&(i, g)) => Err(SimError::InvalidHeld {
                index: i as usize,
                value: i64::from(g),
                reason: "gripper index not below the number of grippers in the actions",
            }),
            None => Ok(()),
        }
    }

    /// Advance `state` by one model step (`config.step_dt`), grippers moving linearly from
    /// `from` to `to`. Allocation-free once the scratch has seen this gripper count. On error
    /// the state is left unchanged. Use one scratch per rollout: it carries that rollout's rest
    /// lengths and effect states.
    ///
    /// ```
    /// use glam::Vec3;
    /// use springs::{Actions, Backbone, SimConfig, SpringParams, State};
    /// let x: Vec<Vec3> = (0..50).map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.0)).collect();
    /// let held: Vec<i32> = (0..50).map(|i| if i == 0 { 0 } else { -1 }).collect();
    /// let bb = Backbone::new(&x, &held, SpringParams::reference_rope(), SimConfig::default())?;
    /// let frames = (0..4).map(|t| vec![Vec3::new(0.0, 0.0, 0.02 * t as f32)]).collect();
    /// let actions = Actions::new(frames, vec![vec![true]; 4])?;
    /// let (mut state, mut scratch) = (State::at_rest(x), bb.scratch());
    /// for t in 0..3 {
    ///     bb.step(&mut state, actions.frame(t).unwrap(), actions.frame(t + 1).unwrap(), &mut scratch)?;
    ///     // ... a residual model may correct `state` here before the next step ...
    /// }
    /// assert!((state.x[0].z - 0.06).abs() < 1e-5);
    /// # Ok::<(), springs::SimError>(())
    /// ```
    pub fn step(
        &self,
        state: &mut State,
        from: ActionFrame<'_>,
        to: ActionFrame<'_>,
        scratch: &mut Scratch,
    ) -> Result<(), SimError> {
        self.step_inner(state, from, to, scratch, None)
    }

    /// [`Backbone::step`], recording in `tape` what [`crate::StepAdjoint::vjp`] needs to carry
    /// gradients back through this step (positions and velocities at every substep: about
    /// `2 × substeps × n` points). The step itself is bit-identical to [`Backbone::step`]'s.
    pub fn step_taped(
        &self,
        state: &mut State,
        from: ActionFrame<'_>,
        to: ActionFrame<'_>,
        scratch: &mut Scratch,
        tape: &mut StepTape,
    ) -> Result<(), SimError> {
        tape.complete = false;
        self.step_inner(state, from, to, scratch, Some(tape))?;
        tape.complete = true;
        Ok(())
    }

    fn step_inner(
        &self,
        state: &mut State,
        from: ActionFrame<'_>,
        to: ActionFrame<'_>,
        scratch: &mut Scratch,
        tape: Option<&mut StepTape>,
    ) -> Result<(), SimError> {
        let n = self.num_particles();
        if scratch.n != n || scratch.rest.len() != self.springs.len() {
            return Err(SimError::ScratchMismatch {
                scratch_particles: scratch.n,
                scratch_springs: scratch.rest.len(),
                particles: n,
                springs: self.springs.len(),
            });
        }
        state.validate(n)?;
        let g = from.positions.len();
        check_frame(&from, g)?;
        check_frame(&to, g)?;
        self.check_held(g)?;
        for i in 0..n {
            scratch.x[i] = state.x[i].into();
            scratch.v[i] = state.v[i].into();
        }
        let threads = split::crew_size(self);
        split::with_crew(self, threads, scratch, |sc, crew| {
            self.advance(sc, from, to, crew, tape)
        })?;
        for i in 0..n {
            state.x[i] = scratch.x[i].into();
            state.v[i] = scratch.v[i].into();
        }
        Ok(())
    }

    /// Roll out from `init` through all frames of `actions`: the result has one state per frame
    /// (frame 0 = `init`). Single-threaded; see [`rollout_batch`] for parallel runs.
    pub fn rollout(&self, init: &State, actions: &Actions) -> Result<Rollout, SimError> {
        let n = self.num_particles();
        init.validate(n)?;
        let frames = actions.num_frames();
        if frames == 0 {
            return Err(SimError::LengthMismatch {
                what: "actions frames (at least one)",
                expected: 1,
                got: 0,
            });
        }
        self.check_held(actions.num_grippers())?;
        let mut sc = self.scratch();
        for i in 0..n {
            sc.x[i] = init.x[i].into();
            sc.v[i] = init.v[i].into();
        }
        let mut out = Rollout {
            positions: Vec::with_capacity(frames),
            velocities: Vec::with_capacity(frames),
        };
        out.positions.push(init.x.clone());
        out.velocities.push(init.v.clone());
        let threads = split::crew_size(self);
        split::with_crew(self, threads, &mut sc, |sc, crew| {
            for (from, to) in (0..frames)
                .filter_map(|t| actions.frame(t))
                .zip((1..frames).filter_map(|t| actions.frame(t)))
            {
                self.advance(sc, from, to, crew, None)?;
                out.positions
                    .push(sc.x[..n].iter().map(|&p| p.into()).collect());
                out.velocities
                    .push(sc.v[..n].iter().map(|&p| p.into()).collect());
            }
            Ok(out)
        })
    }

    /// One model step on the scratch's internal state (inputs already validated).
    fn advance(
        &self,
        sc: &mut Scratch,
        from: ActionFrame<'_>,
        to: ActionFrame<'_>,
        crew: Option<&Crew>,
        mut tape: Option<&mut StepTape>,
    ) -> Result<(), SimError> {
        sc.g_from.clear();
        sc.g_from.extend_from_slice(from.positions);
        sc.g_to.clear();
        sc.g_to.extend_from_slice(to.positions);
        sc.g_closed.clear();
        sc.g_closed.extend_from_slice(from.closed);
        for (e, st) in self.effects.iter().zip(sc.effect_states.iter_mut()) {
            e.adjust_actions(&mut **st, &mut sc.g_from, &mut sc.g_to, &mut sc.g_closed);
        }
        let step_dt = self.config.step_dt;
        sc.g_vel.clear();
        sc.g_vel.extend(
            sc.g_from
                .iter()
                .zip(&sc.g_to)
                .map(|(a, b)| (*b - *a) / step_dt),
        );
        sc.g_now.clear();
        sc.g_now.extend_from_slice(&sc.g_from);

        let n = sc.n;
        sc.inv_m_eff[..n].copy_from_slice(&self.inv_mass);
        sc.kin.clear();
        if self.grasp_is_kinematic() {
            for &(i, g) in &self.held_list {
                if sc.g_closed[g as usize] {
                    sc.kin.push((i, g, sc.x[i as usize]));
                    sc.inv_m_eff[i as usize] = 0.0;
                    sc.v[i as usize] = sc.g_vel[g as usize].into();
                }
            }
        }
        if self.has_damping {
            self.update_damp_springs(sc, crew);
        }
        let n_sub = self.substeps;
        let dt = self.dt;
        let gravity = Vec3A::from(self.config.gravity);
        if let Some(t) = tape.as_deref_mut() {
            let kin: Vec<u32> = sc.kin.iter().map(|k| k.0).collect();
            t.begin(n, n_sub as usize, &kin, &sc.rest);
        }
        for s in 0..n_sub {
            if let Some(t) = tape.as_deref_mut() {
                t.x.extend_from_slice(&sc.x[..n]);
                t.tangential.resize(t.tangential.len() + n, 1.0);
                if self.explicit_damping || self.transposed_effects {
                    t.v_start.extend_from_slice(&sc.v[..n]);
                }
            }
            let frac0 = s as f32 / n_sub as f32;
            let frac1 = (s + 1) as f32 / n_sub as f32;
            match &self.partition {
                None => self.elastic_pass(
                    0,
                    &self.springs,
                    sc.x.as_slice(),
                    &sc.v,
                    &sc.rest,
                    &mut sc.f,
                    &mut sc.dir,
                ),
                Some(p) => split::elastic(self, p, sc, crew),
            }
            if !self.effects.is_empty() {
                lerp_grippers(&sc.g_from, &sc.g_to, frac0, &mut sc.g_now);
                let ctx = SubstepContext {
                    backbone: self,
                    dt,
                    substep: s as usize,
                    x: &sc.x[..n],
                    v: &sc.v[..n],
                    grippers: &sc.g_now,
                    gripper_velocities: &sc.g_vel,
                    closed: &sc.g_closed,
                };
                for (e, st) in self.effects.iter().zip(sc.effect_states.iter_mut()) {
                    e.add_forces(&ctx, &mut **st, &sc.rest, &mut sc.f[..n]);
                }
            }
            if let Some(h) = self.config.ground_z {
                kernels::ground_force(h, &sc.x[..n], &sc.inv_m_eff[..n], &mut sc.f[..n]);
            }
            kernels::kick(
                dt,
                gravity,
                &mut sc.f[..n],
                &sc.inv_m_eff[..n],
                &mut sc.v[..n],
            );
            for &(i, g, _) in &sc.kin {
                sc.v[i as usize] = sc.g_vel[g as usize].into();
            }
            if let Some(t) = tape.as_deref_mut() {
                t.v_kicked.extend_from_slice(&sc.v[..n]);
            }
            if self.has_damping {
                match &self.partition {
                    None => kernels::damping_sweeps(&sc.damp, &sc.dir, &mut sc.v),
                    Some(p) => split::damping(self, p, sc, crew),
                }
            }
            for e in &self.effects {
                e.damp_velocities(dt, &sc.inv_m_eff[..n], &mut sc.v[..n]);
            }
            if let Some(h) = self.config.ground_z {
                let len = tape.as_ref().map_or(0, |t| t.tangential.len());
                let tangential = tape.as_deref_mut().map(|t| &mut t.tangential[len - n..]);
                self.ground_velocity(h, sc, tangential);
            }
            kernels::drift(dt, &sc.v[..n], &mut sc.x[..n]);
            for &(i, g, x0) in &sc.kin {
                let g = g as usize;
                sc.x[i as usize] = x0 + frac1 * Vec3A::from(sc.g_to[g] - sc.g_from[g]);
            }
            if self.config.manipulation == Manipulation::Push || !self.effects.is_empty() {
                lerp_grippers(&sc.g_from, &sc.g_to, frac1, &mut sc.g_now);
            }
            if self.config.manipulation == Manipulation::Push {
                self.push(sc);
            }
            if !self.config.obstacles.is_empty() {
                crate::obstacles::resolve(
                    self.config.obstacles.as_slice(),
                    self.mu,
                    &mut sc.x[..n],
                    &mut sc.v[..n],
                    &sc.inv_m_eff[..n],
                );
            }
            if !self.effects.is_empty() {
                let ctx = SubstepContext {
                    backbone: self,
                    dt,
                    substep: s as usize,
                    x: &sc.x[..n],
                    v: &sc.v[..n],
                    grippers: &sc.g_now,
                    gripper_velocities: &sc.g_vel,
                    closed: &sc.g_closed,
                };
                for (e, st) in self.effects.iter().zip(sc.effect_states.iter_mut()) {
                    e.end_substep(&ctx, &mut **st, &mut sc.rest);
                }
            }
        }
        if let (Some(h), true) = (self.config.ground_z, self.config.clamp_to_ground) {
            // The reference clamps positions above the ground after each model step.
            for (i, (x, &im)) in sc.x[..n].iter_mut().zip(&sc.inv_m_eff[..n]).enumerate() {
                if im > 0.0 && x.z < h {
                    x.z = h;
                    if let Some(t) = tape.as_deref_mut() {
                        t.clamped[i] = true;
                    }
                }
            }
        }
        let limit2 = DIVERGENCE_LIMIT * DIVERGENCE_LIMIT;
        let bad = sc.x[..n].iter().zip(&sc.v[..n]).position(|(x, v)| {
            !(x.is_finite()
                && v.is_finite()
                && x.length_squared() <= limit2
                && v.length_squared() <= limit2)
        });
        if let Some(particle) = bad {
            return Err(SimError::Diverged {
                step: sc.steps,
                particle,
            });
        }
        sc.steps += 1;
        Ok(())
    }

    /// Ground contact on velocities: implicit normal damping, then friction that removes
    /// `min(viscous, Coulomb)` tangential speed without reversing it (docs/physics.md).
    /// With `tangential`, also records each contact's factor `|v_t'| / |v_t|` (for the
    /// step's adjoint).
    fn ground_velocity(&self, h: f32, sc: &mut Scratch, mut tangential: Option<&mut [f32]>) {
        let dt = self.dt;
        for i in 0..sc.n {
            let depth = h - sc.x[i].z;
            let im = sc.inv_m_eff[i];
            if depth <= 0.0 || im == 0.0 {
                continue;
            }
            let v = &mut sc.v[i];
            v.z *= self.ground_normal_factor[i];
            let vt = Vec3A::new(v.x, v.y, 0.0);
            let normal_force = GROUND_STIFFNESS * depth;
            let new_vt = match self.friction_effect {
                Some(k) => self.effects[k].ground_friction(&GroundContact {
                    particle: i,
                    tangential_velocity: vt,
                    normal_force,
                    mass: self.masses[i],
                    mu: self.mu,
                    dt,
                }),
                None => {
                    let speed = vt.length();
                    if speed > 0.0 {
                        let dec = (speed * self.ground_viscous_fraction[i])
                            .min(self.mu * normal_force * dt * im);
                        vt * (1.0 - dec / speed)
                    } else {
                        vt
                    }
                }
            };
            if let Some(t) = tangential.as_deref_mut() {
                let speed = vt.length();
                t[i] = if speed > 0.0 {
                    new_vt.length() / speed
                } else {
                    1.0
                };
            }
            v.x = new_vt.x;
            v.y = new_vt.y;
        }
    }

    /// Push: project free particles inside an active gripper sphere onto its surface and remove
    /// their inward velocity relative to the gripper.
    fn push(&self, sc: &mut Scratch) {
        let r = self.config.gripper_radius;
        for g in 0..sc.g_now.len() {
            if !sc.g_closed[g] {
                continue;
            }
            let c = Vec3A::from(sc.g_now[g]);
            let vg = Vec3A::from(sc.g_vel[g]);
            for i in 0..sc.n {
                let d = sc.x[i] - c;
                let d2 = d.length_squared();
                if d2 >= r * r || sc.inv_m_eff[i] == 0.0 {
                    continue;
                }
                let dist = d2.sqrt();
                // A particle exactly at the centre is pushed up (+z).
                let nrm = if dist > 0.0 { d / dist } else { Vec3A::Z };
                sc.x[i] = c + r * nrm;
                let vn = (sc.v[i] - vg).dot(nrm);
                if vn < 0.0 {
                    sc.v[i] -= vn * nrm;
                }
            }
        }
    }
}

impl Backbone {
    /// Rebuild the dashpot sweep data when the set of kinematic particles changed: a kinematic
    /// end has zero inverse mass, so it receives no impulse.
    fn update_damp_springs(&self, sc: &mut Scratch, crew: Option<&Crew>) {
        let same = sc.damp_kin.as_ref().is_some_and(|k| {
            k.len() == sc.kin.len() && k.iter().zip(&sc.kin).all(|(a, b)| *a == b.0)
        });
        if same {
            return;
        }
        let im = &sc.inv_m_eff;
        let damp_spring = |[a, b]: [u32; 2], [la, lb]: [u32; 2], w: f32| kernels::DampSpring {
            a: la,
            b: lb,
            wa: w * im[a as usize],
            wb: w * im[b as usize],
        };
        let start = match &self.partition {
            None => 0,
            Some(p) => p.cross_start,
        };
        for s in start..self.springs.len() {
            sc.damp[s] = damp_spring(self.springs[s], self.springs[s], self.damp_weight[s]);
        }
        if let Some(p) = &self.partition {
            split::fill_damp(self, p, sc, crew);
        }
        let ids = sc.damp_kin.get_or_insert_with(Vec::new);
        ids.clear();
        ids.extend(sc.kin.iter().map(|k| k.0));
    }
}

impl Backbone {
    /// Elastic forces (and the explicit dashpot, when chosen) of `springs`, which are the
    /// backbone's springs from index `first` on, with endpoints indexing `x`, `v` and `f`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn elastic_pass(
        &self,
        first: usize,
        springs: &[[u32; 2]],
        x: &[Vec3A],
        v: &[Vec3A],
        rest: &[f32],
        f: &mut [Vec3A],
        dir: &mut [Vec3A],
    ) {
        let r = first..first + springs.len();
        if self.explicit_damping {
            kernels::elastic_explicit_dashpot(
                springs,
                &self.stiffness[r.clone()],
                &self.damping[r.clone()],
                &rest[r],
                x,
                v,
                f,
            );
        } else {
            kernels::elastic(springs, &self.stiffness[r.clone()], &rest[r], x, f, dir);
        }
    }
}

fn lerp_grippers(from: &[Vec3], to: &[Vec3], t: f32, out: &mut [Vec3]) {
    for ((o, a), b) in out.iter_mut().zip(from).zip(to) {
        *o = *a + t * (*b - *a);
    }
}
