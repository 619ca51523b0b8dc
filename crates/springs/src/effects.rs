//! Extension point for extra force terms ("effects") and the one built-in effect, [`AirDrag`].
//!
//! An effect is handed to [`crate::Backbone::with_options`] and can act at five points:
//! once at construction ([`Effect::setup`]: masses, per-spring stiffness / damping / rest
//! length, precomputed data such as bending triplets), in the stability bound
//! ([`Effect::stability`]), once per model step ([`Effect::adjust_actions`]: e.g. actuation
//! delay), every substep ([`Effect::add_forces`] before the velocity update and
//! [`Effect::end_substep`] after the position update, which may change rest lengths, e.g.
//! plasticity), and in ground contact ([`Effect::ground_friction`]). [`Effect::compliant_grasp`]
//! turns kinematic grasping off so that the effect can attach held particles with forces.
//! Per-rollout mutable data lives in the state from [`Effect::new_state`], which the
//! [`crate::Scratch`] owns. With no effects none of this code runs.
//!
//! The step's adjoint ([`crate::StepAdjoint`]) differentiates an effect when it says so
//! ([`Effect::adjoint`]): an effect that acts only in `setup` needs nothing more (its changes
//! are in the backbone's arrays, which the adjoint reads); one with forces gives the transpose
//! of their Jacobian in [`Effect::force_vjp`]. Every other effect's forces are held fixed by
//! the adjoint ([`crate::Backbone::held_fixed_effects`] names them).

use std::any::Any;
use std::fmt::Debug;

use glam::{Vec3, Vec3A};

use crate::{Backbone, SimError, SpringParams};

/// Model data an effect may edit once, before the stability bound and the damping weights are
/// computed. Spring arrays are in the backbone's internal spring order.
#[derive(Debug)]
pub struct ModelSetup<'a> {
    /// Rest positions (first frame), m.
    pub rest_positions: &'a [Vec3],
    /// Gripper assignment per particle (-1: none).
    pub held: &'a [i32],
    /// The fitted parameters.
    pub params: &'a SpringParams,
    /// Spring endpoints.
    pub springs: &'a [[u32; 2]],
    /// Rest length per spring, m (initial rest lengths of every rollout).
    pub rest_lengths: &'a mut [f32],
    /// Stiffness per spring, N/m (starts at `params.stiffness`).
    pub stiffness: &'a mut [f32],
    /// Dashpot coefficient per spring, N·s/m (starts at `params.damping`).
    pub damping: &'a mut [f32],
    /// Mass per particle, kg (must stay finite and > 0).
    pub masses: &'a mut [f32],
    /// The particles in order along the centreline when the object is a chain (a cable's
    /// markers with the particles between them; [`crate::BackboneOptions::chain`]), else
    /// `None`. Effects that act along a curve (bending) use it instead of neighbourhoods.
    pub chain: Option<&'a [u32]>,
}

/// What an effect sees during a substep.
#[derive(Debug, Clone, Copy)]
pub struct SubstepContext<'a> {
    /// The model.
    pub backbone: &'a Backbone,
    /// Substep length, s.
    pub dt: f32,
    /// Index of this substep within the model step (0-based).
    pub substep: usize,
    /// Positions, m (start of the substep in `add_forces`, end in `end_substep`).
    pub x: &'a [Vec3A],
    /// Velocities, m/s (same timing as `x`).
    pub v: &'a [Vec3A],
    /// Gripper positions at the same time, m.
    pub grippers: &'a [Vec3],
    /// Gripper velocities during this step, m/s.
    pub gripper_velocities: &'a [Vec3],
    /// Gripper closed flags for this step.
    pub closed: &'a [bool],
}

