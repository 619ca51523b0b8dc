//! The candidate effects as [`springs::Effect`]s. Each is a textbook form with one to two
//! parameters; at its neutral value it leaves the backbone unchanged (grasp slip: approaches it).
//! Formulas and ranges are listed in `docs/gap.md`.

use std::any::Any;
use std::sync::Arc;

use glam::{Vec3, Vec3A, Vec4};
use springs::{
    AdjointContext, Backbone, Effect, EffectAdjoint, GROUND_VISCOUS_FRICTION, GroundContact,
    ModelSetup, SimError, SubstepContext,
};

use crate::lanes;

mod chain;
mod twist;
pub use chain::BendingDamping;
use chain::ChainStencil;
pub use twist::Twist;

fn bad(name: &str, message: String) -> SimError {
    SimError::Effect {
        name: name.to_owned(),
        message,
    }
}

fn check_finite(name: &str, values: &[(&str, f32)]) -> Result<(), SimError> {
    for (what, v) in values {
        if !v.is_finite() {
            return Err(bad(name, format!("{what} = {v} is not finite")));
        }
    }
    Ok(())
}

/// Material coordinate of every simulated particle: the tracked particles' own values, and for
/// hidden / interior particles the value of the nearest tracked particle at rest.
fn material_of_all(name: &str, material: &[f32], rest: &[Vec3]) -> Result<Vec<f32>, SimError> {
    let tracked = material.len();
    if rest.len() < tracked || tracked == 0 {
        return Err(bad(
            name,
            format!(
                "{} particles but {tracked} material coordinates",
                rest.len()
            ),
        ));
    }
    Ok(springs::StiffnessField::owners(tracked, rest)
        .into_iter()
        .map(|i| material[i])
        .collect())
}

/// Quadratic drag `F = −c |v| v` per particle (`c = ½ ρ C_d A`, kg/m, equal areas); the
/// impulse per substep is capped at the particle's momentum so drag never reverses a velocity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QuadraticDrag {
    /// `½ ρ C_d A`, kg/m.
    pub coefficient: f32,
}

impl Effect for QuadraticDrag {
    fn name(&self) -> &str {
        "drag"
    }
    fn setup(&mut self, _model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite("drag", &[("coefficient", self.coefficient)])
    }
    fn add_forces(
        &self,
        ctx: &SubstepContext<'_>,
        _s: &mut dyn Any,
        _r: &[f32],
        force: &mut [Vec3A],
    ) {
        let masses = ctx.backbone.masses();
        for ((f, v), m) in force.iter_mut().zip(ctx.v).zip(masses) {
            let speed = v.length();
            if speed > 0.0 {
                let magnitude = (self.coefficient.abs() * speed * speed).min(m * speed / ctx.dt);
                *f -= *v * (magnitude / speed);
            }
        }
    }
    fn adjoint(&self) -> EffectAdjoint {
        EffectAdjoint::Transposed
    }
    fn force_vjp(
        &self,
        ctx: &AdjointContext<'_>,
        lambda: &[Vec3A],
        _gx: &mut [Vec3A],
        grad_v: &mut [Vec3A],
    ) {
        let c = self.coefficient.abs();
        for ((g, (v, l)), m) in grad_v
            .iter_mut()
            .zip(ctx.v.iter().zip(lambda))
            .zip(ctx.masses)
        {
            let speed = v.length();
            if speed == 0.0 {
                continue;
            }
            if c * speed * speed <= m * speed / ctx.dt {
                // f = −c |v| v: ∂f/∂v = −c (|v| I + v vᵀ / |v|), symmetric.
                *g -= c * (speed * *l + *v * (v.dot(*l) / speed));
            } else {
                // Capped: f = −(m / dt) v.
                *g -= *l * (m / ctx.dt);
            }
        }
    }
}

/// Per-spring stiffness `k_s = k exp(a ū_s) exp(e λ̄_s − |e|)`, `ū_s` the mean material
/// coordinate of the spring's ends (`u ∈ [−1, 1]` along the rest shape's principal axis) and
/// `λ̄_s` their mean grasp lag (`λ ∈ [−1, 1]`, [`crate::grasp_lag`]; the second factor only
/// when the frame has one). Soft material sags and trails the grippers wherever it sits on
/// the object, which no axis can say (the sloth's limbs around its head, session 79).
#[derive(Debug, Clone)]
pub struct StiffnessGradient {
    /// Log-stiffness slope along the axis (0: uniform).
    pub slope: f32,
    /// Material coordinate of each tracked particle.
    pub material: Arc<Vec<f32>>,
    /// Anchored log-stiffness slope `e` along the grasp lag: each spring's factor is also
    /// `exp(e λ̄_s − |e|)`, so the end of the lag coordinate that stays stiffest keeps `k`
    /// (0: no lag term).
    pub lag_slope: f32,
    /// Grasp-lag coordinate λ of each tracked particle in [−1, 1] (`None`: no lag term).
    pub lag: Option<Arc<Vec<f32>>>,
}

impl Effect for StiffnessGradient {
    fn name(&self) -> &str {
        // The candidate it stands for: `stiffness-lag` carries the lag coordinate.
        if self.lag.is_some() || self.lag_slope != 0.0 {
            "stiffness-lag"
        } else {
            "stiffness-heterogeneity"
        }
    }
    fn setup(&mut self, model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite(
            self.name(),
            &[("slope", self.slope), ("lag slope", self.lag_slope)],
        )?;
        let u = material_of_all(self.name(), &self.material, model.rest_positions)?;
        for (k, [a, b]) in model.stiffness.iter_mut().zip(model.springs) {
            *k *= (self.slope * 0.5 * (u[*a as usize] + u[*b as usize])).exp();
        }
        if let Some(lag) = self.lag.as_deref().filter(|_| self.lag_slope != 0.0) {
            let l = material_of_all(self.name(), lag, model.rest_positions)?;
            let e = self.lag_slope;
            for (k, [a, b]) in model.stiffness.iter_mut().zip(model.springs) {
                *k *= (e * 0.5 * (l[*a as usize] + l[*b as usize]) - e.abs()).exp();
            }
        }
        Ok(())
    }
    fn adjoint(&self) -> EffectAdjoint {
        EffectAdjoint::SetupOnly
    }
}

