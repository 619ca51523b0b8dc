//! Chamfer distances: nearest-neighbour means in each direction, and the named conventions.

use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::{Manhattan, SquaredEuclidean};
use rayon::prelude::*;

use crate::error::{Cloud, MetricsError};
use crate::point::{Point3, dist2, to_f64};

/// Queries per parallel chunk. Fixed (not derived from the thread count) so that the chunk
/// sums, added in chunk order, give bit-identical results with any number of threads.
const CHUNK: usize = 256;

/// Points per k-d tree leaf: 16 measured ~30% faster than kiddo's usual 32 for 1000 points
/// (and faster than 8).
const BUCKET: usize = 16;

/// The k-d tree type used for all nearest-neighbour queries.
pub(crate) type Tree = ImmutableKdTree<f64, u32, 3, BUCKET>;

/// Euclidean-nearest point of `points` (indexed by `tree`) to `q`: (index, squared distance).
#[inline]
fn nearest_in(tree: &Tree, points: &[[f64; 3]], q: &[f64; 3]) -> (usize, f64) {
    let i = tree.nearest_one::<SquaredEuclidean>(q).item as usize;
    // Recomputed here so every metric in the crate uses one distance formula.
    (i, dist2(*q, points[i]))
}

/// Sums over `queries` of the nearest distance and its square, in parallel over fixed chunks.
fn nearest_sums(tree: &Tree, points: &[[f64; 3]], queries: &[[f64; 3]]) -> (f64, f64) {
    let partial: Vec<(f64, f64)> = queries
        .par_chunks(CHUNK)
        .map(|chunk| {
            chunk.iter().fold((0.0, 0.0), |(s, s2), q| {
                let d2 = nearest_in(tree, points, q).1;
                (s + d2.sqrt(), s2 + d2)
            })
        })
        .collect();
    partial
        .iter()
        .fold((0.0, 0.0), |(a, b), (c, d)| (a + c, b + d))
}

/// Means from sums over `n` points.
fn one_sided_from((s, s2): (f64, f64), n: usize) -> OneSided {
    OneSided {
        mean: s / n as f64,
        mean_squared: s2 / n as f64,
    }
}

/// The Chamfer variants used by the projects this one is compared with. Every reported number
/// should carry [`ChamferConvention::label`] so it cannot be mistaken for another variant.
///
/// All variants use nearest neighbours over the whole other cloud (many-to-one), means over the
/// query cloud's points, and the input's units (metres here; squared variants in m²).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ChamferConvention {
    /// Mean Euclidean distance from each predicted point to its nearest ground-truth point
    /// (one-sided, not squared). The PGRD authors' evaluation code.
    PredToGt,
    /// Mean Euclidean distance from each ground-truth point to its nearest predicted point.
    GtToPred,
    /// `PredToGt + GtToPred`: the sum of the two one-sided means (PGND). What this project
    /// reports as `chamfer`.
    TwoSidedSum,
    /// Sum of the two one-sided means of *squared* Euclidean nearest distances (the usual
    /// training loss; units squared).
    TwoSidedSquaredSum,
    /// Mean L1 (Manhattan) distance from each predicted point to its L1-nearest ground-truth
    /// point (one-sided): PhysTwin's evaluation convention.
    PredToGtManhattan,
}

impl ChamferConvention {
    /// A short, unambiguous label to print beside a number, e.g. in JSON output.
    pub fn label(self) -> &'static str {
        match self {
            ChamferConvention::PredToGt => {
                "one-sided pred->gt, mean Euclidean NN distance (PGRD code)"
            }
            ChamferConvention::GtToPred => "one-sided gt->pred, mean Euclidean NN distance",
            ChamferConvention::TwoSidedSum => {
                "two-sided sum of means, mean_pred min|p-g| + mean_gt min|g-p| (PGND)"
            }
            ChamferConvention::TwoSidedSquaredSum => {
                "two-sided sum of means of squared Euclidean NN distances"
            }
            ChamferConvention::PredToGtManhattan => {
                "one-sided pred->gt, mean L1 NN distance (PhysTwin)"
            }
        }
    }

    /// Picks this variant's value out of a [`Chamfer`] result. Returns `None` for
    /// [`ChamferConvention::PredToGtManhattan`], which needs [`chamfer_manhattan`].
    pub fn value(self, c: &Chamfer) -> Option<f64> {
        match self {
            ChamferConvention::PredToGt => Some(c.pred_to_gt),
            ChamferConvention::GtToPred => Some(c.gt_to_pred),
            ChamferConvention::TwoSidedSum => Some(c.two_sided_sum()),
            ChamferConvention::TwoSidedSquaredSum => Some(c.two_sided_squared_sum()),
            ChamferConvention::PredToGtManhattan => None,
        }
    }
}

