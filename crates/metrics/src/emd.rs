//! Exact Earth Mover's Distance between point clouds via optimal one-to-one assignment.

use rayon::prelude::*;

use crate::emd_graph::CandidateSolver;
use crate::error::{Cloud, MetricsError};
use crate::lsap::LsapSolver;
use crate::point::{Point3, dist2, to_f64_into};

/// Cost-matrix rows per parallel task (each entry is independent, so any split gives the same
/// numbers).
const ROWS_PER_TASK: usize = 32;

/// Problems up to this many point pairs go straight to the dense solver; larger ones try the
/// candidate-graph solver first (same optimum, proven by a dual check, much faster).
const DENSE_MAX_CELLS: usize = 96 * 96;

/// Largest dense fallback (2^27 entries = 1 GiB of costs); beyond it EMD reports an error
/// rather than exhausting memory.
const FALLBACK_MAX_CELLS: usize = 1 << 27;

/// An EMD value with the matching that attains it.
#[derive(Debug, Clone, PartialEq)]
pub struct Emd {
    /// Mean Euclidean distance over the matched pairs, in the input's units.
    pub mean: f64,
    /// Matched `(pred index, gt index)` pairs, sorted by pred index; `min(n, m)` of them.
    pub pairs: Vec<(usize, usize)>,
}

/// Exact EMD solver keeping its cost matrix and assignment scratch between calls, for loops
/// that evaluate many clouds (planning).
///
/// ```
/// let mut solver = metrics::EmdSolver::new();
/// let gt = [[0.0_f64, 0.0, 0.0], [1.0, 0.0, 0.0]];
/// let pred = [[1.0_f64, 0.0, 0.5], [0.0, 0.0, 0.5]];
/// let e = solver.solve(&pred, &gt)?;
/// assert!((e.mean - 0.5).abs() < 1e-12);
/// assert_eq!(e.pairs, vec![(0, 1), (1, 0)]);
/// # Ok::<(), metrics::MetricsError>(())
/// ```
#[derive(Debug, Clone, Default)]
pub struct EmdSolver {
    a: Vec<[f64; 3]>,
    b: Vec<[f64; 3]>,
    cost: Vec<f64>,
    lsap: LsapSolver,
    /// Column of each row in the last solve.
    lsap_rows: Vec<u32>,
    sparse: CandidateSolver,
    /// Large problems that needed the dense solver (for tests).
    dense_fallbacks: usize,
}

impl EmdSolver {
    /// A solver with empty scratch memory.
    pub fn new() -> Self {
        Self::default()
    }

    /// Mean matched Euclidean distance of the optimal one-to-one assignment between `pred` and
    /// `gt` (see [`emd`]).
    ///
    /// # Errors
    /// Empty clouds, non-finite coordinates, or [`MetricsError::EmdTooLarge`].
    pub fn emd<P: Point3>(&mut self, pred: &[P], gt: &[P]) -> Result<f64, MetricsError> {
        self.run(pred, gt).map(|(mean, _)| mean)
    }

    /// As [`EmdSolver::emd`], also returning the matched pairs.
    ///
    /// # Errors
    /// Empty clouds, non-finite coordinates, or [`MetricsError::EmdTooLarge`].
    pub fn solve<P: Point3>(&mut self, pred: &[P], gt: &[P]) -> Result<Emd, MetricsError> {
        let (mean, pred_is_rows) = self.run(pred, gt)?;
        let assignment = &self.lsap_rows;
        let mut pairs: Vec<(usize, usize)> = assignment
            .iter()
            .enumerate()
            .map(|(r, &c)| {
                if pred_is_rows {
                    (r, c as usize)
                } else {
                    (c as usize, r)
                }
            })
            .collect();
        pairs.sort_unstable();
        Ok(Emd { mean, pairs })
    }

