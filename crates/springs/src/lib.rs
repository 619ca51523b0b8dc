//! Spring-mass physics backbone of PGRD: topology, forces, semi-implicit Euler rollouts,
//! batched in parallel.
//!
//! An object is a cloud of point masses (1 kg each by default) joined by axial springs with
//! dashpots, built once from the first frame ([`Topology::build`]; controller points that
//! join the object by a rule of their own: [`AnchorSprings`]). A [`Backbone`] holds the
//! topology, the five fitted [`SpringParams`] and a fixed substep derived from a stability bound
//! ([`Substep::Auto`]); [`Backbone::step`] advances one model step (0.1 s) without allocating,
//! [`Backbone::rollout`] runs a whole action sequence, and [`rollout_batch`] runs many rollouts
//! in parallel with results independent of the thread count. [`Backbone::step_taped`] and
//! [`StepAdjoint::vjp`] carry gradients back through a step, for models trained on top of the
//! backbone. Units: metres, seconds, kilograms, newtons; z is up. The model, its stability
//! bound and every deviation from the reference code are described in `docs/physics.md`.
//!
//! ```
//! use glam::Vec3;
//! use springs::{Actions, Backbone, SimConfig, SpringParams, State};
//! // A 10 x 10 x 4 block, 1 cm spacing, dropped from 5 cm onto the ground.
//! let mut x = Vec::new();
//! for i in 0..10 { for j in 0..10 { for k in 0..4 {
//!     x.push(Vec3::new(i as f32, j as f32, k as f32 + 5.0) * 0.01);
//! }}}
//! let params = SpringParams { threshold: 0.018, ..SpringParams::reference_rope() };
//! let bb = Backbone::new(&x, &[], params, SimConfig::default())?;
//! let out = bb.rollout(&State::at_rest(x), &Actions::without_grippers(11))?;
//! let lowest = out.positions[10].iter().map(|p| p.z).fold(f32::INFINITY, f32::min);
//! assert!(lowest >= 0.0 && lowest < 0.005); // landed after 1 s
//! # Ok::<(), springs::SimError>(())
//! ```

mod actions;
mod adjoint;
mod backbone;
mod config;
mod effects;
mod error;
mod fill;
mod kernels;
mod obstacles;
mod params;
mod partition;
mod spectral;
mod split;
mod step;
mod topology;

pub use actions::{ActionFrame, Actions, Rollout, State};
pub use adjoint::{StepAdjoint, StepTape};
pub use backbone::{Backbone, BackboneOptions};
pub use config::{Dashpot, Manipulation, SimConfig, Substep};
pub use effects::{
    AdjointContext, AirDrag, Effect, EffectAdjoint, GroundContact, ModelSetup, StiffnessField,
    SubstepContext,
};
pub use error::SimError;
pub use fill::fill_interior;
pub use obstacles::{BoxObstacle, Obstacles};
pub use params::{
    DIVERGENCE_LIMIT, GROUND_DAMPING, GROUND_MU, GROUND_STIFFNESS, GROUND_VISCOUS_FRICTION,
    PAPER_BOUNDS, ParamBounds, REFERENCE_BOUNDS, SpringParams,
};
pub use step::{RolloutJob, Scratch, rollout_batch};
pub use topology::{AnchorSprings, PairFilter, Topology};
