use std::path::PathBuf;

/// Everything that can go wrong building or writing a reference-world dataset.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An object name that is not one of the six.
    #[error("unknown object '{0}' (expected one of: rope, paper, flag, sloth, duster, teddy)")]
    UnknownObject(String),
    /// An effect name that is not in the list.
    #[error(
        "unknown effect '{0}' (expected 'none', 'default' or a comma-separated list of: drag, \
         stiffness-heterogeneity, nonlinear-elasticity, bending, friction, plasticity, \
         actuation-delay, grasp-slip, mass-distribution, magnet, rotating-frame, fan)"
    )]
    UnknownEffect(String),
    /// An effect parameter outside its physical range.
    #[error("effect '{effect}': {message}")]
    EffectParameter {
        /// The effect's name.
        effect: &'static str,
        /// What is wrong.
        message: String,
    },
    /// A generation or observation setting that cannot be used.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// The simulation produced non-finite positions (a bug or absurd parameters).
    #[error("simulation of {object} diverged in recording {recording} at frame {frame}")]
    Diverged {
        /// Object name.
        object: String,
        /// Recording index.
        recording: usize,
        /// Stored frame index.
        frame: usize,
    },
    /// The dataset could not be built or written.
    #[error(transparent)]
    Dataset(#[from] dataset::Error),
    /// A file could not be read or is not what it claims to be.
    #[error("{path}: {message}")]
    Read {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// A file could not be written.
    #[error("{path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
}