    /// Returns the mean and whether `pred` was the row (smaller or equal) side.
    fn run<P: Point3>(&mut self, pred: &[P], gt: &[P]) -> Result<(f64, bool), MetricsError> {
        to_f64_into(pred, Cloud::Pred, &mut self.a)?;
        to_f64_into(gt, Cloud::Gt, &mut self.b)?;
        // The assignment needs rows <= cols: the smaller cloud indexes the rows. EMD is
        // symmetric, so this choice does not change the value.
        let pred_is_rows = self.a.len() <= self.b.len();
        if !pred_is_rows {
            std::mem::swap(&mut self.a, &mut self.b);
        }
        let result = self.solve_rows_cols();
        if !pred_is_rows {
            std::mem::swap(&mut self.a, &mut self.b);
        }
        Ok((result?, pred_is_rows))
    }

    /// Optimal assignment of the points of `self.a` (rows) into `self.b` (columns); fills
    /// `lsap_rows` and returns the mean matched distance.
    fn solve_rows_cols(&mut self) -> Result<f64, MetricsError> {
        let (n, m) = (self.a.len(), self.b.len());
        if n.saturating_mul(m) > DENSE_MAX_CELLS && self.sparse.solve_points(&self.a, &self.b) {
            self.lsap_rows.clear();
            self.lsap_rows.extend_from_slice(&self.sparse.lsap.row_col);
            let sum: f64 = self.sparse.lsap.row_cost.iter().sum();
            return Ok(sum / n as f64);
        }
        self.dense_fallbacks += usize::from(n.saturating_mul(m) > DENSE_MAX_CELLS);
        if n.saturating_mul(m) > FALLBACK_MAX_CELLS {
            return Err(MetricsError::EmdTooLarge {
                rows: n,
                cols: m,
                max_cells: FALLBACK_MAX_CELLS,
            });
        }
        let (rows, cols) = (&self.a, &self.b);
        self.cost.resize(n * m, 0.0);
        self.cost
            .par_chunks_mut(m * ROWS_PER_TASK)
            .enumerate()
            .for_each(|(t, block)| {
                for (r, out) in block.chunks_mut(m).enumerate() {
                    let p = rows[t * ROWS_PER_TASK + r];
                    for (o, q) in out.iter_mut().zip(cols.iter()) {
                        *o = dist2(p, *q).sqrt();
                    }
                }
            });
        let assignment = self.lsap.solve(&self.cost, n, m)?;
        let sum: f64 = assignment
            .iter()
            .enumerate()
            .map(|(i, &j)| self.cost[i * m + j as usize])
            .sum();
        self.lsap_rows.clear();
        self.lsap_rows.extend_from_slice(assignment);
        Ok(sum / n as f64)
    }
}

