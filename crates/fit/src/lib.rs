//! Fits a model's physical parameters to tracked episodes with CMA-ES, the paper's first stage.
//!
//! Contacts make gradients unreliable, so the search is black-box: each CMA-ES candidate is
//! rolled out on a sample of training [`scene::Scene`]s and scored by the mean squared position
//! error over the window. A [`Family`] says which parameters are searched and how a real
//! parameter vector becomes a backbone; [`BackboneFamily`] is the paper's five parameters,
//! [`ControllerFamily`] adds the rule joining an `attach` dataset's controller points.
//! Later stages add effect parameters by implementing [`Family`]. [`widen_threshold_range`]
//! lets the spring threshold reach past the reference range where tracked points are sparser
//! than it assumes.
//!
//! - Each generation draws `samples` scenes (seeded by the run's seed and the generation), and
//!   every candidate of that generation is scored on the same scenes, so candidates compete on
//!   equal terms.
//! - The best candidate is kept; with [`FitConfig::rescore`] the final choice is made on the
//!   loss over *all* scenes among the optimiser's mean and the best few generations' bests,
//!   instead of on whichever sample a generation drew.
//! - Rollouts run in parallel across (candidate, scene) pairs; losses are reduced in a fixed
//!   order, so results do not depend on the thread count.
//! - A rollout that diverges or returns non-finite values scores [`PENALTY`] instead of failing
//!   the fit.
//! - With a checkpoint path, the optimiser state is written atomically after every generation;
//!   a later call with the same settings (and scenes under the same substep rule) resumes from
//!   it and produces exactly the candidates the uninterrupted run would have.
//! - [`PausedFit`] runs the same fit in stages in memory, so a caller can look at a run
//!   halfway and decide whether to spend the rest of its budget on it.
//!
//! [`refine_stiffness`] is the second stage of the paper's "Diff. Spring-Mass" baseline: a
//! stiffness that varies over the object, refined by gradient descent through the simulator's
//! adjoint.

mod controller;
mod family;
mod refine;
mod run;

pub use controller::{
    CONTROLLER_RADIUS_RANGE_M, CONTROLLER_SPRINGS_RANGE, ControllerFamily, ControllerFit,
    ControllerStart, MAX_CONTROLLER_STARTS, controller_start_radii, fit_controller,
};
pub use family::{BackboneFamily, Family, GAP_REACH, widen_threshold_range};
pub use refine::{
    ModelOptions, RefineConfig, RefineOutcome, RefineStep, batch_gradient, field_options,
    refine_stiffness, scene_gradient,
};
pub use run::{
    Contender, FitConfig, FitError, FitOutcome, Generation, PENALTY, PausedFit, Rescore, fit,
    scene_loss,
};
