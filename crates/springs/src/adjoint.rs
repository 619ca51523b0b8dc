//! The vector-Jacobian product of one model step, for training a model that sits on top of the
//! backbone (the residual network) with gradients that cross the backbone.
//!
//! [`Backbone::step_taped`] records what one step did (the positions at every substep start,
//! the velocities after every kick, the ground contacts' friction factors, the kinematic
//! particles); [`StepAdjoint::vjp`] then carries an adjoint `(∂L/∂x', ∂L/∂v')` of the step's
//! output back to its input `(∂L/∂x, ∂L/∂v)` through the same substeps in reverse. It is the
//! exact transpose of the step's linearisation in the elastic forces, the implicit (or
//! explicit) dashpots (directions included), gravity, the ground's penalty force, normal
//! damping and friction, the kinematic grasp and the final clamp, and the forces of every
//! effect that gives its own transpose ([`crate::EffectAdjoint::Transposed`]: drag, bending
//! springs, fields, the implicit bending damping), besides every effect that acts only at
//! construction. Held fixed (their derivatives are left out): the other effects' forces
//! ([`Backbone::held_fixed_effects`]; a friction effect's law is taken as its recorded speed
//! ratio), pushing, obstacles and a compliant grasp;
//! with `SimConfig::partitions > 1` the sweeps are transposed in the unsplit order. A contact
//! that switches within the step is not differentiable: this is the gradient of the smooth
//! piece the step is on. `docs/physics.md`, "The step's adjoint".

use std::sync::Arc;

use glam::{Vec3, Vec3A};

use crate::params::GROUND_STIFFNESS;
use crate::{AdjointContext, Backbone, Effect, EffectAdjoint, SimError};

/// What one [`Backbone::step_taped`] recorded for [`StepAdjoint::vjp`]. Reusable: each taped step
/// overwrites it.
#[derive(Debug, Clone, Default)]
pub struct StepTape {
    pub(crate) n: usize,
    pub(crate) substeps: usize,
    /// Positions at every substep's start, substep-major (`substeps × n`).
    pub(crate) x: Vec<Vec3A>,
    /// Velocities after each substep's kick (kinematic ones set), before the dashpot sweeps.
    pub(crate) v_kicked: Vec<Vec3A>,
    /// Velocities at each substep's start (explicit dashpots only).
    pub(crate) v_start: Vec<Vec3A>,
    /// Tangential velocity factor of the ground friction per substep and particle (1 off the
    /// ground), `substeps × n`.
    pub(crate) tangential: Vec<f32>,
    /// Particles moved kinematically by a closed gripper during the step.
    pub(crate) kinematic: Vec<u32>,
    /// Rest lengths during the step (effects such as plasticity change them between steps).
    pub(crate) rest: Vec<f32>,
    /// Free particles the final ground clamp moved up.
    pub(crate) clamped: Vec<bool>,
    pub(crate) complete: bool,
}

impl StepTape {
    /// An empty tape.
    pub fn new() -> Self {
        Self::default()
    }

    pub(crate) fn begin(&mut self, n: usize, substeps: usize, kinematic: &[u32], rest: &[f32]) {
        self.n = n;
        self.substeps = substeps;
        self.x.clear();
        self.x.reserve(n * substeps);
        self.tangential.clear();
        self.tangential.reserve(n * substeps);
        self.v_kicked.clear();
        self.v_kicked.reserve(n * substeps);
        self.v_start.clear();
        self.kinematic.clear();
        self.kinematic.extend_from_slice(kinematic);
        self.rest.clear();
        self.rest.extend_from_slice(rest);
        self.clamped.clear();
        self.clamped.resize(n, false);
        self.complete = false;
    }
}

