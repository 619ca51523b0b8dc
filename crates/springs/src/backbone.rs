//! The backbone model: construction, stability bound, accessors and force queries.

use glam::{Vec3, Vec3A};

use crate::effects::ModelSetup;
use crate::params::{GROUND_DAMPING, GROUND_STIFFNESS, GROUND_VISCOUS_FRICTION};
use crate::{Dashpot, Effect, Manipulation, SimConfig, SimError, SpringParams, Substep, Topology};

/// Most substeps one model step may take.
const MAX_SUBSTEPS: u64 = 1_000_000;

/// Optional extras for [`Backbone::with_options`].
#[derive(Debug, Default)]
pub struct BackboneOptions {
    /// Mass per particle, kg (default: 1 kg each, as in the reference).
    pub masses: Option<Vec<f32>>,
    /// Extra force terms, applied in order.
    pub effects: Vec<Box<dyn Effect>>,
    /// Pairs that may not be joined by a spring even within the threshold
    /// ([`Topology::build_with`]); `None` joins every pair within it, as the reference does.
    pub pair_filter: Option<std::sync::Arc<dyn crate::PairFilter>>,
    /// The particles in order along the centreline, for an object that is a chain (a
    /// cable's markers and the particles between them); handed to every effect's setup
    /// ([`crate::ModelSetup::chain`]). Every index must name a particle, none twice.
    pub chain: Option<std::sync::Arc<[u32]>>,
    /// Particles joined to the object by their own radius and spring count (PhysTwin's
    /// controller points; [`Topology::build_anchored`]); `None` joins every particle by the
    /// object's threshold and count.
    pub anchors: Option<crate::AnchorSprings>,
}

/// A spring-mass model of one object: topology, parameters and a fixed substep.
///
/// Immutable once built, so one backbone can drive many rollouts at once (`Backbone: Sync`).
#[derive(Debug)]
pub struct Backbone {
    pub(crate) rest_positions: Vec<Vec3>,
    pub(crate) held: Vec<i32>,
    /// `(particle, gripper)` for every particle with `held >= 0`.
    pub(crate) held_list: Vec<(u32, u32)>,
    pub(crate) params: SpringParams,
    pub(crate) config: SimConfig,
    pub(crate) springs: Vec<[u32; 2]>,
    pub(crate) rest_lengths: Vec<f32>,
    pub(crate) stiffness: Vec<f32>,
    pub(crate) damping: Vec<f32>,
    /// Weight of each spring's implicit dashpot impulse per sweep, kg (depends on the substep;
    /// empty with [`Dashpot::Explicit`]).
    pub(crate) damp_weight: Vec<f32>,
    pub(crate) masses: Vec<f32>,
    pub(crate) inv_mass: Vec<f32>,
    /// Per particle `1 / (1 + c_g dt / m)`: implicit normal damping in ground contact.
    pub(crate) ground_normal_factor: Vec<f32>,
    /// Per particle `(k_f dt / m) / (1 + k_f dt / m)`: implicit viscous friction fraction.
    pub(crate) ground_viscous_fraction: Vec<f32>,
    pub(crate) mu: f32,
    pub(crate) stable_dt: f32,
    pub(crate) substeps: u32,
    pub(crate) dt: f32,
    /// Implicit dashpot sweeps are needed (some implicit damping weight > 0).
    pub(crate) has_damping: bool,
    /// Dashpot forces go into the elastic pass ([`Dashpot::Explicit`] and some damping > 0).
    pub(crate) explicit_damping: bool,
    /// Shared so that [`crate::StepAdjoint`] can hold them too.
    pub(crate) effects: Vec<std::sync::Arc<dyn Effect>>,
    /// Some effect gives its forces' transpose, which needs each substep's start velocities
    /// on the tape.
    pub(crate) transposed_effects: bool,
    pub(crate) friction_effect: Option<usize>,
    pub(crate) compliant_grasp: bool,
    /// Slabs for a split rollout (`config.partitions > 1`).
    pub(crate) partition: Option<crate::partition::Partition>,
}