/// What an effect's adjoint sees ([`Effect::force_vjp`]): the state at the start of the substep
/// whose forces are being differentiated.
#[derive(Debug, Clone, Copy)]
pub struct AdjointContext<'a> {
    /// Substep length, s.
    pub dt: f32,
    /// Positions at the substep's start, m.
    pub x: &'a [Vec3A],
    /// Velocities at the substep's start, m/s.
    pub v: &'a [Vec3A],
    /// Mass per particle, kg.
    pub masses: &'a [f32],
}

/// How the step's adjoint ([`crate::StepAdjoint`]) treats an effect ([`Effect::adjoint`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EffectAdjoint {
    /// Its forces are held fixed: the adjoint is not exact with it.
    HeldFixed,
    /// It acts only in [`Effect::setup`]; its changes are in the backbone's arrays, which the
    /// adjoint reads: exact, nothing to carry.
    SetupOnly,
    /// Its only other hooks are [`Effect::add_forces`], whose forces depend on nothing but the
    /// substep's positions and velocities (not on the per-spring stiffness, the grippers or
    /// per-rollout state), with [`Effect::force_vjp`] applying the transpose of their Jacobian,
    /// and [`Effect::damp_velocities`], linear in the velocities and independent of the
    /// positions, with [`Effect::damp_velocities_vjp`] applying its transpose.
    Transposed,
}

/// One particle in ground contact, given to [`Effect::ground_friction`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroundContact {
    /// Particle index.
    pub particle: usize,
    /// Velocity component parallel to the ground after the force update, m/s.
    pub tangential_velocity: Vec3A,
    /// Penalty normal force, N.
    pub normal_force: f32,
    /// Particle mass, kg.
    pub mass: f32,
    /// The backbone's effective Coulomb coefficient.
    pub mu: f32,
    /// Substep length, s.
    pub dt: f32,
}

/// An extra force term or model change. All hooks have no-op defaults.
///
/// Contract: forces are in N; an effect that adds stiffness or explicit damping must report it in
/// [`Effect::stability`], otherwise the automatic substep may be unstable; a replacement friction
/// law must never increase the tangential speed.
pub trait Effect: Send + Sync + Debug {
    /// Short name used in error messages.
    fn name(&self) -> &str;

    /// Once, when the backbone is built: edit masses / springs, precompute data.
    fn setup(&mut self, model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        let _ = model;
        Ok(())
    }

    /// Add this effect's contribution to the stability bound of each particle: `row_stiffness`
    /// (N/m) gets the sum of the norms of the effect's stiffness blocks in that particle's row
    /// (a pair spring of stiffness k adds 2k at both ends; a kinematic anchor adds k), `damping`
    /// (N·s/m) the explicit velocity damping it applies to the particle.
    fn stability(&self, backbone: &Backbone, row_stiffness: &mut [f32], damping: &mut [f32]) {
        let _ = (backbone, row_stiffness, damping);
    }

    /// `Some(f)` when all of this effect's stiffness is an extra axial stiffness on the
    /// backbone's own springs of at most `f` times each spring's stiffness (a strain-dependent
    /// spring law), i.e. at most `f K` with `K` the springs' stiffness matrix. The spectral
    /// substep ([`crate::Substep::Spectral`]) then scales the springs' eigenvalue estimate by
    /// `1 + f` instead of adding the stiffness rows of [`Effect::stability`] (which must still
    /// report them, `2 f k` per spring end, for the Gershgorin bound of the other modes).
    fn spring_stiffness_factor(&self) -> Option<f32> {
        None
    }

    /// Fresh per-rollout state (e.g. action history, anchors); stored in the [`crate::Scratch`].
    fn new_state(&self, backbone: &Backbone) -> Box<dyn Any + Send> {
        let _ = backbone;
        Box::new(())
    }

    /// At the start of each model step: may rewrite the gripper motion applied during the step
    /// (`from`, `to`: positions, m; `closed`: flags of the step).
    fn adjust_actions(
        &self,
        state: &mut dyn Any,
        from: &mut [Vec3],
        to: &mut [Vec3],
        closed: &mut [bool],
    ) {
        let _ = (state, from, to, closed);
    }