/// Mass per particle `m_i ∝ exp(b u_i)` along the principal axis, normalised to mean 1 so the
/// total mass is unchanged.
#[derive(Debug, Clone)]
pub struct MassGradient {
    /// Log-mass slope along the axis (0: uniform).
    pub slope: f32,
    /// Material coordinate of each tracked particle.
    pub material: Arc<Vec<f32>>,
}

impl Effect for MassGradient {
    fn name(&self) -> &str {
        "mass-distribution"
    }
    fn setup(&mut self, model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite(self.name(), &[("slope", self.slope)])?;
        let u = material_of_all(self.name(), &self.material, model.rest_positions)?;
        let w: Vec<f32> = u.iter().map(|u| (self.slope * u).exp()).collect();
        let mean = w.iter().sum::<f32>() / w.len().max(1) as f32;
        for (m, w) in model.masses.iter_mut().zip(&w) {
            *m *= w / mean;
        }
        Ok(())
    }
    fn adjoint(&self) -> EffectAdjoint {
        EffectAdjoint::SetupOnly
    }
}

/// Strain-dependent spring term: in tension the axial force becomes
/// `k Δl (1 + β min(ε, ε_max)²)`, in compression `k Δl (1 − γ)` (`ε = Δl / l₀`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StrainStiffening {
    /// Stiffening coefficient β (0: linear).
    pub beta: f32,
    /// Compression softening γ in [0, 1) (0: symmetric).
    pub gamma: f32,
}

/// Strain at which stiffening saturates (keeps the stability bound finite).
pub const STIFFENING_MAX_STRAIN: f32 = 0.05;

impl Effect for StrainStiffening {
    fn name(&self) -> &str {
        "nonlinear-elasticity"
    }
    fn setup(&mut self, _model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite(self.name(), &[("beta", self.beta), ("gamma", self.gamma)])?;
        if self.beta < 0.0 || !(0.0..1.0).contains(&self.gamma) {
            return Err(bad(self.name(), "need beta >= 0 and 0 <= gamma < 1".into()));
        }
        Ok(())
    }
    fn stability(&self, backbone: &Backbone, row: &mut [f32], _damping: &mut [f32]) {
        let factor = self.tangent_factor();
        for (k, [a, b]) in backbone.stiffness().iter().zip(backbone.springs()) {
            row[*a as usize] += 2.0 * factor * k;
            row[*b as usize] += 2.0 * factor * k;
        }
    }
    fn spring_stiffness_factor(&self) -> Option<f32> {
        Some(self.tangent_factor().max(0.0))
    }
    fn add_forces(
        &self,
        ctx: &SubstepContext<'_>,
        _s: &mut dyn Any,
        rest: &[f32],
        force: &mut [Vec3A],
    ) {
        let bb = ctx.backbone;
        let (springs, stiffness) = (bb.springs(), bb.stiffness());
        let blocks = springs.len().min(rest.len()) / 4 * 4;
        for ((ab, k), l0) in springs[..blocks]
            .chunks_exact(4)
            .zip(stiffness[..blocks].chunks_exact(4))
            .zip(rest[..blocks].chunks_exact(4))
        {
            let (d, l) = lanes::geometry(ctx.x, ab);
            let l0 = Vec4::from_slice(l0);
            let dl = l - l0;
            let strain = dl / l0;
            // Both branches in lanes, then a select: the sign of the strain is close to a
            // coin flip from spring to spring, and a branch per spring mispredicted half the
            // time (this is what made the term cost twice the backbone's elastic pass).
            let k = Vec4::from_slice(k);
            let e = strain.min(Vec4::splat(STIFFENING_MAX_STRAIN));
            let tension = k * dl * self.beta * e * e;
            let compression = -k * dl * self.gamma;
            let extra = Vec4::select(strain.cmpgt(Vec4::ZERO), tension, compression);
            let scale = extra / l;
            for (j, [a, b]) in ab.iter().enumerate() {
                if l[j] <= 0.0 || l0[j] <= 0.0 {
                    continue;
                }
                let f = lanes::lane(&d, j) * scale[j];
                force[*a as usize] += f;
                force[*b as usize] -= f;
            }
        }
        for ((k, [a, b]), l0) in stiffness[blocks..]
            .iter()
            .zip(&springs[blocks..])
            .zip(&rest[blocks..])
        {
            let (a, b) = (*a as usize, *b as usize);
            let d = ctx.x[b] - ctx.x[a];
            let l = d.length();
            if l <= 0.0 || *l0 <= 0.0 {
                continue;
            }
            let dl = l - l0;
            let f = d * (self.extra_force(*k, dl, dl / l0) / l);
            force[a] += f;
            force[b] -= f;
        }
    }
}

impl StrainStiffening {
    /// The extra axial tangent stiffness as a fraction of the spring's own: at most
    /// `3 β ε_max²` in tension, negative (softening) in compression.
    fn tangent_factor(&self) -> f32 {
        3.0 * self.beta * STIFFENING_MAX_STRAIN * STIFFENING_MAX_STRAIN
    }

    /// The axial force beyond the linear spring's, N (tension positive), of a spring of
    /// stiffness `k` stretched by `dl` (m), strain `dl / l₀`.
    #[inline(always)]
    fn extra_force(&self, k: f32, dl: f32, strain: f32) -> f32 {
        if strain > 0.0 {
            let e = strain.min(STIFFENING_MAX_STRAIN);
            k * dl * self.beta * e * e
        } else {
            -k * dl * self.gamma
        }
    }
}