/// The backbone's constants that [`StepAdjoint::vjp`] needs, copied out of it
/// ([`Backbone::step_adjoint`]) so that gradients can be taken where the backbone is out of
/// reach, such as inside an autograd graph. Make one per backbone and reuse it for every step.
#[derive(Debug, Clone)]
pub struct StepAdjoint {
    dt: f32,
    ground_z: Option<f32>,
    inv_mass: Vec<f32>,
    springs: Vec<[u32; 2]>,
    stiffness: Vec<f32>,
    damping: Vec<f32>,
    damp_weight: Vec<f32>,
    ground_normal_factor: Vec<f32>,
    ground_viscous_fraction: Vec<f32>,
    mu: f32,
    explicit_damping: bool,
    has_damping: bool,
    friction_effect: bool,
    /// The effects whose forces the adjoint differentiates ([`EffectAdjoint::Transposed`]).
    effects: Vec<Arc<dyn Effect>>,
    masses: Vec<f32>,
}

impl Backbone {
    /// What [`StepAdjoint::vjp`] needs of this backbone (a copy of its per-spring and
    /// per-particle constants).
    pub fn step_adjoint(&self) -> StepAdjoint {
        StepAdjoint {
            dt: self.dt,
            ground_z: self.config.ground_z,
            inv_mass: self.inv_mass.clone(),
            springs: self.springs.clone(),
            stiffness: self.stiffness.clone(),
            damping: self.damping.clone(),
            damp_weight: self.damp_weight.clone(),
            ground_normal_factor: self.ground_normal_factor.clone(),
            ground_viscous_fraction: self.ground_viscous_fraction.clone(),
            mu: self.mu,
            explicit_damping: self.explicit_damping,
            has_damping: self.has_damping,
            friction_effect: self.friction_effect.is_some(),
            effects: self
                .effects
                .iter()
                .filter(|e| e.adjoint() == EffectAdjoint::Transposed)
                .cloned()
                .collect(),
            masses: self.masses.clone(),
        }
    }

    /// Names of the effects whose forces [`StepAdjoint`] holds fixed (their
    /// [`Effect::adjoint`] is [`EffectAdjoint::HeldFixed`]): with none, the adjoint is the exact transpose of the
    /// step's linearisation (up to contacts that switch within it).
    pub fn held_fixed_effects(&self) -> Vec<&str> {
        self.effects
            .iter()
            .filter(|e| e.adjoint() == EffectAdjoint::HeldFixed)
            .map(|e| e.name())
            .collect()
    }
}

impl StepAdjoint {
    /// Carry the adjoint of a step's output back to its input, in place: on entry `grad_x`,
    /// `grad_v` hold `∂L/∂x'`, `∂L/∂v'` of the state the taped step produced; on return
    /// `∂L/∂x`, `∂L/∂v` of the state it started from (linearised as the module docs say).
    /// `tape` must come from a step of the backbone this adjoint was made from.
    ///
    /// ```
    /// use glam::Vec3;
    /// use springs::{Actions, Backbone, SimConfig, SpringParams, State, StepTape};
    /// let x: Vec<Vec3> = (0..10).map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.5)).collect();
    /// let bb = Backbone::new(&x, &[], SpringParams::reference_rope(), SimConfig::default())?;
    /// let actions = Actions::without_grippers(2);
    /// let (mut state, mut scratch, mut tape) = (State::at_rest(x), bb.scratch(), StepTape::new());
    /// let (from, to) = (actions.frame(0).unwrap(), actions.frame(1).unwrap());
    /// bb.step_taped(&mut state, from, to, &mut scratch, &mut tape)?;
    /// // How the mean height after the step depends on the velocities before it.
    /// let mut gx = vec![Vec3::new(0.0, 0.0, 0.1); 10];
    /// let mut gv = vec![Vec3::ZERO; 10];
    /// bb.step_adjoint().vjp(&tape, &mut gx, &mut gv)?;
    /// let dt = bb.config().step_dt;
    /// assert!(gv.iter().all(|g| (g.z - 0.1 * dt).abs() < 1e-3 * dt)); // a free fall
    /// # Ok::<(), springs::SimError>(())
    /// ```
    pub fn vjp(
        &self,
        tape: &StepTape,
        grad_x: &mut [Vec3],
        grad_v: &mut [Vec3],
    ) -> Result<(), SimError> {
        self.vjp_inner(tape, grad_x, grad_v, None)
    }