    /// Every substep, before the velocity update: add forces (N) to `force`.
    fn add_forces(
        &self,
        ctx: &SubstepContext<'_>,
        state: &mut dyn Any,
        rest_lengths: &[f32],
        force: &mut [Vec3A],
    ) {
        let _ = (ctx, state, rest_lengths, force);
    }

    /// Every substep, after the velocity update (forces, the grasp, the springs' dashpots) and
    /// before ground friction and the position update: may replace the velocities (m/s) by an
    /// implicit damping's, `v ← (M + dt C)⁻¹ M v` for a damping matrix `C` (N·s/m), which stays
    /// stable at any substep where an explicit `−C v` force would need tiny ones. Particles
    /// with `inv_mass` 0 (held by a closed gripper) must keep their velocities. An effect that
    /// uses this hook reports [`EffectAdjoint::HeldFixed`] (the adjoint takes it as the
    /// identity) unless the map is linear in the velocities and does not depend on the
    /// positions, and [`Effect::damp_velocities_vjp`] gives its transpose
    /// ([`EffectAdjoint::Transposed`]).
    fn damp_velocities(&self, dt: f32, inv_mass: &[f32], v: &mut [Vec3A]) {
        let _ = (dt, inv_mass, v);
    }

    /// The transpose of [`Effect::damp_velocities`] (a linear map of the velocities): on entry
    /// `grad` holds `∂L/∂v'` of the velocities it produced, on return `∂L/∂v` of those it was
    /// given, with the same `dt` and `inv_mass`. Called only for [`EffectAdjoint::Transposed`].
    fn damp_velocities_vjp(&self, dt: f32, inv_mass: &[f32], grad: &mut [Vec3A]) {
        let _ = (dt, inv_mass, grad);
    }

    /// Every substep, after the position update: may change the rest lengths (m) of this rollout.
    fn end_substep(&self, ctx: &SubstepContext<'_>, state: &mut dyn Any, rest_lengths: &mut [f32]) {
        let _ = (ctx, state, rest_lengths);
    }

    /// Whether [`Effect::ground_friction`] replaces the built-in ground friction.
    fn replaces_ground_friction(&self) -> bool {
        false
    }

    /// New tangential velocity (m/s) of a particle in ground contact; called only when
    /// [`Effect::replaces_ground_friction`] is true (the first such effect wins).
    fn ground_friction(&self, contact: &GroundContact) -> Vec3A {
        contact.tangential_velocity
    }

    /// When true, closed grippers no longer move held particles kinematically; the effect is
    /// expected to attach them (e.g. a compliant spring to the gripper) in `add_forces`.
    fn compliant_grasp(&self) -> bool {
        false
    }

    /// How the step's adjoint treats this effect ([`EffectAdjoint`]; default: held fixed).
    fn adjoint(&self) -> EffectAdjoint {
        EffectAdjoint::HeldFixed
    }

    /// The transpose of [`Effect::add_forces`]' Jacobian: given `lambda` (∂L/∂f, one entry per
    /// particle), add `λᵀ ∂f/∂x` to `grad_x` and `λᵀ ∂f/∂v` to `grad_v`, the forces taken at
    /// the substep's start state in `ctx`. Called only for [`EffectAdjoint::Transposed`].
    fn force_vjp(
        &self,
        ctx: &AdjointContext<'_>,
        lambda: &[Vec3A],
        grad_x: &mut [Vec3A],
        grad_v: &mut [Vec3A],
    ) {
        let _ = (ctx, lambda, grad_x, grad_v);
    }
}

/// Linear air drag `f = -coefficient * v` on every particle (isotropic, still air).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AirDrag {
    /// Drag coefficient per particle, N·s/m.
    pub coefficient: f32,
}

impl Effect for AirDrag {
    fn name(&self) -> &str {
        "air-drag"
    }

