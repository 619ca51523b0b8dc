//! Point-cloud metrics (MDE, Chamfer, exact EMD) and image metrics for deformable-object
//! prediction, matching the values scipy / POT / the `lpips` package compute.
//!
//! # Point clouds
//! All point metrics take slices of `[f32; 3]` or `[f64; 3]` (see [`Point3`]) and compute every
//! distance in `f64`. Results are in the input's units (metres in this project).
//!
//! | function | what it is |
//! | --- | --- |
//! | [`mde`] | mean Euclidean distance between same-index points |
//! | [`chamfer`] | both one-sided nearest-neighbour means (plain and squared), see [`Chamfer`] |
//! | [`emd`] | exact Earth Mover's Distance: optimal one-to-one assignment, mean matched distance |
//!
//! Chamfer conventions differ between projects; [`ChamferConvention`] names each variant and
//! carries the text reports print beside a number. For loops that evaluate many candidate
//! clouds against one target (planning), build a [`PointIndex`] once and reuse it, and reuse an
//! [`EmdSolver`] for its scratch memory.
//!
//! ```
//! use metrics::{chamfer, emd, mde};
//! let pred = [[0.0_f32, 0.0, 0.0], [1.0, 0.0, 0.0]];
//! let gt = [[1.0_f32, 0.0, 0.1], [0.0, 0.0, 0.1]];
//! // Same-index distances are ~1 m, but the clouds are only 0.1 m apart as sets.
//! assert!((mde(&pred, &gt)? - 1.004987562).abs() < 1e-8);
//! let c = chamfer(&pred, &gt)?;
//! assert!((c.pred_to_gt - 0.1).abs() < 1e-7);
//! assert!((c.two_sided_sum() - 0.2).abs() < 1e-7);
//! assert!((emd(&pred, &gt)? - 0.1).abs() < 1e-7);
//! # Ok::<(), metrics::MetricsError>(())
//! ```
//!
//! # Rollouts
//! [`RolloutAggregate`] averages per-step errors the way the paper's tables do.
//!
//! # Images
//! [`image`] has mask IoU (J), the DAVIS boundary F-measure (F), masked PSNR and SSIM; with the
//! `lpips` cargo feature, `lpips` has LPIPS v0.1 (AlexNet) on candle.

mod aggregate;
mod chamfer;
mod emd;
mod emd_graph;
mod error;
pub mod image;
#[cfg(feature = "lpips")]
pub mod lpips;
pub mod lsap;
mod point;
mod sparse_lsap;

pub use aggregate::RolloutAggregate;
pub use chamfer::{Chamfer, ChamferConvention, OneSided, PointIndex, chamfer, chamfer_manhattan};
pub use emd::{Emd, EmdSolver, emd};
pub use error::{Cloud, MetricsError};
pub use point::{Point3, mde};