/// Both one-sided Chamfer means of a prediction against a ground truth, plain and squared.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Chamfer {
    /// Mean over predicted points of the Euclidean distance to the nearest ground-truth point.
    pub pred_to_gt: f64,
    /// Mean over ground-truth points of the Euclidean distance to the nearest predicted point.
    pub gt_to_pred: f64,
    /// As `pred_to_gt` with squared distances (units squared).
    pub pred_to_gt_squared: f64,
    /// As `gt_to_pred` with squared distances (units squared).
    pub gt_to_pred_squared: f64,
}

impl Chamfer {
    fn from_sides(pred_to_gt: OneSided, gt_to_pred: OneSided) -> Self {
        Self {
            pred_to_gt: pred_to_gt.mean,
            gt_to_pred: gt_to_pred.mean,
            pred_to_gt_squared: pred_to_gt.mean_squared,
            gt_to_pred_squared: gt_to_pred.mean_squared,
        }
    }

    /// `pred_to_gt + gt_to_pred` ([`ChamferConvention::TwoSidedSum`]).
    pub fn two_sided_sum(&self) -> f64 {
        self.pred_to_gt + self.gt_to_pred
    }

    /// `pred_to_gt_squared + gt_to_pred_squared` ([`ChamferConvention::TwoSidedSquaredSum`]).
    pub fn two_sided_squared_sum(&self) -> f64 {
        self.pred_to_gt_squared + self.gt_to_pred_squared
    }
}

/// The one-sided nearest-neighbour means of a query cloud against an indexed cloud.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OneSided {
    /// Mean Euclidean distance to the nearest indexed point.
    pub mean: f64,
    /// Mean squared Euclidean distance to the nearest indexed point.
    pub mean_squared: f64,
}

/// A k-d tree over one point cloud, for repeated nearest-neighbour queries against it (e.g. a
/// fixed target evaluated against many candidate predictions in a planner).
///
/// ```
/// use metrics::PointIndex;
/// let target = [[0.0_f32, 0.0, 0.0], [0.0, 0.0, 1.0]];
/// let index = PointIndex::new(&target)?;
/// for shift in [0.1_f32, 0.2] {
///     let candidate = [[shift, 0.0, 0.0]];
///     let d = index.one_sided(&candidate)?.mean; // candidate -> target
///     assert!((d - f64::from(shift)).abs() < 1e-12);
/// }
/// # Ok::<(), metrics::MetricsError>(())
/// ```
#[derive(Debug, Clone)]
pub struct PointIndex {
    points: Vec<[f64; 3]>,
    tree: Tree,
}

impl PointIndex {
    /// Builds the index over `points` (coordinates widened to `f64`).
    ///
    /// # Errors
    /// An empty cloud or a non-finite coordinate (reported as [`Cloud::Gt`]: the indexed cloud
    /// is the reference side).
    pub fn new<P: Point3>(points: &[P]) -> Result<Self, MetricsError> {
        Ok(Self::from_checked(to_f64(points, Cloud::Gt)?))
    }

    fn from_checked(points: Vec<[f64; 3]>) -> Self {
        let tree = Tree::new_from_slice(&points);
        Self { points, tree }
    }

    /// Number of indexed points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Always false: an index is never built over an empty cloud.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The indexed points, widened to `f64`.
    pub fn points(&self) -> &[[f64; 3]] {
        &self.points
    }

    /// Index of the Euclidean-nearest indexed point and its squared distance.
    pub fn nearest(&self, q: [f64; 3]) -> (usize, f64) {
        nearest_in(&self.tree, &self.points, &q)
    }