    /// As [`Self::vjp`], and also adds the step's `∂L/∂k_s` to `grad_stiffness` (one entry per
    /// spring, N/m, in the backbone's spring order): how the loss depends on each spring's
    /// stiffness through this step's elastic forces, with the substep count held fixed. Summed
    /// over a rollout's steps it is the gradient a per-spring stiffness fit needs (the
    /// paper's "Diff. Spring-Mass" baseline, `fit::refine_stiffness`).
    pub fn vjp_stiffness(
        &self,
        tape: &StepTape,
        grad_x: &mut [Vec3],
        grad_v: &mut [Vec3],
        grad_stiffness: &mut [f32],
    ) -> Result<(), SimError> {
        if grad_stiffness.len() != self.springs.len() {
            return Err(SimError::LengthMismatch {
                what: "grad_stiffness",
                expected: self.springs.len(),
                got: grad_stiffness.len(),
            });
        }
        self.vjp_inner(tape, grad_x, grad_v, Some(grad_stiffness))
    }

    fn vjp_inner(
        &self,
        tape: &StepTape,
        grad_x: &mut [Vec3],
        grad_v: &mut [Vec3],
        mut grad_k: Option<&mut [f32]>,
    ) -> Result<(), SimError> {
        let n = tape.n;
        if !tape.complete {
            return Err(SimError::TapeMismatch {
                reason: "no completed taped step recorded",
            });
        }
        if n != self.inv_mass.len() || tape.rest.len() != self.springs.len() {
            return Err(SimError::TapeMismatch {
                reason: "recorded by a backbone of another size",
            });
        }
        let needs_start_velocities = self.explicit_damping || !self.effects.is_empty();
        if needs_start_velocities && tape.v_start.len() != n * tape.substeps {
            return Err(SimError::TapeMismatch {
                reason: "recorded by a backbone without these dashpots or effects",
            });
        }
        for (what, len) in [("grad_x", grad_x.len()), ("grad_v", grad_v.len())] {
            if len != n {
                return Err(SimError::LengthMismatch {
                    what,
                    expected: n,
                    got: len,
                });
            }
        }
        let bb = self;
        let dt = bb.dt;
        let ground = bb.ground_z;
        let mut inv_m = bb.inv_mass.clone();
        for &k in &tape.kinematic {
            inv_m[k as usize] = 0.0;
        }
        let mut ax: Vec<Vec3A> = grad_x.iter().map(|&g| g.into()).collect();
        let mut av: Vec<Vec3A> = grad_v.iter().map(|&g| g.into()).collect();
        for (a, &c) in ax.iter_mut().zip(&tape.clamped) {
            if c {
                a.z = 0.0;
            }
        }
        // A kinematic particle ends every substep at its step-start position plus the gripper's
        // displacement so far: its adjoint bypasses the substeps and returns at the end.
        let mut kin_carry = vec![Vec3A::ZERO; tape.kinematic.len()];
        let mut lambda = vec![Vec3A::ZERO; n];
        let mut v2 = vec![Vec3A::ZERO; n];
        let mut pre = Vec::new();
        let mut geom: Vec<(Vec3A, f32)> = Vec::with_capacity(bb.springs.len());
        for s in (0..tape.substeps).rev() {
            let x0 = &tape.x[s * n..(s + 1) * n];
            let v1 = &tape.v_kicked[s * n..(s + 1) * n];
            for (c, &k) in kin_carry.iter_mut().zip(&tape.kinematic) {
                *c += ax[k as usize];
                ax[k as usize] = Vec3A::ZERO;
            }
            // x' = x + dt v'
            for (v, x) in av.iter_mut().zip(&ax) {
                *v += dt * *x;
            }
            // Each spring's direction and length at the substep's start, shared by the three
            // passes below (one square root per spring instead of three).
            geom.clear();
            geom.extend(bb.springs.iter().map(|&[a, b]| {
                let d = x0[b as usize] - x0[a as usize];
                let l = d.length();
                if l > 0.0 {
                    (d / l, l)
                } else {
                    (Vec3A::ZERO, 0.0)
                }
            }));
            v2.copy_from_slice(v1);
            if bb.has_damping {
                replay_sweeps(bb, &geom, &inv_m, &mut v2, &mut pre);
            }
            for e in &bb.effects {
                e.damp_velocities(dt, &inv_m, &mut v2);
            }
            if let Some(h) = ground {
                let tang = &tape.tangential[s * n..(s + 1) * n];
                ground_transpose(bb, h, x0, &v2, tang, &inv_m, &mut ax, &mut av);
            }
            for e in bb.effects.iter().rev() {
                e.damp_velocities_vjp(dt, &inv_m, &mut av);
            }
            if bb.has_damping {
                sweeps_transpose(bb, &geom, &inv_m, &pre, &mut ax, &mut av);
            }
            for &k in &tape.kinematic {
                av[k as usize] = Vec3A::ZERO;
            }
            // v1 = v + dt (f(x, v) / m + g): λ = dt av / m is the adjoint of the forces.
            for ((l, a), &im) in lambda.iter_mut().zip(&av).zip(&inv_m) {
                *l = *a * (dt * im);
            }
            let v0 = (bb.explicit_damping).then(|| &tape.v_start[s * n..(s + 1) * n]);
            for (si, (&[a, b], &(u, l))) in bb.springs.iter().zip(&geom).enumerate() {
                let (a, b) = (a as usize, b as usize);
                if l <= 0.0 {
                    continue;
                }
                let dl = lambda[b] - lambda[a];
                let along = u * u.dot(dl);
                let k = bb.stiffness[si];
                if let Some(gk) = grad_k.as_deref_mut() {
                    // f_a = k (l − l0) u = −f_b: ∂L/∂k = (λ_a − λ_b)·(l − l0) u.
                    gk[si] -= (l - tape.rest[si]) * u.dot(dl);
                }
                // ∂(k (l − l0) u)/∂d = k [(1 − l0/l)(I − u uᵀ) + u uᵀ], symmetric.
                let mut gd = k * ((1.0 - tape.rest[si] / l) * (dl - along) + along);
                if let Some(v0) = v0 {
                    let c = bb.damping[si];
                    let dv = v0[b] - v0[a];
                    gd += dashpot_direction_transpose(u, l, dv, dl) * c;
                    let cd = along * c;
                    av[a] += cd;
                    av[b] -= cd;
                }
                ax[a] += gd;
                ax[b] -= gd;
            }
            if let Some(h) = ground {
                for i in 0..n {
                    if inv_m[i] > 0.0 && x0[i].z < h {
                        ax[i].z -= GROUND_STIFFNESS * lambda[i].z;
                    }
                }
            }
            if !bb.effects.is_empty() {
                let ctx = AdjointContext {
                    dt,
                    x: x0,
                    v: &tape.v_start[s * n..(s + 1) * n],
                    masses: &bb.masses,
                };
                for e in &bb.effects {
                    e.force_vjp(&ctx, &lambda, &mut ax, &mut av);
                }
            }
        }
        for (c, &k) in kin_carry.iter().zip(&tape.kinematic) {
            ax[k as usize] += *c;
            // The step starts by setting a held particle's velocity to its gripper's.
            av[k as usize] = Vec3A::ZERO;
        }
        for (g, a) in grad_x.iter_mut().zip(&ax) {
            *g = (*a).into();
        }
        for (g, a) in grad_v.iter_mut().zip(&av) {
            *g = (*a).into();
        }
        Ok(())
    }
}

