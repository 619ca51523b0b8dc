//! Sim-to-real gap diagnosis: given tracked episodes and a fitted spring-mass backbone, say
//! **where** its error lies (per particle, region, step, phase and state), **which** unmodelled
//! physical effect causes it, and **how far** the held-out error shrinks once that effect is
//! added.
//!
//! - [`Candidate`] is the library of nine effects (`drag`, `stiffness-heterogeneity`,
//!   `nonlinear-elasticity`, `bending`, `friction`, `plasticity`, `actuation-delay`,
//!   `grasp-slip`, `mass-distribution`), each a [`springs::Effect`] with one or two
//!   parameters ([`forces`]), plus a generic probe used to detect gaps no named effect
//!   explains: an external acceleration field, first order in position within a window, plus
//!   a workless velocity term ([`forces::ExternalField`]). [`Candidate::EXTRA`] holds
//!   candidates offered only on request (`gravity-scale`, for recordings whose gravity or
//!   clock the backbone gets wrong; `bending-damping`, a cable's internal bending damping,
//!   and `twist`, its torsion between clamped ends, on chain datasets; `stiffness-lag`, a
//!   stiffness field along each point's lag behind the grippers, [`grasp_lag`]). The probe is
//!   refitted from the point the backbone's
//!   residuals converge on ([`residual_focus`]) and from a broad start, for
//!   [`DiagnoseConfig::probe_factor`] times the candidates' generations, and the lower
//!   training loss is kept.
//! - [`diagnose`] refits the backbone alone (the control) and the backbone with each candidate on
//!   the training scenes with the same small CMA-ES budget, scores all on held-out scenes,
//!   bootstraps the shrinkage over episodes ([`paired_shrinkage`]) and applies the verdict
//!   rule ([`decide`]): an effect, `none` or `unknown`. A candidate counts only if switching
//!   its effect off in its own refit also loses significantly (the effect, not the refit of
//!   the shared parameters, carries the gain); significant candidates that held-out error
//!   cannot separate go to the one whose signature matches the residual best ([`break_tie`]).
//! - With [`DiagnoseConfig::race`] the candidates' refits race: half the generations for
//!   every candidate, the rest only for the best few by training loss ([`RACE_SCENES`]);
//!   the control always runs whole, and the probe's two starts race each other. [`effort`] counts a diagnosis's simulator
//!   work before it runs (no clock), so a time budget can choose the race and the substep rule.
//! - A model may already hold some library effects ([`BaseEffect`], e.g. the verdict of an
//!   earlier diagnosis): they are refitted with the backbone in the control and in every
//!   candidate refit, so the diagnosis ranks the remaining candidates against that model.
//! - [`Diagnosis::rejudge`] applies another [`VerdictRule`] to a stored report's refits
//!   (the same stage as the diagnosis, [`judge`]): how the verdict depends on the rule.
//! - [`add_learnable`] adds a trained residual network's held-out errors: how much of the
//!   gap is learnable, and `unknown` when the network beats every model the library offers.
//! - [`Diagnosis::carry_over_caution`] flags a diagnosis whose control refit scores
//!   worse on the held-out episodes than the model as given: its comparisons are fragile.
//! - [`render_html`] turns a [`Diagnosis`] into a self-contained page.
//!
//! Method, formulas and parameter ranges: `docs/gap.md`; measured bench results, run by run:
//! `docs/gap-log.md`.
//!
//! ```
//! // Held-out MDE per episode of the control and of one candidate, cm.
//! let before = [2.0, 2.4, 1.9, 2.2, 2.1, 2.3];
//! let after = [1.2, 1.5, 1.1, 1.4, 1.2, 1.3];
//! let c = gap::paired_shrinkage(&before, &after, 2000, 0)?;
//! let lib = vec![("drag".to_string(), c)];
//! let rule = gap::VerdictRule::default();
//! let v = gap::decide(gap::best_candidate(&lib, &rule), None, None, &rule);
//! assert_eq!(v.label(), "drag");
//! # Ok::<(), gap::GapError>(())
//! ```

mod base;
mod candidates;
mod diagnose;
mod effort;
mod focus;
pub mod forces;
mod html;
mod judge;
mod lanes;
mod learnable;
mod locate;
mod nan;
mod race;
mod stats;

pub use base::{BaseEffect, backbone_options};
pub use candidates::{
    Candidate, CandidateFamily, MaterialFrame, PROBE_GYRO, PROBE_WINDOW_M, principal_axis,
};
pub use diagnose::{
    CONTROL_EXCESS_CAUTION, ControlFit, DiagnoseConfig, Diagnosis, Heldout, HowFar, RACE_SCENES,
    RankedEffect, TieBreak, diagnose, evaluate, grasp_lag, material_frame,
};
pub use effort::{BudgetChoice, ESTIMATE_MARGIN, Effort, SECONDS_PER_WORK, effort};
pub use focus::{FOCUS_SCENES, ProbeStart, ResidualFocus, focus_of_lines, residual_focus};
pub use html::render_html;
pub use judge::{Judgement, judge};
pub use learnable::{Learnable, add_learnable};
pub use locate::{Bin, CONTACT_HEIGHT_M, Trend, Where, locate, spearman};
pub use stats::{
    Comparison, Rival, Verdict, VerdictRule, best_candidate, break_tie, decide, paired_shrinkage,
};

/// Why a diagnosis failed.
#[derive(Debug, thiserror::Error)]
pub enum GapError {
    /// A split has no scenes.
    #[error("no {0} episodes to diagnose on")]
    NoScenes(&'static str),
    /// Bad settings or inputs.
    #[error("invalid input: {0}")]
    Config(String),
    /// The fitted backbone itself fails on a held-out episode.
    #[error("the fitted backbone diverged on held-out episode {index}")]
    Rollout {
        /// Position of the episode among the held-out scenes.
        index: usize,
    },
    /// A refit failed.
    #[error("refit: {0}")]
    Fit(fit::FitError),
    /// A parameter set was refused.
    #[error("CMA-ES parameters: {0}")]
    Cmaes(cmaes::Error),
    /// Building a scene or scoring failed.
    #[error("scene: {0}")]
    Scene(scene::SceneError),
}

// The wrapped error is part of the message, not its source: a report printing the chain of
// causes would otherwise repeat its text.
impl From<fit::FitError> for GapError {
    fn from(e: fit::FitError) -> Self {
        GapError::Fit(e)
    }
}
impl From<cmaes::Error> for GapError {
    fn from(e: cmaes::Error) -> Self {
        GapError::Cmaes(e)
    }
}
impl From<scene::SceneError> for GapError {
    fn from(e: scene::SceneError) -> Self {
        GapError::Scene(e)
    }
}
