//! Exact linear sum assignment (minimum-cost one-to-one matching) on dense `f64` costs.
//!
//! The method is Jonker & Volgenant's (1987): column reduction with reduction transfer and two
//! passes of augmenting row reduction give a cheap partial assignment with feasible dual prices,
//! then every row still free is assigned along a shortest augmenting path (Dijkstra on reduced
//! costs), which keeps the duals feasible. The result is optimal, the same guarantee as scipy's
//! `linear_sum_assignment`; it is checked against brute force and LP duality in the tests.
//!
//! Rectangular problems (`rows < cols`) assign every row to a distinct column and leave
//! `cols - rows` columns unused. Column reduction is skipped there because it would give
//! unused columns non-zero prices, which breaks optimality; the other phases keep the
//! rectangular dual conditions (prices `<= 0`, zero on unused columns).
//!
//! ```
//! use metrics::lsap::LsapSolver;
//! // 2 rows x 3 columns, row-major.
//! let cost = [4.0, 1.0, 3.5,
//!             2.0, 0.0, 5.0];
//! let mut solver = LsapSolver::new();
//! let assignment = solver.solve(&cost, 2, 3)?;
//! assert_eq!(assignment, &[1, 0]); // 1 + 2 = 3 beats 4 + 0 and 3.5 + 0
//! # Ok::<(), metrics::MetricsError>(())
//! ```

use crate::error::MetricsError;

/// Marks an unassigned row or column.
const NONE: u32 = u32::MAX;

/// Exact assignment solver holding its scratch memory, so repeated solves of similar size do
/// not allocate.
#[derive(Debug, Clone, Default)]
pub struct LsapSolver {
    /// Column prices (dual variables). Row prices are implicit: `c[i][x_i] - v[x_i]`.
    v: Vec<f64>,
    /// Shortest-path distances to columns during one augmentation.
    d: Vec<f64>,
    /// Row preceding each column on the shortest-path tree.
    pred: Vec<u32>,
    /// Column order during Dijkstra: `[scanned | at current minimum | not yet reached]`.
    perm: Vec<u32>,
    row_col: Vec<u32>,
    col_row: Vec<u32>,
    free: Vec<u32>,
    free_next: Vec<u32>,
    col_min_row: Vec<u32>,
    matches: Vec<u32>,
}

impl LsapSolver {
    /// A solver with empty scratch memory.
    pub fn new() -> Self {
        Self::default()
    }

    /// Solves the assignment problem for a row-major `rows x cols` cost matrix with
    /// `rows <= cols`, returning for each row its column. The total cost
    /// `sum_i cost[i * cols + result[i]]` is minimal over all one-to-one assignments.
    ///
    /// # Errors
    /// `cost.len() != rows * cols`, `rows > cols`, sizes beyond `u32`, or a non-finite cost.
    pub fn solve(
        &mut self,
        cost: &[f64],
        rows: usize,
        cols: usize,
    ) -> Result<&[u32], MetricsError> {
        let bad = |msg: String| Err(MetricsError::InvalidCostMatrix(msg));
        if rows.checked_mul(cols) != Some(cost.len()) {
            return bad(format!(
                "{} values for a {rows} x {cols} matrix",
                cost.len()
            ));
        }
        if rows > cols {
            return bad(format!(
                "{rows} rows > {cols} columns; transpose the matrix"
            ));
        }
        if u32::try_from(cols).is_err() || cols == NONE as usize {
            return bad(format!("{cols} columns exceed the supported size"));
        }
        if let Some(k) = cost.iter().position(|c| !c.is_finite()) {
            return bad(format!(
                "non-finite cost at row {}, column {}",
                k / cols,
                k % cols
            ));
        }
        self.row_col.clear();
        self.row_col.resize(rows, NONE);
        self.col_row.clear();
        self.col_row.resize(cols, NONE);
        self.v.clear();
        self.v.resize(cols, 0.0);
        self.d.resize(cols, 0.0);
        self.pred.resize(cols, 0);
        self.perm.resize(cols, 0);
        self.free.clear();
        if rows == 0 {
            return Ok(&self.row_col);
        }
        if cols == 1 {
            self.row_col[0] = 0;
            self.col_row[0] = 0;
            return Ok(&self.row_col);
        }
        if rows == cols {
            self.column_reduction(cost, rows);
        } else {
            self.free.extend(0..rows as u32);
        }
        self.augmenting_row_reduction(cost, cols);
        let free = std::mem::take(&mut self.free);
        for &f in &free {
            self.augment(cost, cols, f as usize);
        }
        self.free = free;
        Ok(&self.row_col)
    }