/// Bending springs: extra springs of stiffness `κ k` between particles whose rest distance is
/// in `(threshold, 2 threshold]` (the second ring of neighbours), at most
/// [`BENDING_PER_PARTICLE`] nearest per particle.
///
/// On a chain (the model knows its particles' order along a centreline,
/// [`springs::ModelSetup::chain`]: a DEFORM cable's markers and the particles between them)
/// bending acts on the centreline's curvature instead: each three consecutive particles a, b,
/// c with rest segment lengths l₁, l₂ store `E = ½ k_b |(x_c − x_b)/l₂ − (x_b − x_a)/l₁|²`,
/// zero for a straight chain, with `k_b = κ k l̄²` (l̄ the mean rest segment length), a
/// discrete form of `½ EI κ²` (the bending energy of an elastic rod, as in discrete elastic
/// rods). Springs to a second ring bend a nearly straight chain only to second order (the
/// chord of a slightly bent pair barely shortens) and pull each episode's chain towards its
/// own first frame; the curvature form is linear in the bend and straight at rest, as a cable
/// is (session 92, `docs/gap-log.md`). Each triplet's `k_b` follows a stiffness field set up
/// before it by its middle particle's factor; it stays linear under a spring law.
///
/// A bending spring follows the material at its ends: `k` is scaled by the geometric mean of
/// its two particles' factors, each the mean factor (spring stiffness over the fitted
/// stiffness) of the backbone's springs at that particle when this effect is set up. So a
/// [`StiffnessGradient`] set up before it scales the bending of its soft and stiff parts as it
/// scales their springs, as a material field does (the reference world scales its bending
/// stencils with its links; until session 79 the bending springs ignored the field); without
/// one every factor is exactly 1. Models built from [`crate::Candidate`]s (the refits,
/// [`crate::backbone_options`]) set the field up first; `refine`'s per-particle field
/// (`springs::StiffnessField`) comes last, so refined models keep the bending they were
/// fitted with.
///
/// They follow the composition's spring law too: with a [`StrainStiffening`] (the
/// `nonlinear-elasticity` candidate) in the same composition, each bending spring stiffens in
/// tension and softens in compression as the backbone's springs do (until session 80 they
/// stayed linear, and held a body that the world lets give way in compression).
#[derive(Debug, Clone, Default)]
pub struct BendingSprings {
    /// Relative stiffness κ of the bending springs (0: none).
    pub relative_stiffness: f32,
    /// The spring law of the composition, when it has one (`None`: linear springs).
    pub stiffening: Option<StrainStiffening>,
    pairs: Vec<[u32; 2]>,
    rest: Vec<f32>,
    /// Per pair, N/m.
    stiffness: Vec<f32>,
    /// On a chain: consecutive triplets along it, the inverse rest lengths of their two
    /// segments (1/m) and their bending stiffness `κ k l̄²` (N·m).
    triplets: Vec<[u32; 3]>,
    inv_lengths: Vec<[f32; 2]>,
    curvature_stiffness: Vec<f32>,
}

/// Most bending springs started from one particle.
pub const BENDING_PER_PARTICLE: usize = 6;

impl BendingSprings {
    /// Bending springs with relative stiffness κ.
    pub fn new(relative_stiffness: f32) -> Self {
        BendingSprings {
            relative_stiffness,
            ..Default::default()
        }
    }

    /// The same springs following the spring law `stiffening`.
    pub fn with_stiffening(mut self, stiffening: StrainStiffening) -> Self {
        self.stiffening = Some(stiffening);
        self
    }

    /// The curvature form along `order` (at least three particles).
    fn set_up_chain(&mut self, model: &ModelSetup<'_>, order: &[u32]) {
        let factors = particle_factors(model);
        self.pairs.clear();
        self.rest.clear();
        self.stiffness.clear();
        let stencil = ChainStencil::new(model.rest_positions, order);
        let mean = stencil.mean_length;
        self.triplets = stencil.triplets;
        self.inv_lengths = stencil.inv_lengths;
        let base = self.relative_stiffness.max(0.0) * model.params.stiffness * mean * mean;
        self.curvature_stiffness = self
            .triplets
            .iter()
            .map(|t| base * factors[t[1] as usize])
            .collect();
    }

    /// Adds the curvature form's forces at positions `x` (or its transpose applied to `x`).
    fn curvature_forces(&self, x: &[Vec3A], out: &mut [Vec3A]) {
        for ((t, [i1, i2]), k) in self
            .triplets
            .iter()
            .zip(&self.inv_lengths)
            .zip(&self.curvature_stiffness)
        {
            let (a, b, c) = (t[0] as usize, t[1] as usize, t[2] as usize);
            let d = ((x[c] - x[b]) * *i2 - (x[b] - x[a]) * *i1) * *k;
            out[a] -= d * *i1;
            out[b] += d * (i1 + i2);
            out[c] -= d * *i2;
        }
    }
}

/// Each particle's mean factor of the springs at it (spring stiffness over the fitted
/// stiffness; unchanged springs give exactly 1, a sum of ones over their count; 1 at a
/// particle without springs).
fn particle_factors(model: &ModelSetup<'_>) -> Vec<f32> {
    let n = model.rest_positions.len();
    let k0 = model.params.stiffness;
    let (mut sum, mut count) = (vec![0.0f32; n], vec![0u32; n]);
    for (k, [a, b]) in model.stiffness.iter().zip(model.springs) {
        for i in [*a as usize, *b as usize] {
            sum[i] += if k0 > 0.0 { *k / k0 } else { 1.0 };
            count[i] += 1;
        }
    }
    sum.iter()
        .zip(&count)
        .map(|(s, &c)| if c == 0 { 1.0 } else { s / c as f32 })
        .collect()
}

