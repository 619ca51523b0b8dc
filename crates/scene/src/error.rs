/// Errors of scene building, rollouts and scoring.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// Reading the dataset failed.
    #[error(transparent)]
    Dataset(#[from] dataset::Error),
    /// The simulator refused the input or the rollout diverged.
    #[error("simulation: {0}")]
    Sim(#[from] springs::SimError),
    /// A metric could not be computed.
    #[error("metrics: {0}")]
    Metrics(#[from] metrics::MetricsError),
    /// The episode is too short for the protocol.
    #[error("episode has {frames} frames; the {protocol} protocol needs at least {needed}")]
    TooShort {
        /// Frames in the episode.
        frames: usize,
        /// Frames the protocol needs.
        needed: usize,
        /// Protocol name.
        protocol: &'static str,
    },
    /// The material-neighbour table was learned on another particle count.
    #[error(
        "the material-neighbour table covers {table} tracked points, the episode has {particles}: \
         every episode of a dataset must track the same points"
    )]
    NeighboursMismatch {
        /// Points in the table.
        table: usize,
        /// Tracked points in the episode.
        particles: usize,
    },
    /// Material springs need a pair table learned from the training split.
    #[error(
        "cannot learn material springs from {dataset}: its training split is empty, its episodes \
         disagree on the tracked points, or they track more than {} points",
        dataset::MAX_PAIR_POINTS
    )]
    MaterialPairs {
        /// The dataset's directory.
        dataset: String,
    },
    /// The prediction does not match the scene's window.
    #[error("prediction has {got} steps of {particles} particles, expected {steps} steps")]
    PredictionShape {
        /// Steps given.
        got: usize,
        /// Steps expected.
        steps: usize,
        /// Particles per step given in the first step.
        particles: usize,
    },
}
