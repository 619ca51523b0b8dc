/// Errors of scene building, rollouts and scoring.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// Reading the dataset failed.
    #[error(transparent)]
    Dataset(#[from] dataset::Error),
    /// The simulator refused the input or the rollout diverged.
    #[error("simulation: {0}")]
    Sim(springs::SimError),
    /// A metric could not be computed.
    #[error("metrics: {0}")]
    Metrics(metrics::MetricsError),
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
    /// A `volume` dataset whose tracked points sit on top of one another at the start frame.
    #[error(
        "structure `volume`: at frame {frame} most tracked points lie on top of one another \
         (the median distance to the nearest other point is 0), so no interior spacing follows \
         from them; check the tracking, or declare the dataset's structure `points`"
    )]
    CollapsedVolume {
        /// The start frame.
        frame: usize,
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

// The wrapped error is part of the message, not its source: a report printing the chain of
// causes would otherwise repeat its text.
impl From<springs::SimError> for SceneError {
    fn from(e: springs::SimError) -> Self {
        SceneError::Sim(e)
    }
}
impl From<metrics::MetricsError> for SceneError {
    fn from(e: metrics::MetricsError) -> Self {
        SceneError::Metrics(e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_wrapped_error_is_told_once() {
        let sim = springs::SimError::InvalidParameter {
            name: "spacing_m",
            value: 0.0,
            reason: "must be finite and > 0",
        };
        let e = SceneError::from(sim);
        assert_eq!(
            e.to_string(),
            "simulation: invalid spacing_m = 0: must be finite and > 0"
        );
        assert!(std::error::Error::source(&e).is_none());
    }
}