    /// Square problems only: price each column at its minimum, assign each column's argmin row
    /// when that row is still free, and move slack from singly-matched rows into the prices.
    fn column_reduction(&mut self, cost: &[f64], n: usize) {
        // Row-major sweep (the matrix is row-major) instead of JV's column-by-column loop.
        self.v.clear();
        self.v.extend_from_slice(&cost[..n]);
        self.col_min_row.clear();
        self.col_min_row.resize(n, 0);
        for i in 1..n {
            let row = &cost[i * n..(i + 1) * n];
            for ((vj, arg), &c) in self.v.iter_mut().zip(self.col_min_row.iter_mut()).zip(row) {
                if c < *vj {
                    *vj = c;
                    *arg = i as u32;
                }
            }
        }
        self.matches.clear();
        self.matches.resize(n, 0);
        for j in 0..n {
            let i = self.col_min_row[j] as usize;
            if self.row_col[i] == NONE {
                self.row_col[i] = j as u32;
                self.col_row[j] = i as u32;
            }
            self.matches[i] += 1;
        }
        for i in 0..n {
            match self.matches[i] {
                0 => self.free.push(i as u32),
                1 => {
                    // Reduction transfer: lower the price of the row's column until it ties with
                    // the row's second-best column; the row keeps its column at minimal reduced
                    // cost, and other rows only see that column become dearer.
                    let j1 = self.row_col[i] as usize;
                    let row = &cost[i * n..(i + 1) * n];
                    let mut mu = f64::INFINITY;
                    for (j, (&c, &vj)) in row.iter().zip(&self.v).enumerate() {
                        if j != j1 && c - vj < mu {
                            mu = c - vj;
                        }
                    }
                    let own = row[j1] - self.v[j1];
                    self.v[j1] -= mu - own;
                }
                _ => {}
            }
        }
    }

    /// Two passes of JV's augmenting row reduction. Invariant kept: every assigned row's column
    /// has the row's minimal reduced cost `c - v`, and prices only decrease.
    fn augmenting_row_reduction(&mut self, cost: &[f64], cols: usize) {
        // With float costs a displaced row can bounce on ever smaller price steps; cap the
        // immediate retries so the phase stays linear-ish. Rows left free go to `augment`,
        // which is exact regardless.
        let mut retries = 8 * cols + 64;
        for _pass in 0..2 {
            let mut cur = std::mem::take(&mut self.free);
            self.free_next.clear();
            let mut k = 0;
            while k < cur.len() {
                let i = cur[k] as usize;
                k += 1;
                let row = &cost[i * cols..(i + 1) * cols];
                let (mut u1, mut u2) = (f64::INFINITY, f64::INFINITY);
                let (mut j1, mut j2) = (0usize, 0usize);
                for (j, (&c, &vj)) in row.iter().zip(&self.v).enumerate() {
                    let h = c - vj;
                    if h < u2 {
                        if h < u1 {
                            u2 = u1;
                            j2 = j1;
                            u1 = h;
                            j1 = j;
                        } else {
                            u2 = h;
                            j2 = j;
                        }
                    }
                }
                let mut i0 = self.col_row[j1];
                let lowers = u1 < u2;
                if lowers {
                    self.v[j1] -= u2 - u1;
                } else if i0 != NONE {
                    // Tie: take the second column instead, so the displaced row (if any)
                    // waits for the next pass rather than cycling.
                    j1 = j2;
                    i0 = self.col_row[j2];
                }
                self.row_col[i] = j1 as u32;
                self.col_row[j1] = i as u32;
                if i0 != NONE {
                    self.row_col[i0 as usize] = NONE;
                    if lowers && retries > 0 {
                        retries -= 1;
                        k -= 1;
                        cur[k] = i0;
                    } else {
                        self.free_next.push(i0);
                    }
                }
            }
            cur.clear();
            self.free = std::mem::replace(&mut self.free_next, cur);
        }
    }