impl Backbone {
    /// Build a backbone with unit masses and no effects. `held` has one entry per particle
    /// (`-1`: not held, `g >= 0`: follows gripper `g` while it is closed) or is empty (none held).
    ///
    /// ```
    /// use glam::Vec3;
    /// use springs::{Actions, Backbone, SimConfig, SpringParams, State};
    /// // A 1 m chain of 101 particles lying on the ground, its first particle held.
    /// let x: Vec<Vec3> = (0..101).map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.0)).collect();
    /// let mut held = vec![-1; x.len()];
    /// held[0] = 0;
    /// let bb = Backbone::new(&x, &held, SpringParams::reference_rope(), SimConfig::default())?;
    /// // Lift the gripper 5 cm per 0.1 s step for 5 steps.
    /// let frames: Vec<Vec<Vec3>> = (0..6).map(|t| vec![Vec3::new(0.0, 0.0, 0.05 * t as f32)]).collect();
    /// let actions = Actions::new(frames, vec![vec![true]; 6])?;
    /// let out = bb.rollout(&State::at_rest(x), &actions)?;
    /// assert_eq!(out.positions.len(), 6);
    /// assert!((out.positions[5][0].z - 0.25).abs() < 1e-5);
    /// # Ok::<(), springs::SimError>(())
    /// ```
    pub fn new(
        rest_positions: &[Vec3],
        held: &[i32],
        params: SpringParams,
        config: SimConfig,
    ) -> Result<Self, SimError> {
        Self::with_options(
            rest_positions,
            held,
            params,
            config,
            BackboneOptions::default(),
        )
    }

    /// Build a backbone with per-particle masses and/or effects (see [`Backbone::new`]).
    pub fn with_options(
        rest_positions: &[Vec3],
        held: &[i32],
        params: SpringParams,
        config: SimConfig,
        options: BackboneOptions,
    ) -> Result<Self, SimError> {
        params.validate()?;
        config.validate()?;
        let n = rest_positions.len();
        let held = match held.len() {
            0 => vec![-1; n],
            len if len == n => held.to_vec(),
            len => {
                return Err(SimError::LengthMismatch {
                    what: "held",
                    expected: n,
                    got: len,
                });
            }
        };
        if let Some(index) = held.iter().position(|&h| h < -1) {
            return Err(SimError::InvalidHeld {
                index,
                value: i64::from(held[index]),
                reason: "must be -1 or a gripper index",
            });
        }
        let mut masses = options.masses.unwrap_or_else(|| vec![1.0; n]);
        if masses.len() != n {
            return Err(SimError::LengthMismatch {
                what: "masses",
                expected: n,
                got: masses.len(),
            });
        }
        let topo = Topology::build_anchored(
            rest_positions,
            params.threshold,
            params.max_springs,
            options.pair_filter.as_deref(),
            options.anchors.as_ref(),
        )?;
        let (springs, mut rest_lengths, partition) = if config.partitions > 1 {
            let (s, l, p) = crate::partition::order(
                topo,
                rest_positions,
                config.partitions as usize,
                color_order,
            );
            (s, l, Some(p))
        } else {
            let (s, l) = color_order(topo, n);
            (s, l, None)
        };
        let mut stiffness = vec![params.stiffness; springs.len()];
        let mut damping = vec![params.damping; springs.len()];
        if let Some(chain) = &options.chain {
            crate::topology::mark_each_once(n, chain, "chain")?;
        }
        let mut effects = options.effects;
        for e in &mut effects {
            e.setup(&mut ModelSetup {
                rest_positions,
                held: &held,
                params: &params,
                springs: &springs,
                rest_lengths: &mut rest_lengths,
                stiffness: &mut stiffness,
                damping: &mut damping,
                masses: &mut masses,
                chain: options.chain.as_deref(),
            })?;
        }
        check_nonneg("masses", &masses, true)?;
        check_nonneg("spring stiffness", &stiffness, false)?;
        check_nonneg("spring damping", &damping, false)?;
        check_nonneg("rest lengths", &rest_lengths, false)?;
        let held_list = held
            .iter()
            .enumerate()
            .filter(|&(_, &g)| g >= 0)
            .map(|(i, &g)| (i as u32, g as u32))
            .collect();
        let friction_effect = effects.iter().position(|e| e.replaces_ground_friction());
        let compliant_grasp = effects.iter().any(|e| e.compliant_grasp());
        let transposed_effects = effects
            .iter()
            .any(|e| e.adjoint() == crate::EffectAdjoint::Transposed);
        let inv_mass = masses.iter().map(|m| 1.0 / m).collect();
        let mut bb = Self {
            rest_positions: rest_positions.to_vec(),
            held,
            held_list,
            mu: params.effective_ground_mu(),
            params,
            config,
            springs,
            rest_lengths,
            stiffness,
            damping,
            damp_weight: Vec::new(),
            masses,
            inv_mass,
            ground_normal_factor: Vec::new(),
            ground_viscous_fraction: Vec::new(),
            stable_dt: f32::INFINITY,
            substeps: 1,
            dt: config.step_dt,
            has_damping: false,
            explicit_damping: false,
            effects: effects.into_iter().map(std::sync::Arc::from).collect(),
            transposed_effects,
            friction_effect,
            compliant_grasp,
            partition,
        };
        bb.stable_dt = match config.substep {
            Substep::Spectral { .. } => bb.spectral_bound(),
            Substep::Auto { .. } | Substep::Fixed { .. } => bb.stability_bound(),
        };
        let substeps = match config.substep {
            Substep::Auto { safety, max_dt } | Substep::Spectral { safety, max_dt } => {
                let dt = (f64::from(safety) * f64::from(bb.stable_dt)).min(f64::from(max_dt));
                f64::from(config.step_dt) / dt
            }
            Substep::Fixed { dt } => (f64::from(config.step_dt) / f64::from(dt)).round(),
        }
        .ceil()
        .max(1.0);
        if substeps > MAX_SUBSTEPS as f64 {
            return Err(SimError::TooLarge {
                what: "substeps per model step",
                value: substeps as u64,
                limit: MAX_SUBSTEPS,
            });
        }
        bb.substeps = substeps as u32;
        bb.dt = config.step_dt / bb.substeps as f32;
        bb.precompute_implicit_terms();
        Ok(bb)
    }

