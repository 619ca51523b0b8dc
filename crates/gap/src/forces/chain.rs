//! Terms on a chain's discrete curvature (a cable's centreline): the stencil they share, and
//! the bending's internal damping, applied implicitly.

use glam::{Vec3, Vec3A};
use springs::{Effect, ModelSetup, SimError};

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
/// chain's rigid rotation a little (the curvature stencil turns with it). Held particles keep
/// their velocities. Chains only: its setup is an error on a model without one
/// ([`springs::ModelSetup::chain`]). The adjoint takes it as the identity (`HeldFixed`).
#[derive(Debug, Clone, Default)]
pub struct BendingDamping {
    /// Damping time τ, s (0: none).
    pub damping_time_s: f32,
    order: Vec<u32>,
    /// Per triplet: the curvature stencil's weights on a, b, c (1/m).
    weights: Vec<[f32; 3]>,
    /// c, N·m·s.
    coefficient: f32,
}

impl BendingDamping {
    /// Damping of time `damping_time_s` (s).
    pub fn new(damping_time_s: f32) -> Self {
        BendingDamping {
            damping_time_s,
            ..Default::default()
        }
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
        Ok(())
    }

    fn damp_velocities(&self, dt: f32, inv_mass: &[f32], v: &mut [Vec3A]) {
        if self.coefficient <= 0.0 || self.weights.is_empty() {
            return;
        }
        implicit_chain_damping(
            &self.order,
            &self.weights,
            f64::from(self.coefficient) * f64::from(dt),
            inv_mass,
            v,
        );
    }
}

/// Solves `(M + h Σ_j w_j w_jᵀ) v' = M v` for the particles of `order` (triplet j acts on
/// positions j, j+1, j+2 of it with weights `weights[j]`, `h = c dt`), each coordinate
/// separately; particles with `inv_mass` 0 keep their velocities and enter the others' right
/// side. The matrix is banded (two off-diagonals) and symmetric positive definite: Cholesky,
/// in place, in buffers kept per thread (the hook runs every substep).
pub(crate) fn implicit_chain_damping(
    order: &[u32],
    weights: &[[f32; 3]],
    h: f64,
    inv_mass: &[f32],
    v: &mut [Vec3A],
) {
    thread_local! {
        static BUFFERS: std::cell::RefCell<Buffers> = std::cell::RefCell::default();
    }
    BUFFERS.with(|b| solve_banded(order, weights, h, inv_mass, v, &mut b.borrow_mut()));
}

/// The band (row p: the entries at columns p−2, p−1, p, then its Cholesky factor's), the right
/// sides (then the solutions) and which particles are held.
#[derive(Default)]
struct Buffers {
    band: Vec<[f64; 3]>,
    rhs: Vec<[f64; 3]>,
    fixed: Vec<bool>,
}

fn solve_banded(
    order: &[u32],
    weights: &[[f32; 3]],
    h: f64,
    inv_mass: &[f32],
    v: &mut [Vec3A],
    buffers: &mut Buffers,
) {
    let Buffers { band, rhs, fixed } = buffers;
    let n = order.len();
    let vel = |i: u32| {
        let q = v[i as usize];
        [f64::from(q.x), f64::from(q.y), f64::from(q.z)]
    };
    fixed.clear();
    fixed.extend(order.iter().map(|&i| inv_mass[i as usize] <= 0.0));
    band.clear();
    rhs.clear();
    for (p, &i) in order.iter().enumerate() {
        if fixed[p] {
            band.push([0.0, 0.0, 1.0]);
            rhs.push(vel(i));
        } else {
            let m = 1.0 / f64::from(inv_mass[i as usize]);
            band.push([0.0, 0.0, m]);
            rhs.push(vel(i).map(|c| c * m));
        }
    }
    // Each triplet's h w wᵀ: into the band between free particles; a held particle's column
    // moves to the free row's right side; a held row stays the identity.
    for (j, w) in weights.iter().enumerate() {
        for r in 0..3 {
            for c in 0..=r {
                let (p, q) = (j + r, j + c);
                let value = h * f64::from(w[r]) * f64::from(w[c]);
                match (fixed[p], fixed[q]) {
                    (false, false) => band[p][2 - (r - c)] += value,
                    (false, true) => {
                        let vq = vel(order[q]);
                        for (x, s) in rhs[p].iter_mut().zip(vq) {
                            *x -= value * s;
                        }
                    }
                    (true, false) => {
                        let vp = vel(order[p]);
                        for (x, s) in rhs[q].iter_mut().zip(vp) {
                            *x -= value * s;
                        }
                    }
                    (true, true) => {}
                }
            }
        }
    }
    // Cholesky of the band in place: row p's entries become L's at columns p−2, p−1, p.
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
    for (p, &i) in order.iter().enumerate() {
        if !fixed[p] {
            let [x, y, z] = rhs[p];
            v[i as usize] = Vec3A::new(x as f32, y as f32, z as f32);
        }
    }
}
