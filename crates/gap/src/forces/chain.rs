//! Terms on a chain's discrete curvature (a cable's centreline): the stencil they share, and
//! the bending's internal damping, applied implicitly.

use glam::{Vec3, Vec3A};
use springs::{Effect, EffectAdjoint, ModelSetup, SimError};

use super::{bad, check_finite};

/// Consecutive triplets a, b, c along a chain with the inverse rest lengths 1/l₁, 1/l₂ of their
/// two segments: the discrete curvature of each is `(x_c − x_b)/l₂ − (x_b − x_a)/l₁`
/// (dimensionless, zero on a straight chain).
#[derive(Debug, Clone, Default)]
pub(crate) struct ChainStencil {
    pub(crate) triplets: Vec<[u32; 3]>,
    pub(crate) inv_lengths: Vec<[f32; 2]>,
    /// Mean rest segment length l̄, m.
    pub(crate) mean_length: f32,
}

impl ChainStencil {
    /// The stencil of `order` (at least three particles) at rest positions `x`; a chain
    /// collapsed to a point has no curvature to keep: no triplets.
    pub(crate) fn new(x: &[Vec3], order: &[u32]) -> Self {
        let length = |a: u32, b: u32| x[a as usize].distance(x[b as usize]);
        let total: f32 = order.windows(2).map(|w| length(w[0], w[1])).sum();
        let mean = total / (order.len().max(2) - 1) as f32;
        if order.len() < 3 || !(mean.is_finite() && mean > 0.0) {
            return ChainStencil::default();
        }
        let triplets: Vec<[u32; 3]> = order.windows(3).map(|w| [w[0], w[1], w[2]]).collect();
        // A segment of zero rest length would divide by zero; a tenth of the mean stands in.
        let inv = |a: u32, b: u32| 1.0 / length(a, b).max(0.1 * mean).max(f32::MIN_POSITIVE);
        let inv_lengths = triplets
            .iter()
            .map(|t| [inv(t[0], t[1]), inv(t[1], t[2])])
            .collect();
        ChainStencil {
            triplets,
            inv_lengths,
            mean_length: mean,
        }
    }
}

/// Internal damping of a chain's bending: a cable's material damping, which takes the energy
/// out of its fast bending vibrations while barely slowing its slow swing (drag slows both
/// alike). Each three consecutive particles dissipate `½ c |d/dt[(x_c − x_b)/l₂ − (x_b −
/// x_a)/l₁]|²` (the rate of the curvature stencil of [`super::BendingSprings`]), with `c = τ k
/// l̄²` (N·m·s; τ the damping time in s, k the fitted spring stiffness, l̄ the mean rest
/// segment length): bending of relative stiffness κ then loses each mode of frequency ω at the
/// rate ≈ ½ (τ/κ) ω², so the fast modes far more than the slow ones (Rayleigh damping).
///
/// Applied implicitly each substep ([`Effect::damp_velocities`]): `v ← (M + dt C)⁻¹ M v`, a
/// banded solve along the chain, stable at any τ (an explicit force needed substeps up to 30
/// times shorter on the DEFORM cables, session 93, `docs/gap-log.md`). Being linear in the
/// velocities, it conserves momentum and never adds kinetic energy; it also damps a bent
/// chain's rigid rotation, since the curvature stencil turns with it (on DLO1's fitted model
/// the sagging cable's swing about its held ends loses its energy at 190–360 s⁻¹; exempting
/// the chain's rigid motion made DLO1 worse, session 94, `docs/gap-log.md`). Held particles keep
/// their velocities. Chains only: its setup is an error on a model without one
/// ([`springs::ModelSetup::chain`]). The map depends on neither positions nor the per-spring
/// stiffness, so the step's adjoint carries its exact transpose, `M (M + dt C)⁻¹` on the free
/// particles ([`EffectAdjoint::Transposed`]; `cargo xtask refine` takes models with it).
#[derive(Debug, Clone, Default)]
pub struct BendingDamping {
    /// Damping time τ, s (0: none).
    pub damping_time_s: f32,
    order: Vec<u32>,
    /// Per triplet: the curvature stencil's weights on a, b, c (1/m).
    weights: Vec<[f32; 3]>,
    /// c, N·m·s.
    coefficient: f32,
    /// Names this set-up (its order, weights and coefficient) in the per-thread cache of the
    /// factored system ([`implicit_chain_damping`]); 0 before setup.
    id: u64,
}

/// The next [`BendingDamping::id`].
static NEXT_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

impl BendingDamping {
    /// Damping of time `damping_time_s` (s).
    pub fn new(damping_time_s: f32) -> Self {
        BendingDamping {
            damping_time_s,
            ..Default::default()
        }
    }