impl Effect for BendingSprings {
    fn name(&self) -> &str {
        "bending"
    }
    fn setup(&mut self, model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite(
            self.name(),
            &[("relative_stiffness", self.relative_stiffness)],
        )?;
        let x = model.rest_positions;
        if let Some(order) = model.chain.filter(|c| c.len() >= 3) {
            self.set_up_chain(model, order);
            return Ok(());
        }
        let r = model.params.threshold;
        let mut pairs = std::collections::BTreeSet::new();
        for (i, p) in x.iter().enumerate() {
            let mut near: Vec<(f32, usize)> = x
                .iter()
                .enumerate()
                .map(|(j, q)| (p.distance(*q), j))
                .filter(|(d, _)| *d > r && *d <= 2.0 * r)
                .collect();
            near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            for (_, j) in near.into_iter().take(BENDING_PER_PARTICLE) {
                pairs.insert([i.min(j) as u32, i.max(j) as u32]);
            }
        }
        self.pairs = pairs.into_iter().collect();
        self.rest = self
            .pairs
            .iter()
            .map(|[a, b]| x[*a as usize].distance(x[*b as usize]))
            .collect();
        let factors = particle_factors(model);
        let base = self.relative_stiffness.max(0.0) * model.params.stiffness;
        self.stiffness = self
            .pairs
            .iter()
            .map(|[a, b]| base * (factors[*a as usize] * factors[*b as usize]).sqrt())
            .collect();
        self.triplets.clear();
        self.inv_lengths.clear();
        self.curvature_stiffness.clear();
        Ok(())
    }
    fn stability(&self, _backbone: &Backbone, row: &mut [f32], _damping: &mut [f32]) {
        let factor = 1.0 + self.stiffening.map_or(0.0, |s| s.tangent_factor().max(0.0));
        for ([a, b], k) in self.pairs.iter().zip(&self.stiffness) {
            row[*a as usize] += 2.0 * factor * k;
            row[*b as usize] += 2.0 * factor * k;
        }
        // The curvature energy's Hessian rows, k_b |∂D/∂x_i| Σ_j |∂D/∂x_j| (Gershgorin).
        for ((t, [i1, i2]), k) in self
            .triplets
            .iter()
            .zip(&self.inv_lengths)
            .zip(&self.curvature_stiffness)
        {
            let sum = 2.0 * (i1 + i2);
            row[t[0] as usize] += k * i1 * sum;
            row[t[1] as usize] += k * (i1 + i2) * sum;
            row[t[2] as usize] += k * i2 * sum;
        }
    }
    fn add_forces(
        &self,
        ctx: &SubstepContext<'_>,
        _s: &mut dyn Any,
        _r: &[f32],
        force: &mut [Vec3A],
    ) {
        if self.relative_stiffness <= 0.0 {
            return;
        }
        self.curvature_forces(ctx.x, force);
        for (([a, b], l0), k) in self.pairs.iter().zip(&self.rest).zip(&self.stiffness) {
            let (a, b) = (*a as usize, *b as usize);
            let d = ctx.x[b] - ctx.x[a];
            let l = d.length();
            if l > 0.0 {
                let dl = l - l0;
                let extra = match &self.stiffening {
                    Some(s) if *l0 > 0.0 => s.extra_force(*k, dl, dl / l0),
                    _ => 0.0,
                };
                let f = d * ((k * dl + extra) / l);
                force[a] += f;
                force[b] -= f;
            }
        }
    }
    fn adjoint(&self) -> EffectAdjoint {
        // `force_vjp` is the linear springs' transpose; a spring law's Jacobian differs.
        match self.stiffening {
            None => EffectAdjoint::Transposed,
            Some(_) => EffectAdjoint::HeldFixed,
        }
    }
    fn force_vjp(
        &self,
        ctx: &AdjointContext<'_>,
        lambda: &[Vec3A],
        grad_x: &mut [Vec3A],
        _gv: &mut [Vec3A],
    ) {
        if self.relative_stiffness <= 0.0 {
            return;
        }
        // The curvature forces are linear in x with a symmetric Jacobian (−k_b JᵀJ): its
        // transpose applied to λ is the same stencil applied to λ.
        self.curvature_forces(lambda, grad_x);
        for (([a, b], l0), k) in self.pairs.iter().zip(&self.rest).zip(&self.stiffness) {
            let (a, b) = (*a as usize, *b as usize);
            let d = ctx.x[b] - ctx.x[a];
            let l = d.length();
            if l > 0.0 {
                // f_a = k (l − l0) u = −f_b, u = d / l, d = x_b − x_a; its Jacobian in d,
                // k [(1 − l0/l)(I − u uᵀ) + u uᵀ], is symmetric.
                let u = d / l;
                let dl = lambda[b] - lambda[a];
                let along = u * u.dot(dl);
                let gd = *k * ((1.0 - l0 / l) * (dl - along) + along);
                grad_x[a] += gd;
                grad_x[b] -= gd;
            }
        }
    }
}

/// Static/kinetic ground friction: a particle whose tangential speed after the force update is
/// below `(μ + Δ) N dt / m` sticks (speed 0); otherwise the backbone's law (viscous, capped by
/// kinetic Coulomb with the backbone's μ) applies. Δ = μ_s − μ_k ≥ 0; Δ = 0 is the backbone.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StickSlipFriction {
    /// Static excess Δ = μ_s − μ_k.
    pub static_excess: f32,
}

impl Effect for StickSlipFriction {
    fn name(&self) -> &str {
        "friction"
    }
    fn setup(&mut self, _model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite(self.name(), &[("static_excess", self.static_excess)])
    }
    fn replaces_ground_friction(&self) -> bool {
        true
    }
    fn ground_friction(&self, c: &GroundContact) -> Vec3A {
        let speed = c.tangential_velocity.length();
        if speed == 0.0 {
            return c.tangential_velocity;
        }
        let per_mu = c.normal_force * c.dt / c.mass;
        if self.static_excess > 0.0 && speed <= (c.mu + self.static_excess) * per_mu {
            return Vec3A::ZERO;
        }
        let r = GROUND_VISCOUS_FRICTION * c.dt / c.mass;
        let dec = (speed * r / (1.0 + r)).min(c.mu * per_mu);
        c.tangential_velocity * (1.0 - dec / speed)
    }
}

/// Plastic creep: when a spring's strain exceeds the yield strain ε_y, its rest length flows
/// towards the current length at rate `dl₀/dt = η (|ε| − ε_y) sign(ε) l₀`, never past the
/// yield surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlasticCreep {
    /// Yield strain ε_y.
    pub yield_strain: f32,
    /// Flow rate η, 1/s (0: elastic).
    pub rate: f32,
}