    /// Assigns free row `f` along a shortest augmenting path (Dijkstra over columns on reduced
    /// costs) and updates the prices so they stay feasible.
    fn augment(&mut self, cost: &[f64], cols: usize, f: usize) {
        let v = &mut self.v[..cols];
        let d = &mut self.d[..cols];
        let pred = &mut self.pred[..cols];
        let perm = &mut self.perm[..cols];
        let col_row = &self.col_row[..cols];
        let row = &cost[f * cols..(f + 1) * cols];
        let mut mind = f64::INFINITY;
        let mut kmin = 0;
        for j in 0..cols {
            d[j] = row[j] - v[j];
            pred[j] = f as u32;
            perm[j] = j as u32;
            if d[j] < mind {
                mind = d[j];
                kmin = j;
            }
        }
        // perm[..lo]: scanned columns (final distances <= mind); perm[lo..]: tentative.
        let mut lo = 0;
        let sink = loop {
            perm.swap(lo, kmin);
            let j1 = perm[lo] as usize;
            lo += 1;
            if col_row[j1] == NONE {
                break j1;
            }
            let i = col_row[j1] as usize;
            let ri = &cost[i * cols..(i + 1) * cols];
            // Row i is reached at distance `mind` through its zero-reduced-cost edge to j1.
            let h = ri[j1] - v[j1] - mind;
            // One pass relaxes the edges out of row i and finds the next closest column.
            let mut best = f64::INFINITY;
            let mut kbest = lo;
            for (k, &j) in perm.iter().enumerate().skip(lo) {
                let j = j as usize;
                let mut dj = d[j];
                let cred = ri[j] - v[j] - h;
                if cred < dj {
                    pred[j] = i as u32;
                    // Reduced costs are >= 0, so `cred < mind` only happens by rounding:
                    // clamp to keep the Dijkstra order monotone.
                    dj = cred.max(mind);
                    d[j] = dj;
                }
                if dj < best {
                    best = dj;
                    kbest = k;
                }
            }
            mind = best;
            kmin = kbest;
        };
        for &j in &perm[..lo] {
            let j = j as usize;
            v[j] += d[j] - mind;
        }
        let mut j = sink;
        loop {
            let i = pred[j] as usize;
            self.col_row[j] = i as u32;
            let prev = self.row_col[i];
            self.row_col[i] = j as u32;
            if i == f {
                break;
            }
            j = prev as usize;
        }
    }

    /// Column prices after the last solve (for optimality certificates in tests).
    #[cfg(test)]
    pub(crate) fn prices(&self) -> &[f64] {
        &self.v
    }
}

/// One-shot [`LsapSolver::solve`]: for each row of the row-major `rows x cols` matrix
/// (`rows <= cols`), its column in a minimum-cost one-to-one assignment.
///
/// # Errors
/// As [`LsapSolver::solve`].
pub fn linear_sum_assignment(
    cost: &[f64],
    rows: usize,
    cols: usize,
) -> Result<Vec<usize>, MetricsError> {
    let mut s = LsapSolver::new();
    Ok(s.solve(cost, rows, cols)?
        .iter()
        .map(|&j| j as usize)
        .collect())
}

#[cfg(test)]
#[path = "lsap_tests.rs"]
mod tests;