    fn setup(&mut self, _model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        if self.coefficient.is_finite() && self.coefficient >= 0.0 {
            Ok(())
        } else {
            Err(SimError::Effect {
                name: self.name().to_owned(),
                message: format!("coefficient {} must be finite and >= 0", self.coefficient),
            })
        }
    }

    fn stability(&self, _backbone: &Backbone, _row_stiffness: &mut [f32], damping: &mut [f32]) {
        // Explicit drag: the bound needs its rate c/m.
        for d in damping {
            *d += self.coefficient;
        }
    }

    fn add_forces(
        &self,
        ctx: &SubstepContext<'_>,
        _state: &mut dyn Any,
        _rest: &[f32],
        force: &mut [Vec3A],
    ) {
        for (f, v) in force.iter_mut().zip(ctx.v) {
            *f -= self.coefficient * *v;
        }
    }

    fn adjoint(&self) -> EffectAdjoint {
        EffectAdjoint::Transposed
    }

    fn force_vjp(
        &self,
        _ctx: &AdjointContext<'_>,
        lambda: &[Vec3A],
        _grad_x: &mut [Vec3A],
        grad_v: &mut [Vec3A],
    ) {
        for (g, l) in grad_v.iter_mut().zip(lambda) {
            *g -= self.coefficient * *l;
        }
    }
}

/// Spatially varying stiffness: every spring's stiffness multiplied by
/// `exp((a_i + a_j) / 2)`, the geometric mean of its ends' factors `exp(a)`. `log_factor` holds
/// `a` for the first particles (the tracked ones of a scene); every further particle (hidden or
/// interior) takes the value of the nearest of them at rest. What the per-particle stiffness fit
/// (`fit::refine_stiffness`, the paper's "Diff. Spring-Mass" baseline) adjusts.
#[derive(Debug, Clone, PartialEq)]
pub struct StiffnessField {
    /// Natural log of the stiffness factor per leading particle.
    pub log_factor: std::sync::Arc<Vec<f32>>,
}

impl StiffnessField {
    /// For every particle of a model whose rest positions are `rest`, the leading particle
    /// whose factor it takes: itself among the first `lead`, else the nearest of them at rest
    /// (ties: the lower index).
    pub fn owners(lead: usize, rest: &[Vec3]) -> Vec<usize> {
        let lead = lead.min(rest.len());
        let mut owner: Vec<usize> = (0..lead).collect();
        owner.extend(rest[lead..].iter().map(|p| {
            rest[..lead]
                .iter()
                .enumerate()
                .map(|(i, q)| (q.distance_squared(*p), i))
                .min_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)))
                .map_or(0, |(_, i)| i)
        }));
        owner
    }

    /// The factor's log for every particle of a model whose rest positions are `rest`
    /// ([`Self::owners`]).
    pub fn per_particle(&self, rest: &[Vec3]) -> Result<Vec<f32>, SimError> {
        let lead = self.log_factor.len();
        if lead == 0 || rest.len() < lead || !self.log_factor.iter().all(|a| a.is_finite()) {
            return Err(SimError::Effect {
                name: "stiffness-field".into(),
                message: format!(
                    "{lead} finite log factors needed for a model of {} particles",
                    rest.len()
                ),
            });
        }
        Ok(Self::owners(lead, rest)
            .into_iter()
            .map(|i| self.log_factor[i])
            .collect())
    }
}

impl Effect for StiffnessField {
    fn name(&self) -> &str {
        "stiffness-field"
    }

    fn setup(&mut self, model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        let a = self.per_particle(model.rest_positions)?;
        for (k, &[i, j]) in model.stiffness.iter_mut().zip(model.springs) {
            *k *= (0.5 * (a[i as usize] + a[j as usize])).exp();
        }
        Ok(())
    }

    fn adjoint(&self) -> EffectAdjoint {
        EffectAdjoint::SetupOnly
    }
}