    /// Largest stable substep, s (docs/physics.md "Stability bound"); infinite when nothing is
    /// stiff or explicitly damped. Per particle, Gershgorin's theorem bounds the eigenvalues of
    /// `M^-1 K` by `lambda_i = (2 sum_s k_s + k_ground + effect stiffness) / m_i`; with the
    /// explicit damping rate `gamma_i` that effects report, symplectic Euler is stable for
    /// `dt^2 lambda + 2 dt gamma <= 4`. The implicit dashpot and ground damping get no credit;
    /// the explicit dashpot adds `2 sum_s c_s` to the damping row (Gershgorin on `M^-1 C`).
    fn stability_bound(&self) -> f32 {
        let n = self.rest_positions.len();
        let (row, damp) = self.gershgorin_rows(true);
        let mut dt_max = f64::INFINITY;
        for i in 0..n {
            let inv_m = f64::from(self.inv_mass[i]);
            let lambda = f64::from(row[i].max(0.0)) * inv_m;
            let gamma = f64::from(damp[i].max(0.0)) * inv_m;
            if lambda > 0.0 || gamma > 0.0 {
                // Positive root of lambda dt^2 + 2 gamma dt - 4 = 0.
                dt_max = dt_max.min(4.0 / (gamma + (gamma * gamma + 4.0 * lambda).sqrt()));
            }
        }
        dt_max as f32
    }