    /// Nearest-neighbour means from every point of `query` to this index (query -> index).
    ///
    /// # Errors
    /// An empty query or a non-finite coordinate (reported as [`Cloud::Pred`]).
    pub fn one_sided<P: Point3>(&self, query: &[P]) -> Result<OneSided, MetricsError> {
        let q = to_f64(query, Cloud::Pred)?;
        Ok(self.one_sided_checked(&q))
    }

    fn one_sided_checked(&self, q: &[[f64; 3]]) -> OneSided {
        one_sided_from(nearest_sums(&self.tree, &self.points, q), q.len())
    }

    /// Both Chamfer directions between `pred` and this index (the ground truth). A tree over
    /// `pred` is built internally for the gt -> pred direction.
    ///
    /// # Errors
    /// An empty prediction or a non-finite coordinate.
    pub fn chamfer<P: Point3>(&self, pred: &[P]) -> Result<Chamfer, MetricsError> {
        let p = to_f64(pred, Cloud::Pred)?;
        Ok(self.chamfer_checked(p))
    }

    fn chamfer_checked(&self, pred: Vec<[f64; 3]>) -> Chamfer {
        // The two directions are independent: one per thread when two are available.
        let (fwd, bwd) = rayon::join(
            || self.one_sided_checked(&pred),
            || PointIndex::from_checked(pred.clone()).one_sided_checked(&self.points),
        );
        Chamfer::from_sides(fwd, bwd)
    }
}

/// Both one-sided Chamfer means (plain and squared) between a prediction and a ground truth.
/// The clouds may differ in size. See [`ChamferConvention`] for which combination to report.
///
/// ```
/// let pred = [[0.0_f64, 0.0, 0.0], [2.0, 0.0, 0.0]];
/// let gt = [[0.0_f64, 0.0, 0.0]];
/// let c = metrics::chamfer(&pred, &gt)?;
/// assert_eq!(c.pred_to_gt, 1.0); // (0 + 2) / 2
/// assert_eq!(c.gt_to_pred, 0.0);
/// assert_eq!(c.two_sided_sum(), 1.0);
/// assert_eq!(c.two_sided_squared_sum(), 2.0); // (0 + 4) / 2 + 0
/// # Ok::<(), metrics::MetricsError>(())
/// ```
///
/// # Errors
/// Empty clouds or non-finite coordinates.
pub fn chamfer<P: Point3>(pred: &[P], gt: &[P]) -> Result<Chamfer, MetricsError> {
    let p = to_f64(pred, Cloud::Pred)?;
    let g = to_f64(gt, Cloud::Gt)?;
    // Each side builds its tree and answers the other side's queries on its own thread.
    let (fwd, bwd) = rayon::join(
        || PointIndex::from_checked(g.clone()).one_sided_checked(&p),
        || PointIndex::from_checked(p.clone()).one_sided_checked(&g),
    );
    Ok(Chamfer::from_sides(fwd, bwd))
}

/// One-sided pred -> gt Chamfer with L1 (Manhattan) point distances: for every predicted point
/// the smallest `|dx| + |dy| + |dz|` to a ground-truth point, averaged
/// ([`ChamferConvention::PredToGtManhattan`], PhysTwin's convention).
///
/// # Errors
/// Empty clouds or non-finite coordinates.
pub fn chamfer_manhattan<P: Point3>(pred: &[P], gt: &[P]) -> Result<f64, MetricsError> {
    let p = to_f64(pred, Cloud::Pred)?;
    let g = to_f64(gt, Cloud::Gt)?;
    let tree = Tree::new_from_slice(&g);
    let partial: Vec<f64> = p
        .par_chunks(CHUNK)
        .map(|chunk| {
            chunk
                .iter()
                .map(|q| {
                    let h = g[tree.nearest_one::<Manhattan>(q).item as usize];
                    (q[0] - h[0]).abs() + (q[1] - h[1]).abs() + (q[2] - h[2]).abs()
                })
                .sum::<f64>()
        })
        .collect();
    Ok(partial.iter().sum::<f64>() / p.len() as f64)
}