    /// The damping's map over a substep of `dt` (s), or its transpose, applied to `v` in place.
    fn apply(&self, dt: f32, inv_mass: &[f32], v: &mut [Vec3A], direction: Direction) {
        if self.coefficient <= 0.0 || self.weights.is_empty() {
            return;
        }
        implicit_chain_damping(
            self.id,
            &self.order,
            &self.weights,
            f64::from(self.coefficient) * f64::from(dt),
            inv_mass,
            v,
            direction,
        );
    }
}

impl Effect for BendingDamping {
    fn name(&self) -> &str {
        "bending-damping"
    }

    fn setup(&mut self, model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite(self.name(), &[("damping_time_s", self.damping_time_s)])?;
        let Some(order) = model.chain.filter(|c| c.len() >= 3) else {
            return Err(bad(
                self.name(),
                "needs a chain: the particles' order along a cable (a `chain` dataset)".into(),
            ));
        };
        let stencil = ChainStencil::new(model.rest_positions, order);
        self.order = order.to_vec();
        self.weights = stencil
            .inv_lengths
            .iter()
            .map(|[i1, i2]| [*i1, -(i1 + i2), *i2])
            .collect();
        let l = stencil.mean_length;
        self.coefficient = self.damping_time_s.max(0.0) * model.params.stiffness * l * l;
        self.id = NEXT_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        Ok(())
    }

    fn damp_velocities(&self, dt: f32, inv_mass: &[f32], v: &mut [Vec3A]) {
        self.apply(dt, inv_mass, v, Direction::Forward);
    }

    fn damp_velocities_vjp(&self, dt: f32, inv_mass: &[f32], grad: &mut [Vec3A]) {
        self.apply(dt, inv_mass, grad, Direction::Transpose);
    }

    fn adjoint(&self) -> EffectAdjoint {
        EffectAdjoint::Transposed
    }
}

/// Which map [`implicit_chain_damping`] applies.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Direction {
    /// The damping itself: free particles `v' = A⁻¹ (M v_F − h C_FH v_H)`, held ones `v' = v`,
    /// with `A = M + h C` on the free particles.
    Forward,
    /// Its transpose, for the adjoint: free `g = M A⁻¹ g'_F`, held `g = g'_H − h C_HF A⁻¹ g'_F`.
    Transpose,
}

/// Solves `(M + h Σ_j w_j w_jᵀ) v' = M v` for the particles of `order` (triplet j acts on
/// positions j, j+1, j+2 of it with weights `weights[j]`, `h = c dt`), each coordinate
/// separately; particles with `inv_mass` 0 keep their velocities and enter the others' right
/// side. The matrix is banded (two off-diagonals) and symmetric positive definite: Cholesky,
/// in place. The factor depends only on the set-up `id` names, `h` and the masses (held
/// particles included), which change only when a grasp opens or closes, so each thread keeps
/// its last one and reuses it while those are the same; the right side is built every call.
pub(crate) fn implicit_chain_damping(
    id: u64,
    order: &[u32],
    weights: &[[f32; 3]],
    h: f64,
    inv_mass: &[f32],
    v: &mut [Vec3A],
    direction: Direction,
) {
    thread_local! {
        static CACHE: std::cell::RefCell<Factored> = std::cell::RefCell::default();
    }
    CACHE.with(|c| {
        let mut c = c.borrow_mut();
        let same = c.id == id
            && c.h == h
            && c.inv_mass.len() == order.len()
            && order
                .iter()
                .zip(&c.inv_mass)
                .all(|(&i, m)| inv_mass[i as usize] == *m);
        if !same {
            c.factor(id, order, weights, h, inv_mass);
        }
        match direction {
            Direction::Forward => c.solve(order, v),
            Direction::Transpose => c.solve_transpose(order, v),
        }
    });
}

/// One thread's factored system and what it was factored for.
#[derive(Default)]
struct Factored {
    /// The set-up, `h` and inverse masses (in chain order) of the factor; id 0: none yet.
    id: u64,
    h: f64,
    inv_mass: Vec<f32>,
    /// Row p: the Cholesky factor's entries at columns p−2, p−1, p (a held row: the identity).
    band: Vec<[f64; 3]>,
    /// (free row, held column, h w_r w_c): a held particle's velocity on a free row's right
    /// side.
    held_terms: Vec<(usize, usize, f64)>,
    /// Right sides, then solutions.
    rhs: Vec<[f64; 3]>,
}

