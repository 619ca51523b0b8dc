//! Errors of the metric functions.

use std::fmt;

/// Which input of a two-cloud metric an error refers to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cloud {
    /// The predicted cloud (first argument).
    Pred,
    /// The ground-truth cloud (second argument).
    Gt,
}

impl fmt::Display for Cloud {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Cloud::Pred => "prediction",
            Cloud::Gt => "ground truth",
        })
    }
}

/// Everything that can be wrong with the input of a metric.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MetricsError {
    /// A point cloud has no points.
    #[error("the {0} point cloud is empty")]
    Empty(Cloud),
    /// A coordinate is NaN or infinite.
    #[error("the {cloud} point cloud has a non-finite coordinate at point {index}")]
    NonFinite {
        /// The cloud holding the bad point.
        cloud: Cloud,
        /// Index of the first bad point.
        index: usize,
    },
    /// A same-index metric (MDE) got clouds of different sizes.
    #[error(
        "same-index metric needs equal sizes, got {pred} predicted and {gt} ground-truth points"
    )]
    LengthMismatch {
        /// Number of predicted points.
        pred: usize,
        /// Number of ground-truth points.
        gt: usize,
    },
    /// A cloud is too large for the 32-bit point ids used internally.
    #[error("the {0} point cloud has more than 2^32 - 1 points")]
    TooLarge(Cloud),
    /// Exact EMD needed its dense fallback for clouds too large for a dense cost matrix.
    #[error(
        "exact EMD of {rows} x {cols} points needs the dense solver here, whose cost matrix \
         would exceed {max_cells} entries; subsample the clouds"
    )]
    EmdTooLarge {
        /// Points in the smaller cloud.
        rows: usize,
        /// Points in the larger cloud.
        cols: usize,
        /// The largest dense problem attempted.
        max_cells: usize,
    },
    /// An assignment problem got a malformed cost matrix.
    #[error("invalid cost matrix: {0}")]
    InvalidCostMatrix(String),
    /// An image metric got buffers whose sizes do not match the stated dimensions.
    #[error("image buffer has {actual} values, expected {expected} ({what})")]
    ImageSize {
        /// Values in the buffer.
        actual: usize,
        /// Values expected from width x height x channels.
        expected: usize,
        /// Which buffer.
        what: &'static str,
    },
    /// An image metric got a zero-sized image or an unusable parameter.
    #[error("invalid image input: {0}")]
    InvalidImage(String),
    /// A rollout aggregate got no episodes, empty curves, curves of unequal length or NaN.
    #[error("invalid rollout curves: {0}")]
    InvalidCurves(String),
}