/// Transpose of the ground's velocity stage (normal damping, then friction on the
/// tangential velocity `v2` it saw), accumulating the friction's dependence on the depth
/// into `ax`. The backbone's own friction law is linearised exactly; a friction effect's,
/// by the recorded speed ratio.
#[allow(clippy::too_many_arguments)]
fn ground_transpose(
    bb: &StepAdjoint,
    h: f32,
    x0: &[Vec3A],
    v2: &[Vec3A],
    tang: &[f32],
    inv_m: &[f32],
    ax: &mut [Vec3A],
    av: &mut [Vec3A],
) {
    for i in 0..x0.len() {
        let depth = h - x0[i].z;
        let im = inv_m[i];
        if depth <= 0.0 || im == 0.0 {
            continue;
        }
        let a = &mut av[i];
        a.z *= bb.ground_normal_factor[i];
        let at = Vec3A::new(a.x, a.y, 0.0);
        let new_at = if bb.friction_effect {
            at * tang[i]
        } else {
            let vt = Vec3A::new(v2[i].x, v2[i].y, 0.0);
            let speed = vt.length();
            let frac = bb.ground_viscous_fraction[i];
            let coulomb = bb.mu * GROUND_STIFFNESS * depth * bb.dt * im;
            if speed <= 0.0 || speed * frac <= coulomb {
                at * (1.0 - frac)
            } else {
                // v_t' = v_t − c v̂: J = I − (c/s)(I − v̂ v̂ᵀ), symmetric; c grows with
                // the depth h − z.
                let dir = vt / speed;
                let along = dir * dir.dot(at);
                ax[i].z += dir.dot(at) * bb.mu * GROUND_STIFFNESS * bb.dt * im;
                at - (coulomb / speed) * (at - along)
            }
        };
        a.x = new_at.x;
        a.y = new_at.y;
    }
}