impl Factored {
    fn factor(&mut self, id: u64, order: &[u32], weights: &[[f32; 3]], h: f64, inv_mass: &[f32]) {
        let n = order.len();
        self.id = id;
        self.h = h;
        self.inv_mass.clear();
        self.inv_mass
            .extend(order.iter().map(|&i| inv_mass[i as usize]));
        let fixed = |p: usize| self.inv_mass[p] <= 0.0;
        self.band.clear();
        self.band.extend((0..n).map(|p| {
            if fixed(p) {
                [0.0, 0.0, 1.0]
            } else {
                [0.0, 0.0, 1.0 / f64::from(self.inv_mass[p])]
            }
        }));
        self.held_terms.clear();
        // Each triplet's h w wᵀ: into the band between free particles; a held particle's column
        // moves to the free row's right side; a held row stays the identity.
        for (j, w) in weights.iter().enumerate() {
            for r in 0..3 {
                for c in 0..=r {
                    let (p, q) = (j + r, j + c);
                    let value = h * f64::from(w[r]) * f64::from(w[c]);
                    match (fixed(p), fixed(q)) {
                        (false, false) => self.band[p][2 - (r - c)] += value,
                        (false, true) => self.held_terms.push((p, q, value)),
                        (true, false) => self.held_terms.push((q, p, value)),
                        (true, true) => {}
                    }
                }
            }
        }
        // Cholesky in place: row p's entries become L's at columns p−2, p−1, p.
        let band = &mut self.band;
        for p in 0..n {
            for k in 0..3 {
                if p + k < 2 {
                    continue;
                }
                let q = p + k - 2;
                // Σ over the columns m < q that rows p and q of L share (m ≥ p − 2).
                let mut sum = band[p][k];
                for m in p.saturating_sub(2)..q {
                    sum -= band[p][m + 2 - p] * band[q][m + 2 - q];
                }
                band[p][k] = if k == 2 {
                    sum.max(f64::MIN_POSITIVE).sqrt()
                } else {
                    sum / band[q][2]
                };
            }
        }
    }

    /// `v` ← the solution for the right side `M v` (held: `v`), with the factor of [`Self::factor`].
    fn solve(&mut self, order: &[u32], v: &mut [Vec3A]) {
        let vel = |i: u32| {
            let q = v[i as usize];
            [f64::from(q.x), f64::from(q.y), f64::from(q.z)]
        };
        self.rhs.clear();
        self.rhs
            .extend(order.iter().zip(&self.inv_mass).map(|(&i, &im)| {
                if im <= 0.0 {
                    vel(i)
                } else {
                    let m = 1.0 / f64::from(im);
                    vel(i).map(|c| c * m)
                }
            }));
        for &(p, q, value) in &self.held_terms {
            let vq = vel(order[q]);
            for (x, s) in self.rhs[p].iter_mut().zip(vq) {
                *x -= value * s;
            }
        }
        self.substitute();
        for (p, &i) in order.iter().enumerate() {
            if self.inv_mass[p] > 0.0 {
                let [x, y, z] = self.rhs[p];
                v[i as usize] = Vec3A::new(x as f32, y as f32, z as f32);
            }
        }
    }

    /// `grad` ← the transpose of [`Self::solve`]'s map applied to it ([`Direction::Transpose`]).
    fn solve_transpose(&mut self, order: &[u32], grad: &mut [Vec3A]) {
        let g = |i: u32| {
            let q = grad[i as usize];
            [f64::from(q.x), f64::from(q.y), f64::from(q.z)]
        };
        // Held rows are the identity and uncoupled in the factor: they carry g'_H through.
        self.rhs.clear();
        self.rhs.extend(order.iter().map(|&i| g(i)));
        self.substitute();
        let rhs = &self.rhs;
        for &(p, q, value) in &self.held_terms {
            let i = order[q] as usize;
            let y = rhs[p];
            grad[i] -= Vec3A::new(
                (value * y[0]) as f32,
                (value * y[1]) as f32,
                (value * y[2]) as f32,
            );
        }
        for (p, &i) in order.iter().enumerate() {
            let im = self.inv_mass[p];
            if im > 0.0 {
                let m = 1.0 / f64::from(im);
                let [x, y, z] = rhs[p].map(|c| c * m);
                grad[i as usize] = Vec3A::new(x as f32, y as f32, z as f32);
            }
        }
    }

    /// `rhs` ← `(L Lᵀ)⁻¹ rhs` with the factor of [`Self::factor`].
    fn substitute(&mut self) {
        let n = self.band.len();
        let (band, rhs) = (&self.band, &mut self.rhs);
        // L y = b, then Lᵀ x = y.
        for p in 0..n {
            let row = band[p];
            for (k, lk) in row[..2].iter().enumerate() {
                if p + k >= 2 {
                    let yq = rhs[p + k - 2];
                    for (x, s) in rhs[p].iter_mut().zip(yq) {
                        *x -= lk * s;
                    }
                }
            }
            for x in &mut rhs[p] {
                *x /= row[2];
            }
        }
        for p in (0..n).rev() {
            let row = band[p];
            for x in &mut rhs[p] {
                *x /= row[2];
            }
            let xp = rhs[p];
            for (k, lk) in row[..2].iter().enumerate() {
                if p + k >= 2 {
                    for (x, s) in rhs[p + k - 2].iter_mut().zip(xp) {
                        *x -= lk * s;
                    }
                }
            }
        }
    }
}