    /// Per-particle Gershgorin rows (N/m) of the stiffness — the springs' own `2 Σ k` when
    /// `springs` is set, then the ground's and the effects' — and of the explicit damping
    /// (N·s/m: the explicit dashpot's `2 Σ c`, then the effects'). Without `springs`, the
    /// stiffness rows of effects that scale the springs ([`Effect::spring_stiffness_factor`])
    /// are left out too: [`Self::spectral_bound`] scales the springs' eigenvalue instead.
    fn gershgorin_rows(&self, springs: bool) -> (Vec<f32>, Vec<f32>) {
        let n = self.rest_positions.len();
        let mut row = vec![0.0f32; n];
        let mut damp = vec![0.0f32; n];
        if springs {
            for (&[a, b], &k) in self.springs.iter().zip(&self.stiffness) {
                row[a as usize] += 2.0 * k;
                row[b as usize] += 2.0 * k;
            }
        }
        if self.config.dashpot == Dashpot::Explicit {
            for (&[a, b], &c) in self.springs.iter().zip(&self.damping) {
                damp[a as usize] += 2.0 * c;
                damp[b as usize] += 2.0 * c;
            }
        }
        if self.config.ground_z.is_some() {
            for r in &mut row {
                *r += GROUND_STIFFNESS;
            }
        }
        let mut unused = Vec::new();
        for e in &self.effects {
            if !springs && e.spring_stiffness_factor().is_some() {
                unused.clear();
                unused.resize(n, 0.0);
                e.stability(self, &mut unused, &mut damp);
            } else {
                e.stability(self, &mut row, &mut damp);
            }
        }
        (row, damp)
    }

    /// Largest stable substep for [`Substep::Spectral`], s: as [`Self::stability_bound`], with
    /// the springs' part of the stiffness bound replaced by the Lanczos estimate of the largest
    /// eigenvalue of their `M^-1 K` at rest, times `1 + f` for effects that add at most `f K`
    /// ([`Effect::spring_stiffness_factor`]). The ground's and the other effects' stiffness
    /// rows are added as Gershgorin bounds (Weyl: the largest eigenvalue of a sum is at most
    /// the sum of the largest eigenvalues), and explicit damping enters as before.
    fn spectral_bound(&self) -> f32 {
        let n = self.rest_positions.len();
        let (row, damp) = self.gershgorin_rows(false);
        let (mut extra, mut gamma) = (0.0f64, 0.0f64);
        for i in 0..n {
            let inv_m = f64::from(self.inv_mass[i]);
            extra = extra.max(f64::from(row[i].max(0.0)) * inv_m);
            gamma = gamma.max(f64::from(damp[i].max(0.0)) * inv_m);
        }
        let scale = 1.0
            + self
                .effects
                .iter()
                .filter_map(|e| e.spring_stiffness_factor())
                .map(|f| f64::from(f.max(0.0)))
                .sum::<f64>();
        let lambda = crate::spectral::largest_eigenvalue(
            &self.springs,
            &self.stiffness,
            &self.rest_lengths,
            &self.rest_positions,
            &self.inv_mass,
        ) * scale
            + extra;
        if lambda > 0.0 || gamma > 0.0 {
            (4.0 / (gamma + (gamma * gamma + 4.0 * lambda).sqrt())) as f32
        } else {
            f32::INFINITY
        }
    }

    /// Largest eigenvalue of the springs' mass-weighted stiffness `M^-1 K` at positions `x`
    /// (m), 1/s²: a 64-step Lanczos estimate (from below; within 1 % on our scenes) of the
    /// springs' Hessian with the initial rest lengths, compressed springs' negative tension
    /// part left out. The largest stable substep of symplectic Euler for the springs alone is
    /// `2 / sqrt(λ)`; 0 with no springs. Useful to check how far a deformed state is from the
    /// rest state the [`Substep::Spectral`] estimate uses.
    pub fn stiffness_eigenvalue(&self, x: &[Vec3]) -> Result<f64, SimError> {
        let n = self.num_particles();
        if x.len() != n {
            return Err(SimError::LengthMismatch {
                what: "x",
                expected: n,
                got: x.len(),
            });
        }
        if let Some(index) = x.iter().position(|p| !p.is_finite()) {
            return Err(SimError::NonFinite { what: "x", index });
        }
        Ok(crate::spectral::largest_eigenvalue(
            &self.springs,
            &self.stiffness,
            &self.rest_lengths,
            x,
            &self.inv_mass,
        ))
    }