impl Effect for PlasticCreep {
    fn name(&self) -> &str {
        "plasticity"
    }
    fn setup(&mut self, _model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite(
            self.name(),
            &[("yield_strain", self.yield_strain), ("rate", self.rate)],
        )
    }
    fn end_substep(&self, ctx: &SubstepContext<'_>, _s: &mut dyn Any, rest: &mut [f32]) {
        if self.rate <= 0.0 {
            return;
        }
        let springs = ctx.backbone.springs();
        let blocks = springs.len().min(rest.len()) / 4 * 4;
        for (ab, l0) in springs[..blocks]
            .chunks_exact(4)
            .zip(rest[..blocks].chunks_exact_mut(4))
        {
            // |x_a − x_b| = |x_b − x_a| exactly: the differences only change sign.
            let (_, l) = lanes::geometry(ctx.x, ab);
            let rest4 = Vec4::from_slice(l0);
            let strain = (l - rest4) / rest4;
            // [`Self::creep`] in lanes, both outcomes then a select (no branch per spring).
            let sign = strain.signum();
            let excess = strain.abs() - self.yield_strain;
            let target = l / (Vec4::ONE + self.yield_strain * sign);
            let step = Vec4::splat(self.rate * ctx.dt) * excess * rest4;
            // `f32::min` keeps `step` when the other side is NaN; `_mm_min_ps(a, b)` returns
            // `b` then, hence the operand order.
            let step = (target - rest4).abs().min(step);
            let creeps = excess.cmpgt(Vec4::ZERO) & rest4.cmpgt(Vec4::ZERO);
            Vec4::select(creeps, rest4 + step * sign, rest4).write_to_slice(l0);
        }
        for ([a, b], l0) in springs[blocks..].iter().zip(rest[blocks..].iter_mut()) {
            let l = ctx.x[*a as usize].distance(ctx.x[*b as usize]);
            let strain = (l - *l0) / *l0;
            self.creep(ctx.dt, l, strain, l0);
        }
    }
}

impl PlasticCreep {
    /// One substep of creep of the rest length `l0` of a spring of length `l`, strain
    /// `(l − l₀) / l₀`.
    #[inline(always)]
    fn creep(&self, dt: f32, l: f32, strain: f32, l0: &mut f32) {
        if *l0 <= 0.0 {
            return;
        }
        let excess = strain.abs() - self.yield_strain;
        if excess > 0.0 {
            // Stop at the yield surface so the update cannot overshoot.
            let target = l / (1.0 + self.yield_strain * strain.signum());
            let step = (self.rate * dt * excess * *l0).min((target - *l0).abs());
            *l0 += step * strain.signum();
        }
    }
}

/// Actuation delay: the true gripper follows the recorded one `τ` model steps late (linear
/// interpolation between recorded frames; before the first frame it stays there).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ActuationLag {
    /// Delay τ in model steps (fractional; 0: none).
    pub steps: f32,
}

#[derive(Default)]
struct LagState {
    positions: Vec<Vec<Vec3>>,
    closed: Vec<Vec<bool>>,
}

impl LagState {
    fn at(&self, s: f32) -> Vec<Vec3> {
        let last = self.positions.len() - 1;
        let s = s.clamp(0.0, last as f32);
        let i = (s.floor() as usize).min(last);
        let j = (i + 1).min(last);
        let w = s - i as f32;
        self.positions[i]
            .iter()
            .zip(&self.positions[j])
            .map(|(a, b)| a.lerp(*b, w))
            .collect()
    }
}

impl Effect for ActuationLag {
    fn name(&self) -> &str {
        "actuation-delay"
    }
    fn setup(&mut self, _model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite(self.name(), &[("steps", self.steps)])?;
        if self.steps < 0.0 {
            return Err(bad(self.name(), "delay must be >= 0".into()));
        }
        Ok(())
    }
    fn new_state(&self, _backbone: &Backbone) -> Box<dyn Any + Send> {
        Box::new(LagState::default())
    }
    fn adjust_actions(
        &self,
        state: &mut dyn Any,
        from: &mut [Vec3],
        to: &mut [Vec3],
        closed: &mut [bool],
    ) {
        let Some(st) = state.downcast_mut::<LagState>() else {
            return;
        };
        if st.positions.is_empty() {
            st.positions.push(from.to_vec());
        }
        st.positions.push(to.to_vec());
        st.closed.push(closed.to_vec());
        if self.steps == 0.0 {
            return;
        }
        let t = (st.positions.len() - 2) as f32;
        from.copy_from_slice(&st.at(t - self.steps));
        to.copy_from_slice(&st.at(t + 1.0 - self.steps));
        let c = ((t - self.steps).round().max(0.0) as usize).min(st.closed.len() - 1);
        closed.copy_from_slice(&st.closed[c]);
    }
}

/// Compliant, slipping grasp: a held particle is tied to its grasp point on the closed gripper
/// by a spring `k_g` with damping `2 √(k_g m)` (critical); when the spring force exceeds
/// `F_max` the grasp point slides so the force stays at `F_max`.
///
/// Both are given relative to the object, so that one starting guess suits a 5 g sheet and a
/// 250 g toy: with `W` the model's total weight (Σ m × 9.81 m/s²) shared by its `n` held
/// particles, `k_g = relative_stiffness · W / (1 cm · n)` (at 1 the grasp stretches 1 cm
/// under the object's weight), capped at 10⁶ N/m per particle (a kinematic grasp for every
/// object here), and `F_max = relative_slip_force · W / n` (at 1 the grasp slips at the
/// object's weight). Resolved in [`Effect::setup`].
///
/// A grasp point is set when the grasp first acts in a rollout. Rollouts start in the middle
/// of recordings, where a compliant grasp holding a lifted object is already stretched by the
/// weight it carries; starting it unloaded would make the object drop by that stretch. So the
/// grasp starts carrying the weight of the particles not touching the ground (those more than
/// 1 cm above it rest on the grasp, the others on the ground), shared by the held particles and
/// at most `F_max` each: the grasp point starts that stretch above its particle, against
/// gravity. This is a static estimate from heights alone: a hanging object's grasp starts
/// with its whole weight, and a thick object lying on the ground with the weight of its
/// particles higher than 1 cm, which the ground in fact carries (`docs/gap.md`, Candidates).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SlippingGrasp {
    /// Grasp stiffness relative to the object's weight per centimetre (dimensionless).
    pub relative_stiffness: f32,
    /// Slip force relative to the object's weight (dimensionless).
    pub relative_slip_force: f32,
    /// Resolved grasp spring stiffness per held particle, N/m.
    stiffness: f32,
    /// Resolved slip force per held particle, N.
    max_force: f32,
    /// The model's weight per held particle, N.
    weight_share: f32,
}

