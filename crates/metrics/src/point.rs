//! Point type accepted by the metrics, input validation and the same-index error (MDE).

use crate::error::{Cloud, MetricsError};

/// A 3-D point the metrics accept: `[f32; 3]` or `[f64; 3]`. Coordinates are widened to `f64`
/// before any arithmetic, so both give the same numbers for the same values.
pub trait Point3: Copy + Send + Sync {
    /// The coordinates as `f64`.
    fn xyz(self) -> [f64; 3];
}

impl Point3 for [f32; 3] {
    #[inline]
    fn xyz(self) -> [f64; 3] {
        [f64::from(self[0]), f64::from(self[1]), f64::from(self[2])]
    }
}

impl Point3 for [f64; 3] {
    #[inline]
    fn xyz(self) -> [f64; 3] {
        self
    }
}

/// Squared Euclidean distance in `f64`.
#[inline]
pub(crate) fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    let dx = a[0] - b[0];
    let dy = a[1] - b[1];
    let dz = a[2] - b[2];
    dx * dx + dy * dy + dz * dz
}

/// Widens a cloud to `f64`, rejecting empty clouds and non-finite coordinates.
pub(crate) fn to_f64<P: Point3>(points: &[P], cloud: Cloud) -> Result<Vec<[f64; 3]>, MetricsError> {
    let mut out = Vec::with_capacity(points.len());
    to_f64_into(points, cloud, &mut out)?;
    Ok(out)
}

/// As [`to_f64`], writing into a reused buffer.
pub(crate) fn to_f64_into<P: Point3>(
    points: &[P],
    cloud: Cloud,
    out: &mut Vec<[f64; 3]>,
) -> Result<(), MetricsError> {
    if points.is_empty() {
        return Err(MetricsError::Empty(cloud));
    }
    if u32::try_from(points.len()).is_err() {
        return Err(MetricsError::TooLarge(cloud));
    }
    out.clear();
    for (index, p) in points.iter().enumerate() {
        let q = p.xyz();
        if !q.iter().all(|c| c.is_finite()) {
            return Err(MetricsError::NonFinite { cloud, index });
        }
        out.push(q);
    }
    Ok(())
}

/// Mean distance error: the mean Euclidean distance between same-index points, in the input's
/// units. This is the PGRD code's MDE (the paper reports it in cm).
///
/// ```
/// let pred = [[0.0_f64, 0.0, 0.0], [1.0, 1.0, 1.0]];
/// let gt = [[0.0_f64, 0.0, 0.3], [1.0, 1.4, 1.0]];
/// assert!((metrics::mde(&pred, &gt)? - 0.35).abs() < 1e-12);
/// # Ok::<(), metrics::MetricsError>(())
/// ```
///
/// # Errors
/// Empty clouds, different sizes, or non-finite coordinates.
pub fn mde<P: Point3>(pred: &[P], gt: &[P]) -> Result<f64, MetricsError> {
    if pred.len() != gt.len() {
        return Err(MetricsError::LengthMismatch {
            pred: pred.len(),
            gt: gt.len(),
        });
    }
    let a = to_f64(pred, Cloud::Pred)?;
    let b = to_f64(gt, Cloud::Gt)?;
    let sum: f64 = a.iter().zip(&b).map(|(p, q)| dist2(*p, *q).sqrt()).sum();
    Ok(sum / a.len() as f64)
}
