use thiserror::Error;

/// Errors of the residual network, its rollouts and its training.
#[derive(Debug, Error)]
pub enum ResidualError {
    /// A tensor operation failed (shapes, I/O of safetensors).
    #[error("tensor operation: {0}")]
    Candle(candle_core::Error),
    /// The physics backbone refused a step.
    #[error("backbone: {0}")]
    Sim(springs::SimError),
    /// Building a scene failed.
    #[error("scene: {0}")]
    Scene(scene::SceneError),
    /// Reading the dataset failed.
    #[error("dataset: {0}")]
    Dataset(dataset::Error),
    /// Reading or writing a file failed.
    #[error("{path}: {cause}")]
    Io {
        /// The file.
        path: String,
        /// The cause. Part of the message, so not its `source()`: a chain of causes would
        /// repeat it.
        cause: std::io::Error,
    },
    /// A JSON file could not be parsed or written.
    #[error("{path}: {cause}")]
    Json {
        /// The file.
        path: String,
        /// The cause. Part of the message, so not its `source()`: a chain of causes would
        /// repeat it.
        cause: serde_json::Error,
    },
    /// A configuration value is out of range.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// Inputs do not match the model (particle counts, history lengths).
    #[error("input mismatch: {0}")]
    Input(String),
    /// The hybrid state left the finite, bounded range: the rollout diverged.
    #[error("rollout diverged at step {step}: {what}")]
    Diverged {
        /// Step (0-based) at which the state became invalid.
        step: usize,
        /// What was observed.
        what: String,
    },
}

// The wrapped error is part of the message, not its source: a report printing the chain of
// causes would otherwise repeat its text.
impl From<candle_core::Error> for ResidualError {
    fn from(e: candle_core::Error) -> Self {
        ResidualError::Candle(e)
    }
}
impl From<springs::SimError> for ResidualError {
    fn from(e: springs::SimError) -> Self {
        ResidualError::Sim(e)
    }
}
impl From<scene::SceneError> for ResidualError {
    fn from(e: scene::SceneError) -> Self {
        ResidualError::Scene(e)
    }
}
impl From<dataset::Error> for ResidualError {
    fn from(e: dataset::Error) -> Self {
        ResidualError::Dataset(e)
    }
}

/// Result alias of this crate.
pub type Result<T> = std::result::Result<T, ResidualError>;
