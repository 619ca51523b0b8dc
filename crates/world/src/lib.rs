//! A reference world: a higher-fidelity simulator of the paper's six deformable objects that
//! writes datasets in the pgrd format, with known, switchable physical effects.
//!
//! It stands in for reality where no real data exists, and gives a sim-to-real gap whose causes
//! are known. It differs from the spring-mass backbone the way reality does:
//! - **finer discretisation**: each object has several times more particles than are tracked;
//!   datasets export only a tracked subset of surface particles;
//! - **different numerics**: extended position-based dynamics (XPBD) with small substeps, links,
//!   curvature stencils, position-level contact and friction ([`Lab`] gives direct access);
//! - **switchable effects** ([`Effects`], [`EffectKind`]): drag, stiffness heterogeneity,
//!   nonlinear elasticity, bending, stick-slip friction, plasticity, actuation delay, grasp slip,
//!   mass distribution, and the out-of-library magnet and rotating frame;
//! - **an observation model** ([`Observation`]): tracking noise, slow drift, occlusion.
//!
//! [`generate`] builds a dataset in memory from a [`GenConfig`]; [`GeneratedDataset::write`]
//! writes it with a `truth.json` recording effects and parameters, and per episode the fine
//! surface particles' own Gaussians and true trajectories ([`TruthGaussians`],
//! `truth_ep_NNNN.safetensors`), the ground truth for rendered frames. Formulas, defaults and
//! timings are in `docs/world.md`. [`effect_displacement_m`] measures how far an effect moves the
//! object, before any model sees it. Units: metres, seconds, kilograms; z up, ground at z = 0.
//!
//! ```
//! use world::{GenConfig, ObjectKind};
//! let mut cfg = GenConfig::fixture(ObjectKind::Flag);
//! (cfg.train_episodes, cfg.val_episodes, cfg.tracked) = (1, 1, 60);
//! let data = world::generate(&cfg)?;
//! assert_eq!(data.episodes.len(), 2);
//! assert_eq!(data.truth.effects_enabled, world::default_kinds(ObjectKind::Flag));
//! # Ok::<(), world::Error>(())
//! ```

mod build;
mod displacement;
mod effects;
mod error;
mod generate;
mod lab;
mod motion;
mod object;
mod observation;
mod obstacles;
mod plant;
mod record;
mod render;
mod rng;
mod sim;
mod truth_gaussians;

pub use build::Resolution;
pub use displacement::effect_displacement_m;
pub use effects::{
    ActuationDelay, Bending, Drag, EffectKind, Effects, Fan, Friction, GraspSlip, Magnet,
    MassDistribution, NonlinearElasticity, Plasticity, RotatingFrame, StiffnessHeterogeneity,
    default_kinds,
};
pub use error::Error;
pub use generate::{
    BranchInfo, DEFAULT_GAUSSIAN_PARTICLES, EPISODE_STRIDE, EVAL_STEPS, FIXTURE_GAUSSIAN_PARTICLES,
    FPS, FRAMES_PER_EPISODE, GenConfig, GeneratedDataset, HISTORY_FRAMES, MAX_LINK_SWEEPS,
    MaterialInfo, RecordingInfo, TimingInfo, Truth, default_tracked, generate,
    generate_with_progress,
};
pub use lab::Lab;
pub use motion::MotionStyle;
pub use object::ObjectKind;
pub use observation::Observation;
pub use obstacles::BoxObstacle;
pub use plant::{Plant, PlantConfig};
pub use render::render_strip;
pub use truth_gaussians::{
    SIGMA_PER_SPACING, TRUTH_GAUSSIANS_FORMAT, TRUTH_OPACITY, TruthGaussians,
};
