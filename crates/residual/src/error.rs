use thiserror::Error;

/// Errors of the residual network, its rollouts and its training.
#[derive(Debug, Error)]
pub enum ResidualError {
    /// A tensor operation failed (shapes, I/O of safetensors).
    #[error("tensor operation: {0}")]
    Candle(#[from] candle_core::Error),
    /// The physics backbone refused a step.
    #[error("backbone: {0}")]
    Sim(#[from] springs::SimError),
    /// Building a scene failed.
    #[error("scene: {0}")]
    Scene(#[from] scene::SceneError),
    /// Reading the dataset failed.
    #[error("dataset: {0}")]
    Dataset(#[from] dataset::Error),
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The cause.
        source: std::io::Error,
    },
    /// A JSON file could not be parsed or written.
    #[error("{path}: {source}")]
    Json {
        /// The file.
        path: String,
        /// The cause.
        source: serde_json::Error,
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

/// Result alias of this crate.
pub type Result<T> = std::result::Result<T, ResidualError>;
