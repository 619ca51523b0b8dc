//! Ask/tell CMA-ES with box bounds, integer parameters and restarts.
//!
//! The covariance matrix adaptation evolution strategy follows Hansen, "The CMA Evolution
//! Strategy: A Tutorial" (arXiv:1604.00772), with its default parameters: weighted
//! recombination, cumulative step-size adaptation, rank-one plus active rank-μ covariance
//! update. On top of it:
//!
//! - [`CmaEs`]: the ask/tell loop. The caller evaluates each population however it likes (in
//!   parallel); results depend only on the seed, never on thread count or scheduling.
//! - [`Bounds`]: a box, enforced by mirroring candidates into it.
//! - [`Parameters`]: maps the normalised `[0, 1]^n` the optimiser searches onto real parameter
//!   ranges (linear or log scale) and rounds integer parameters on evaluation.
//! - [`Ipop`] and [`minimize`]: restarts with doubling population.
//! - Checkpoints: [`CmaEs`] and [`Ipop`] serialise with serde (floats bit-exact), and a resumed
//!   run continues with exactly the candidates the uninterrupted one would have produced.
//!
//! ```
//! use cmaes::{Parameter, Parameters, minimize};
//!
//! // Fit two physical parameters; the objective sees real units.
//! let params = Parameters::new(vec![
//!     Parameter::log("stiffness_n_per_m", 10.0, 5e4),
//!     Parameter::linear("max_springs", 4.0, 200.0).integer(),
//! ])?;
//! let loss = |real: &[f64]| (real[0].ln() - 1000f64.ln()).powi(2) + (real[1] - 37.0).powi(2);
//! let mut config = params.cmaes_config(&[100.0, 100.0], 0.2, 1)?;
//! config.termination.max_evaluations = Some(3000);
//! let min = minimize(
//!     |pop| pop.iter().map(|u| loss(&params.to_real(u).unwrap())).collect(),
//!     config,
//!     2,
//! )?;
//! let best = params.to_real(&min.x)?;
//! assert!((best[0] - 1000.0).abs() < 1.0 && best[1] == 37.0);
//! # Ok::<(), cmaes::Error>(())
//! ```

mod config;
mod es;
mod exact;
mod linalg;
mod restart;
mod scaling;
mod stop;
mod strategy;

pub use config::{Bounds, CmaesConfig, MAX_POPULATION, Termination, default_population};
pub use es::CmaEs;
pub use restart::{Ipop, Minimum, POPULATION_GROWTH, RunSummary, minimize};
pub use scaling::{INTEGER_STD_FRACTION, Parameter, Parameters, Scale};
pub use stop::StopReason;

/// Errors of this crate.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    /// A configuration field is out of range or inconsistent.
    #[error("invalid CMA-ES configuration: {0}")]
    InvalidConfig(String),
    /// A slice has the wrong length.
    #[error("{what} has length {got}, expected {expected}")]
    LengthMismatch {
        /// What was measured.
        what: &'static str,
        /// Required length.
        expected: usize,
        /// Actual length.
        got: usize,
    },
    /// `tell` was called without a population from `ask` awaiting its fitness.
    #[error("tell() called with no population pending: call ask() first")]
    NoPendingPopulation,
    /// A candidate passed to `tell` is not the one `ask` returned at that position.
    #[error(
        "candidate {index} is not the one ask() returned at that position \
         (candidates must be passed back unchanged and in order)"
    )]
    ForeignCandidate {
        /// Position of the first mismatching candidate.
        index: usize,
    },
    /// A parameter definition or value is invalid.
    #[error("parameter `{name}`: {reason}")]
    InvalidParameter {
        /// The parameter's name.
        name: String,
        /// What is wrong.
        reason: String,
    },
    /// A deserialised state is inconsistent.
    #[error("invalid checkpoint: {0}")]
    InvalidCheckpoint(String),
    /// The objective never returned a finite value.
    #[error("the objective returned no finite fitness value in the whole run")]
    NoFiniteFitness,
}