    fn precompute_implicit_terms(&mut self) {
        let dt = self.dt;
        if self.config.dashpot == Dashpot::Explicit {
            self.explicit_damping = self.damping.iter().any(|&c| c > 0.0);
            self.damp_weight.clear();
        } else {
            self.damp_weight = self
                .springs
                .iter()
                .zip(&self.damping)
                .map(|(&[a, b], &c)| {
                    let mu = 1.0 / (self.inv_mass[a as usize] + self.inv_mass[b as usize]);
                    // Two sweeps each multiply an isolated pair's relative axial velocity by
                    // (1 - w / mu); choose w so that together they give the backward-Euler
                    // factor mu / (mu + c dt) of the pair's dashpot.
                    mu * (1.0 - (mu / (mu + c * dt)).sqrt())
                })
                .collect();
        }
        self.has_damping = self.damp_weight.iter().any(|&w| w > 0.0);
        self.ground_normal_factor = self
            .inv_mass
            .iter()
            .map(|im| 1.0 / (1.0 + GROUND_DAMPING * dt * im))
            .collect();
        self.ground_viscous_fraction = self
            .inv_mass
            .iter()
            .map(|im| {
                let r = GROUND_VISCOUS_FRICTION * dt * im;
                r / (1.0 + r)
            })
            .collect();
    }

    /// Number of particles.
    pub fn num_particles(&self) -> usize {
        self.rest_positions.len()
    }
    /// Rest positions (the first frame), m.
    pub fn rest_positions(&self) -> &[Vec3] {
        &self.rest_positions
    }
    /// Gripper assignment per particle (-1: none).
    pub fn held(&self) -> &[i32] {
        &self.held
    }
    /// The fitted parameters.
    pub fn params(&self) -> &SpringParams {
        &self.params
    }
    /// The scene settings.
    pub fn config(&self) -> &SimConfig {
        &self.config
    }
    /// Spring endpoints, in the backbone's internal order (grouped so that no two springs of a
    /// group share a particle; every per-spring slice uses this order).
    pub fn springs(&self) -> &[[u32; 2]] {
        &self.springs
    }
    /// Per particle, whether some spring joins it to another.
    pub fn connected_particles(&self) -> Vec<bool> {
        let mut connected = vec![false; self.num_particles()];
        for [a, b] in &self.springs {
            connected[*a as usize] = true;
            connected[*b as usize] = true;
        }
        connected
    }
    /// Free (not held) particles that no spring connects to anything: they fall freely, which
    /// is almost always a threshold below the particle spacing rather than what a user meant.
    pub fn unconnected_free_particles(&self) -> usize {
        self.connected_particles()
            .iter()
            .zip(&self.held)
            .filter(|(c, h)| !**c && **h < 0)
            .count()
    }
    /// Initial rest length per spring, m.
    pub fn rest_lengths(&self) -> &[f32] {
        &self.rest_lengths
    }
    /// Stiffness per spring, N/m.
    pub fn stiffness(&self) -> &[f32] {
        &self.stiffness
    }
    /// Dashpot coefficient per spring, N·s/m.
    pub fn damping(&self) -> &[f32] {
        &self.damping
    }
    /// Mass per particle, kg.
    pub fn masses(&self) -> &[f32] {
        &self.masses
    }
    /// Largest stable substep, s, from the estimate the substep mode uses (Gershgorin's bound
    /// for [`Substep::Auto`] and [`Substep::Fixed`], the Lanczos estimate for
    /// [`Substep::Spectral`]); infinite when unbounded.
    pub fn stable_dt(&self) -> f32 {
        self.stable_dt
    }
    /// Substeps per model step.
    pub fn substeps(&self) -> u32 {
        self.substeps
    }
    /// Substep length actually used, s.
    pub fn substep_dt(&self) -> f32 {
        self.dt
    }