/// Height above the ground below which a particle counts as touching it, m.
const CONTACT_MARGIN_M: f32 = 0.01;

/// Per-particle grasp stiffness beyond which the grasp is kinematic for every object here, N/m.
const MAX_GRASP_STIFFNESS_N_PER_M: f32 = 1e6;

impl SlippingGrasp {
    /// A grasp with the given relative stiffness and slip force (see the type's docs).
    pub fn new(relative_stiffness: f32, relative_slip_force: f32) -> Self {
        SlippingGrasp {
            relative_stiffness,
            relative_slip_force,
            stiffness: 0.0,
            max_force: 0.0,
            weight_share: 0.0,
        }
    }
}

struct GraspState {
    /// Grasp point of each particle relative to its gripper (None: not attached).
    offsets: Vec<Option<Vec3A>>,
}

impl SlippingGrasp {
    fn damping(&self, mass: f32) -> f32 {
        2.0 * (self.stiffness * mass).sqrt()
    }

    /// Where a newly attached particle's grasp point sits relative to the particle: above it
    /// by the stretch that carries its share of the weight off the ground.
    fn initial_stretch(&self, ctx: &SubstepContext<'_>) -> Vec3A {
        let config = ctx.backbone.config();
        let gravity = Vec3A::from(config.gravity);
        if gravity.length_squared() == 0.0 {
            return Vec3A::ZERO;
        }
        // Particles touching the ground rest on it; the grasp carries the others.
        let masses = ctx.backbone.masses();
        let fraction = match config.ground_z {
            Some(h) => {
                let free: f32 = ctx
                    .x
                    .iter()
                    .zip(masses)
                    .filter(|(p, _)| p.z >= h + CONTACT_MARGIN_M)
                    .map(|(_, m)| *m)
                    .sum();
                free / masses.iter().sum::<f32>()
            }
            None => 1.0,
        };
        -gravity.normalize() * ((fraction * self.weight_share).min(self.max_force) / self.stiffness)
    }
}

impl Effect for SlippingGrasp {
    fn name(&self) -> &str {
        "grasp-slip"
    }
    fn setup(&mut self, model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite(
            self.name(),
            &[
                ("relative_stiffness", self.relative_stiffness),
                ("relative_slip_force", self.relative_slip_force),
            ],
        )?;
        if self.relative_stiffness <= 0.0 || self.relative_slip_force <= 0.0 {
            return Err(bad(
                self.name(),
                "relative stiffness and slip force must be > 0".into(),
            ));
        }
        let held = model.held.iter().filter(|h| **h >= 0).count().max(1) as f32;
        let weight_share = model.masses.iter().sum::<f32>() * 9.81 / held;
        self.stiffness =
            (self.relative_stiffness * weight_share / 0.01).min(MAX_GRASP_STIFFNESS_N_PER_M);
        self.max_force = self.relative_slip_force * weight_share;
        self.weight_share = weight_share;
        if !(self.stiffness > 0.0 && self.max_force > 0.0 && self.max_force.is_finite()) {
            return Err(bad(
                self.name(),
                format!(
                    "grasp resolves to {} N/m and {} N per held particle",
                    self.stiffness, self.max_force
                ),
            ));
        }
        Ok(())
    }
    fn compliant_grasp(&self) -> bool {
        true
    }
    fn stability(&self, backbone: &Backbone, row: &mut [f32], damping: &mut [f32]) {
        for (i, h) in backbone.held().iter().enumerate() {
            if *h >= 0 {
                row[i] += self.stiffness;
                damping[i] += self.damping(backbone.masses()[i]);
            }
        }
    }
    fn new_state(&self, backbone: &Backbone) -> Box<dyn Any + Send> {
        Box::new(GraspState {
            offsets: vec![None; backbone.num_particles()],
        })
    }
    fn add_forces(
        &self,
        ctx: &SubstepContext<'_>,
        state: &mut dyn Any,
        _r: &[f32],
        force: &mut [Vec3A],
    ) {
        let Some(st) = state.downcast_mut::<GraspState>() else {
            return;
        };
        let bb = ctx.backbone;
        // Computed at most once per substep, and only when a particle attaches.
        let mut stretch = None;
        for (i, h) in bb.held().iter().enumerate() {
            let g = *h as usize;
            if *h < 0 || g >= ctx.grippers.len() {
                continue;
            }
            if !ctx.closed[g] {
                st.offsets[i] = None;
                continue;
            }
            let grip = Vec3A::from(ctx.grippers[g]);
            let offset = *st.offsets[i].get_or_insert_with(|| {
                ctx.x[i] - grip + *stretch.get_or_insert_with(|| self.initial_stretch(ctx))
            });
            let d = grip + offset - ctx.x[i];
            let spring = d * self.stiffness;
            let magnitude = spring.length();
            let spring = if magnitude > self.max_force {
                // Slip: move the grasp point so the spring carries exactly F_max.
                let reach = d * (self.max_force / magnitude);
                st.offsets[i] = Some(ctx.x[i] + reach - grip);
                reach * self.stiffness
            } else {
                spring
            };
            let rel = Vec3A::from(ctx.gripper_velocities[g]) - ctx.v[i];
            force[i] += spring + rel * self.damping(bb.masses()[i]);
        }
    }
}