/// Exact Earth Mover's Distance: the mean Euclidean distance between matched points of the
/// optimal one-to-one assignment (what scipy's `linear_sum_assignment` on the Euclidean cost
/// matrix gives, and POT's `ot.emd2` with uniform weights for equal sizes). In the input's
/// units.
///
/// For clouds of different sizes `n != m` this is the optimal *partial* matching: each point of
/// the smaller cloud is matched to a distinct point of the larger one and the mean is taken
/// over those `min(n, m)` pairs, as the PGRD reference code (scipy on a rectangular matrix)
/// does. It is not the mass-splitting transport distance of `ot.emd2` with uniform weights.
///
/// ```
/// let pred = [[0.0_f32, 0.0, 0.0], [0.0, 0.0, 1.0]];
/// let gt = [[0.0_f32, 0.0, 1.1], [0.0, 0.0, 0.1], [5.0, 5.0, 5.0]];
/// // Partial matching: the far point of gt is left out.
/// assert!((metrics::emd(&pred, &gt)? - 0.1).abs() < 1e-6);
/// # Ok::<(), metrics::MetricsError>(())
/// ```
///
/// # Errors
/// Empty clouds, non-finite coordinates, or [`MetricsError::EmdTooLarge`] (clouds whose
/// product of sizes exceeds 2^27 when the dense fallback is needed).
pub fn emd<P: Point3>(pred: &[P], gt: &[P]) -> Result<f64, MetricsError> {
    EmdSolver::new().emd(pred, gt)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic points in [0, 1)^3 (splitmix64).
    fn cloud(seed: u64, n: usize) -> Vec<[f64; 3]> {
        let mut s = seed;
        let mut next = || {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            (z ^ (z >> 31)) as f64 / 2f64.powi(64)
        };
        (0..n).map(|_| [next(), next(), next()]).collect()
    }

    /// The dense solver on the full cost matrix, as the reference for the graph path.
    fn dense_emd(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
        let (s, l) = if a.len() <= b.len() { (a, b) } else { (b, a) };
        let cost: Vec<f64> = s
            .iter()
            .flat_map(|p| l.iter().map(move |q| dist2(*p, *q).sqrt()))
            .collect();
        let x = crate::lsap::linear_sum_assignment(&cost, s.len(), l.len()).unwrap();
        x.iter()
            .enumerate()
            .map(|(i, &j)| cost[i * l.len() + j])
            .sum::<f64>()
            / s.len() as f64
    }

    fn check(a: &[[f64; 3]], b: &[[f64; 3]]) -> (usize, usize) {
        let mut solver = EmdSolver::new();
        let e = solver.solve(a, b).unwrap();
        let want = dense_emd(a, b);
        assert!(
            (e.mean - want).abs() <= 1e-12 * want,
            "graph {} vs dense {want}",
            e.mean
        );
        let sum: f64 = e.pairs.iter().map(|&(i, j)| dist2(a[i], b[j]).sqrt()).sum();
        assert!((sum / e.pairs.len() as f64 - e.mean).abs() <= 1e-12 * want);
        (solver.sparse.last_rounds, solver.dense_fallbacks)
    }

    #[test]
    fn graph_path_equals_dense_on_independent_clouds() {
        // Unrelated clouds need repair rounds: the first graph misses some optimal pairs.
        let (rounds, fallbacks) = check(&cloud(1, 400), &cloud(2, 400));
        assert_eq!(fallbacks, 0);
        assert!(
            rounds > 1,
            "expected the dual check to add pairs, got {rounds} round(s)"
        );
    }

    #[test]
    fn graph_path_equals_dense_on_perturbed_and_rectangular_clouds() {
        let a = cloud(3, 300);
        let b: Vec<[f64; 3]> = a.iter().rev().map(|p| p.map(|c| c + 0.01)).collect();
        assert_eq!(check(&a, &b).1, 0);
        assert_eq!(check(&cloud(4, 150), &cloud(5, 320)).1, 0);
        assert_eq!(check(&cloud(6, 320), &cloud(7, 150)).1, 0);
    }

    #[test]
    fn graph_path_handles_duplicates() {
        // Every point four times: ties everywhere.
        let base = cloud(8, 60);
        let a: Vec<[f64; 3]> = base.iter().flat_map(|p| [*p; 4]).collect();
        let b: Vec<[f64; 3]> = cloud(9, 240);
        assert_eq!(check(&a, &b).1, 0);
        assert_eq!(check(&a, &a).0, 1);
    }

    #[test]
    fn falls_back_to_dense_when_the_graph_has_no_complete_matching() {
        // All of `a` sits near the origin; half of `b` is far away and every far point's
        // nearest neighbours in `a` are the same few points, so the near-neighbour graph
        // cannot match all rows.
        let a: Vec<[f64; 3]> = cloud(10, 200).iter().map(|p| p.map(|c| 0.01 * c)).collect();
        let mut b: Vec<[f64; 3]> = cloud(11, 100).iter().map(|p| p.map(|c| 0.01 * c)).collect();
        b.extend(
            cloud(12, 100)
                .iter()
                .map(|p| [10.0 + 0.01 * p[0], 0.01 * p[1], 0.01 * p[2]]),
        );
        assert_eq!(check(&a, &b).1, 1);
    }
}