/// `Dᵀ g` for `D = ∂((u·Δv) u)/∂d` at fixed `Δv`: `D = [(u·Δv) Q + u (Q Δv)ᵀ] / l` with
/// `Q = I − u uᵀ`.
fn dashpot_direction_transpose(u: Vec3A, l: f32, dv: Vec3A, g: Vec3A) -> Vec3A {
    let qg = g - u * u.dot(g);
    let qdv = dv - u * u.dot(dv);
    (u.dot(dv) * qg + qdv * u.dot(g)) / l
}

/// The order in which the sweeps apply their pair impulses: forward, then backward.
fn sweep_order(springs: usize) -> impl Iterator<Item = usize> {
    (0..springs).chain((0..springs).rev())
}

/// Run the dashpot sweeps on `v` again, keeping each pair's `Δv = v_b − v_a` before its
/// impulse (in application order) for [`sweeps_transpose`].
fn replay_sweeps(
    bb: &StepAdjoint,
    geom: &[(Vec3A, f32)],
    inv_m: &[f32],
    v: &mut [Vec3A],
    pre: &mut Vec<Vec3A>,
) {
    pre.clear();
    for si in sweep_order(bb.springs.len()) {
        let [a, b] = bb.springs[si];
        let (a, b) = (a as usize, b as usize);
        let dv = v[b] - v[a];
        pre.push(dv);
        let (u, l) = geom[si];
        if l <= 0.0 {
            continue;
        }
        let w = bb.damp_weight[si];
        let imp = u * u.dot(dv);
        v[a] += imp * (w * inv_m[a]);
        v[b] -= imp * (w * inv_m[b]);
    }
}

/// Transpose of the dashpot sweeps, pair by pair in reverse application order: each pair
/// `v_a += w_a P Δv`, `v_b −= w_b P Δv` (`P = u uᵀ`) passes `μ = w_a λ_a − w_b λ_b` back as
/// `λ_a −= P μ`, `λ_b += P μ`, and `P`'s dependence on the positions into `ax`.
fn sweeps_transpose(
    bb: &StepAdjoint,
    geom: &[(Vec3A, f32)],
    inv_m: &[f32],
    pre: &[Vec3A],
    ax: &mut [Vec3A],
    av: &mut [Vec3A],
) {
    let springs = bb.springs.len();
    for (k, &dv) in pre.iter().enumerate().rev() {
        let si = if k < springs { k } else { 2 * springs - 1 - k };
        let [a, b] = bb.springs[si];
        let (a, b) = (a as usize, b as usize);
        let (u, l) = geom[si];
        if l <= 0.0 {
            continue;
        }
        let w = bb.damp_weight[si];
        let mu = w * inv_m[a] * av[a] - w * inv_m[b] * av[b];
        let pm = u * u.dot(mu);
        av[a] -= pm;
        av[b] += pm;
        let gd = dashpot_direction_transpose(u, l, dv, mu);
        ax[b] += gd;
        ax[a] -= gd;
    }
}