/// Not a library effect: a generic external acceleration field, first order in position about a
/// point `c` and confined to a Gaussian window of radius `w` around it, plus a workless
/// velocity term, `a(x, v) = (a₀ + g (x − c)) exp(−|x − c|² / 2w²) + v × b` (m/s²). It probes
/// whether a significant, learnable gap remains that no named effect explains. A wide window
/// (`w` of metres) makes it the plain first-order field about `c`; a narrow one, a force
/// confined to one region of the workspace (an unmodelled support, an air jet, a field
/// source), which a global first-order field cannot follow when the object moves through the
/// region and out again.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExternalField {
    /// Acceleration a₀ at the centre, m/s².
    pub uniform: Vec3,
    /// Isotropic gradient g, 1/s² (negative: attraction towards `centre`).
    pub gradient: f32,
    /// Expansion point and window centre c, m.
    pub centre: Vec3,
    /// Window radius w, m (> 0).
    pub width: f32,
    /// Gyroscopic vector b, 1/s: an acceleration `v × b` on every particle, not windowed. It
    /// turns each velocity about `b` without changing its length (no work), the one part of a
    /// first-order velocity field the backbone's own damping does not already give; a frame
    /// turning at Ω about an axis ê gives b = 2Ω ê (Coriolis). Zero: a position field alone.
    pub gyro: Vec3,
}

/// One substep's turn of the velocity under `dv/dt = v × b`: the unit axis b̂ and the sine
/// and cosine of the angle |b| dt (`None` when b = 0).
struct GyroTurn {
    axis: Vec3A,
    sin: f32,
    cos: f32,
}

impl GyroTurn {
    fn new(gyro: Vec3, dt: f32) -> Option<Self> {
        let rate = gyro.length();
        if rate == 0.0 {
            return None;
        }
        let (sin, cos) = (rate * dt).sin_cos();
        Some(GyroTurn {
            axis: Vec3A::from(gyro) / rate,
            sin,
            cos,
        })
    }

    /// The velocity change `R v − v`, where R turns `v` exactly by |b| dt about −b̂: applied
    /// as a force it conserves speed however large |b| dt is, where `m v × b` itself would
    /// add energy each substep.
    fn change(&self, v: Vec3A) -> Vec3A {
        let across = v - self.axis * v.dot(self.axis);
        across * (self.cos - 1.0) + v.cross(self.axis) * self.sin
    }

    /// The transpose of [`GyroTurn::change`] (a linear map of v) applied to `l`.
    fn change_transposed(&self, l: Vec3A) -> Vec3A {
        let across = l - self.axis * l.dot(self.axis);
        across * (self.cos - 1.0) + self.axis.cross(l) * self.sin
    }
}

impl Effect for ExternalField {
    fn name(&self) -> &str {
        "external-field"
    }
    fn setup(&mut self, _model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        let finite = self.uniform.is_finite()
            && self.gradient.is_finite()
            && self.centre.is_finite()
            && self.width.is_finite()
            && self.gyro.is_finite();
        if !finite {
            Err(bad(self.name(), "non-finite field".into()))
        } else if self.width <= 0.0 {
            Err(bad(
                self.name(),
                format!("window radius {} m <= 0", self.width),
            ))
        } else {
            Ok(())
        }
    }
    fn stability(&self, backbone: &Backbone, row: &mut [f32], _damping: &mut [f32]) {
        // Bound on the field's spatial derivative: |g| (1 + 2/e) + |a₀| / (w √e), the maxima
        // of the window's own slope terms.
        let stiffness = self.gradient.abs() * (1.0 + 2.0 / std::f32::consts::E)
            + self.uniform.length() / (self.width * std::f32::consts::E.sqrt());
        for (r, m) in row.iter_mut().zip(backbone.masses()) {
            *r += stiffness * m;
        }
    }
    fn add_forces(
        &self,
        ctx: &SubstepContext<'_>,
        _s: &mut dyn Any,
        _r: &[f32],
        force: &mut [Vec3A],
    ) {
        let a0 = Vec3A::from(self.uniform);
        let c = Vec3A::from(self.centre);
        let inv = 1.0 / (2.0 * self.width * self.width);
        let turn = GyroTurn::new(self.gyro, ctx.dt);
        let per_dt = 1.0 / ctx.dt;
        for (((f, x), v), m) in force
            .iter_mut()
            .zip(ctx.x)
            .zip(ctx.v)
            .zip(ctx.backbone.masses())
        {
            let r = *x - c;
            let window = (-r.length_squared() * inv).exp();
            *f += (a0 + r * self.gradient) * (window * *m);
            if let Some(turn) = &turn {
                *f += turn.change(*v) * (per_dt * *m);
            }
        }
    }
    fn adjoint(&self) -> EffectAdjoint {
        EffectAdjoint::Transposed
    }
    fn force_vjp(
        &self,
        ctx: &AdjointContext<'_>,
        lambda: &[Vec3A],
        grad_x: &mut [Vec3A],
        grad_v: &mut [Vec3A],
    ) {
        if let Some(turn) = GyroTurn::new(self.gyro, ctx.dt) {
            // The turn is linear in v: f = (m/dt) ((cos θ − 1) P⊥ v + sin θ v × b̂), whose
            // transpose gives λᵀ ∂f/∂v = (m/dt) ((cos θ − 1) P⊥ λ + sin θ b̂ × λ).
            for ((g, l), m) in grad_v.iter_mut().zip(lambda).zip(ctx.masses) {
                *g += turn.change_transposed(*l) * (*m / ctx.dt);
            }
        }
        let a0 = Vec3A::from(self.uniform);
        let c = Vec3A::from(self.centre);
        let inv = 1.0 / (2.0 * self.width * self.width);
        for ((g, (x, l)), m) in grad_x
            .iter_mut()
            .zip(ctx.x.iter().zip(lambda))
            .zip(ctx.masses)
        {
            // f = m w(x) (a₀ + g r), r = x − c, w = exp(−|r|² / 2w²), ∇w = −2 w r inv:
            // λᵀ ∂f/∂x = m (w g λ + ∇w (λ·(a₀ + g r))).
            let r = *x - c;
            let window = (-r.length_squared() * inv).exp();
            let grad_w = r * (-2.0 * window * inv);
            *g += (*l * (window * self.gradient) + grad_w * l.dot(a0 + r * self.gradient)) * *m;
        }
    }
}

