//! The crate's error type.

/// Everything that can go wrong when setting up or running a planner.
#[derive(Debug, thiserror::Error)]
pub enum PlanError {
    /// A setting is out of its valid range.
    #[error("invalid {name} = {value}: {reason}")]
    Config {
        /// Setting name.
        name: &'static str,
        /// The value given.
        value: f64,
        /// What is required.
        reason: &'static str,
    },
    /// A task name that is not one of [`crate::TaskKind::ALL`].
    #[error("unknown task `{0}` (rope-lift, rope-lower, rope-rotate, rope-curve or reroute)")]
    UnknownTask(String),
    /// Inputs that must agree in size do not (particles, grippers, frames).
    #[error("{what}: expected {expected}, got {got}")]
    Mismatch {
        /// Which input.
        what: &'static str,
        /// The size it must have.
        expected: usize,
        /// The size it has.
        got: usize,
    },
    /// A state or target holds a NaN or infinite value.
    #[error("{0} is not finite")]
    NonFinite(&'static str),
    /// The forward model failed on one rollout (the planner drops that candidate).
    #[error("forward model: {0}")]
    Model(String),
    /// Every candidate rollout of a replanning step failed.
    #[error("all {samples} candidate rollouts failed in every iteration; first error: {first}")]
    AllRolloutsFailed {
        /// Candidates per iteration.
        samples: usize,
        /// The first failure.
        first: String,
    },
    /// The backbone refused its inputs.
    #[error("backbone: {0}")]
    Sim(springs::SimError),
    /// The reference world refused a command or diverged.
    #[error("reference world: {0}")]
    World(world::Error),
    /// A metric could not be computed.
    #[error("metric: {0}")]
    Metrics(metrics::MetricsError),
}

// The wrapped error is part of the message, not its source: a report printing the chain of
// causes would otherwise repeat its text.
impl From<springs::SimError> for PlanError {
    fn from(e: springs::SimError) -> Self {
        PlanError::Sim(e)
    }
}
impl From<world::Error> for PlanError {
    fn from(e: world::Error) -> Self {
        PlanError::World(e)
    }
}
impl From<metrics::MetricsError> for PlanError {
    fn from(e: metrics::MetricsError) -> Self {
        PlanError::Metrics(e)
    }
}

/// The crate's result type.
pub type Result<T> = std::result::Result<T, PlanError>;