    /// Internal spring forces (N) at positions `x` (m) and velocities `v` (m/s) with the initial
    /// rest lengths: axial spring `k (l - l0)` plus the dashpot `c d·(v_b - v_a)` in its
    /// continuous form (the integrator applies the dashpot implicitly, docs/physics.md).
    /// Excludes gravity, ground, grippers and effects.
    pub fn spring_forces(&self, x: &[Vec3], v: &[Vec3], out: &mut [Vec3]) -> Result<(), SimError> {
        let n = self.num_particles();
        for (what, len) in [("x", x.len()), ("v", v.len()), ("out", out.len())] {
            if len != n {
                return Err(SimError::LengthMismatch {
                    what,
                    expected: n,
                    got: len,
                });
            }
        }
        out.fill(Vec3::ZERO);
        for (s, &[a, b]) in self.springs.iter().enumerate() {
            let (a, b) = (a as usize, b as usize);
            let d = Vec3A::from(x[b]) - Vec3A::from(x[a]);
            let l = d.length();
            let u = if l > 0.0 { d / l } else { Vec3A::ZERO };
            let rel = u.dot(Vec3A::from(v[b]) - Vec3A::from(v[a]));
            let f = Vec3::from(
                u * (self.stiffness[s] * (l - self.rest_lengths[s]) + self.damping[s] * rel),
            );
            out[a] += f;
            out[b] -= f;
        }
        Ok(())
    }

    /// Elastic energy `sum k (l - l0)^2 / 2` of the springs at positions `x`, J.
    pub fn elastic_energy(&self, x: &[Vec3]) -> Result<f64, SimError> {
        let n = self.num_particles();
        if x.len() != n {
            return Err(SimError::LengthMismatch {
                what: "x",
                expected: n,
                got: x.len(),
            });
        }
        let mut e = 0.0f64;
        for (s, &[a, b]) in self.springs.iter().enumerate() {
            let l = (Vec3A::from(x[b as usize]) - Vec3A::from(x[a as usize])).length();
            let dl = f64::from(l) - f64::from(self.rest_lengths[s]);
            e += 0.5 * f64::from(self.stiffness[s]) * dl * dl;
        }
        Ok(e)
    }

    pub(crate) fn grasp_is_kinematic(&self) -> bool {
        self.config.manipulation == Manipulation::Grasp && !self.compliant_grasp
    }
}

fn check_nonneg(what: &'static str, a: &[f32], positive: bool) -> Result<(), SimError> {
    match a
        .iter()
        .position(|&m| !(m.is_finite() && if positive { m > 0.0 } else { m >= 0.0 }))
    {
        None => Ok(()),
        Some(index) => Err(SimError::InvalidParameter {
            name: what,
            value: f64::from(a[index]),
            reason: if positive {
                "every entry must be finite and > 0"
            } else {
                "every entry must be finite and >= 0"
            },
        }),
    }
}

/// Reorder springs into groups in which no two springs share a particle (greedy edge colouring
/// in acceptance order, then sorted by (colour, a, b)). Inside a group the force scatter and the
/// Gauss–Seidel dashpot sweep have no read-after-write chains, which keeps the CPU pipeline full.
fn color_order(topo: Topology, n: usize) -> (Vec<[u32; 2]>, Vec<f32>) {
    let max_deg = topo.springs_per_particle(n).into_iter().max().unwrap_or(0) as usize;
    let words = (2 * max_deg).div_ceil(64).max(1);
    let mut used = vec![0u64; n * words];
    let mut keyed: Vec<(u32, [u32; 2], f32)> = Vec::with_capacity(topo.len());
    for (&[a, b], &l) in topo.springs.iter().zip(&topo.rest_lengths) {
        let (ua, ub) = (a as usize * words, b as usize * words);
        let mut color = 0u32;
        for w in 0..words {
            let free = !(used[ua + w] | used[ub + w]);
            if free != 0 {
                color = (w * 64) as u32 + free.trailing_zeros();
                break;
            }
        }
        let (w, bit) = (color as usize / 64, 1u64 << (color % 64));
        used[ua + w] |= bit;
        used[ub + w] |= bit;
        keyed.push((color, [a, b], l));
    }
    keyed.sort_unstable_by_key(|&(c, s, _)| (c, s));
    keyed.into_iter().map(|(_, s, l)| (s, l)).unzip()
}