/// Beyond the nine effects: gravity scaled by a factor `s`, i.e. an extra force
/// `(s − 1) m g` on every particle. With stiffness and damping refitted alongside, a model
/// whose gravity is `s g` moves like one whose clock runs `√s` times faster, so this also
/// stands for a recording whose true frame interval differs from its nominal one (the
/// initial velocities, taken from the first two frames, are the one thing it does not scale).
/// DEFORM's rod model carries a learnable integration ratio, a time-scale factor of this kind.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GravityScale {
    /// Factor on the model's gravity (1: unchanged).
    pub factor: f32,
}

impl Effect for GravityScale {
    fn name(&self) -> &str {
        "gravity-scale"
    }
    fn setup(&mut self, _model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite("gravity-scale", &[("factor", self.factor)])
    }
    fn add_forces(
        &self,
        ctx: &SubstepContext<'_>,
        _s: &mut dyn Any,
        _r: &[f32],
        force: &mut [Vec3A],
    ) {
        let extra = Vec3A::from(ctx.backbone.config().gravity) * (self.factor - 1.0);
        for (f, m) in force.iter_mut().zip(ctx.backbone.masses()) {
            *f += extra * *m;
        }
    }
    fn adjoint(&self) -> EffectAdjoint {
        EffectAdjoint::Transposed // a constant force: its transpose is zero
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use springs::{BackboneOptions, SimConfig, SpringParams};

    /// Uniform numbers in [0, 1) from a fixed sequence (xorshift).
    fn unit(state: &mut u64) -> f32 {
        *state ^= *state << 13;
        *state ^= *state >> 7;
        *state ^= *state << 17;
        (*state >> 40) as f32 / (1u64 << 24) as f32
    }

    /// 30 particles in a 6 cm box (springs to all neighbours within 4 cm: many blocks of four
    /// plus a tail), positions with one particle on top of another (a zero-length spring),
    /// and rest lengths from 0 (skipped) to twice the current length (both strain signs, past
    /// the stiffening's saturation and the yield strain).
    fn scene() -> (Backbone, Vec<Vec3A>, Vec<f32>) {
        let mut s = 0x9e37_79b9_7f4a_7c15_u64;
        let mut x: Vec<Vec3> = (0..30)
            .map(|_| Vec3::new(unit(&mut s), unit(&mut s), unit(&mut s)) * 0.06)
            .collect();
        x[7] = x[3];
        let params = SpringParams {
            stiffness: 3000.0,
            damping: 1.0,
            threshold: 0.04,
            max_springs: 12,
            ground_friction: 0.4,
        };
        let held = vec![-1; x.len()];
        let bb = Backbone::with_options(
            &x,
            &held,
            params,
            SimConfig::default(),
            BackboneOptions::default(),
        )
        .unwrap();
        assert!(!bb.springs().len().is_multiple_of(4) && bb.springs().len() > 40);
        let xa: Vec<Vec3A> = x.iter().map(|p| Vec3A::from(*p)).collect();
        let rest = bb
            .springs()
            .iter()
            .enumerate()
            .map(|(i, [a, b])| match i % 9 {
                0 => 0.0,
                _ => xa[*a as usize].distance(xa[*b as usize]) * 2.0 * unit(&mut s),
            })
            .collect();
        (bb, xa, rest)
    }

    fn context<'a>(bb: &'a Backbone, x: &'a [Vec3A]) -> SubstepContext<'a> {
        SubstepContext {
            backbone: bb,
            dt: 1e-3,
            substep: 0,
            x,
            v: x,
            grippers: &[],
            gripper_velocities: &[],
            closed: &[],
        }
    }

    fn bits(a: &[Vec3A]) -> Vec<[u32; 3]> {
        a.iter().map(|p| p.to_array().map(f32::to_bits)).collect()
    }

    /// The four-lane strain term gives bit for bit what the formula gives one spring at a time.
    #[test]
    fn strain_stiffening_blocks_equal_one_spring_at_a_time() {
        let (bb, x, rest) = scene();
        let effect = StrainStiffening {
            beta: 400.0,
            gamma: 0.3,
        };
        let mut f = vec![Vec3A::ZERO; x.len()];
        effect.add_forces(&context(&bb, &x), &mut (), &rest, &mut f);
        let mut expected = vec![Vec3A::ZERO; x.len()];
        for ((k, [a, b]), l0) in bb.stiffness().iter().zip(bb.springs()).zip(&rest) {
            let (a, b) = (*a as usize, *b as usize);
            let d = x[b] - x[a];
            let l = d.length();
            if l <= 0.0 || *l0 <= 0.0 {
                continue;
            }
            let dl = l - l0;
            let strain = dl / l0;
            let extra = if strain > 0.0 {
                let e = strain.min(STIFFENING_MAX_STRAIN);
                k * dl * effect.beta * e * e
            } else {
                -k * dl * effect.gamma
            };
            let fs = d * (extra / l);
            expected[a] += fs;
            expected[b] -= fs;
        }
        assert_eq!(bits(&f), bits(&expected));
        assert!(f.iter().all(|p| p.is_finite()) && f.iter().any(|p| p.length() > 0.0));
    }

    /// The same for plasticity's creep of the rest lengths.
    #[test]
    fn plastic_creep_blocks_equal_one_spring_at_a_time() {
        let (bb, x, rest) = scene();
        let effect = PlasticCreep {
            yield_strain: 0.1,
            rate: 50.0,
        };
        let mut got = rest.clone();
        effect.end_substep(&context(&bb, &x), &mut (), &mut got);
        let mut expected = rest.clone();
        for ([a, b], l0) in bb.springs().iter().zip(expected.iter_mut()) {
            let l = x[*a as usize].distance(x[*b as usize]);
            if *l0 <= 0.0 {
                continue;
            }
            let strain = (l - *l0) / *l0;
            let excess = strain.abs() - effect.yield_strain;
            if excess > 0.0 {
                let target = l / (1.0 + effect.yield_strain * strain.signum());
                let step = (effect.rate * 1e-3 * excess * *l0).min((target - *l0).abs());
                *l0 += step * strain.signum();
            }
        }
        let to_bits = |a: &[f32]| a.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(to_bits(&got), to_bits(&expected));
        let moved = got.iter().zip(&rest).filter(|(a, b)| a != b).count();
        assert!(moved > 5, "only {moved} rest lengths crept");
    }
}
