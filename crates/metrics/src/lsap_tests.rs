//! Tests of the assignment solver: brute force on small sizes, LP-duality certificates on
//! larger ones, degenerate (tied) costs, and input errors.

use super::*;
use proptest::prelude::*;

/// Minimum total cost over all injective row -> column maps, by exhaustive search.
fn brute_force(cost: &[f64], rows: usize, cols: usize) -> f64 {
    fn rec(cost: &[f64], cols: usize, rows: usize, i: usize, used: &mut Vec<bool>) -> f64 {
        if i == rows {
            return 0.0;
        }
        let mut best = f64::INFINITY;
        for j in 0..cols {
            if !used[j] {
                used[j] = true;
                best = best.min(cost[i * cols + j] + rec(cost, cols, rows, i + 1, used));
                used[j] = false;
            }
        }
        best
    }
    rec(cost, cols, rows, 0, &mut vec![false; cols])
}

fn total(cost: &[f64], cols: usize, a: &[u32]) -> f64 {
    a.iter()
        .enumerate()
        .map(|(i, &j)| cost[i * cols + j as usize])
        .sum()
}

fn assert_injective(a: &[u32], cols: usize) {
    let mut seen = vec![false; cols];
    for &j in a {
        assert!((j as usize) < cols, "column {j} out of range");
        assert!(!seen[j as usize], "column {j} used twice");
        seen[j as usize] = true;
    }
}

/// LP-duality certificate: with row prices `u_i = c[i][x_i] - v[x_i]`, every reduced cost
/// `c - u - v` must be >= 0, and (rectangular) prices must be <= 0 and 0 on unused columns.
/// Then no assignment can be cheaper, whatever produced the prices.
fn assert_certificate(s: &LsapSolver, cost: &[f64], rows: usize, cols: usize, tol: f64) {
    let a = s.row_col.clone();
    let v = s.prices();
    for i in 0..rows {
        let xi = a[i] as usize;
        let u = cost[i * cols + xi] - v[xi];
        for j in 0..cols {
            let red = cost[i * cols + j] - u - v[j];
            assert!(red >= -tol, "reduced cost {red} < 0 at ({i}, {j})");
        }
    }
    if rows < cols {
        let mut used = vec![false; cols];
        for &j in &a {
            used[j as usize] = true;
        }
        for j in 0..cols {
            assert!(v[j] <= tol, "price {} > 0 at column {j}", v[j]);
            if !used[j] {
                assert!(v[j].abs() <= tol, "unused column {j} has price {}", v[j]);
            }
        }
    }
}

/// Deterministic pseudo-random numbers in [0, 1) (splitmix64), so these tests need no RNG crate.
fn uniform(seed: u64, n: usize) -> Vec<f64> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            (z ^ (z >> 31)) as f64 / 2f64.powi(64)
        })
        .collect()
}

fn euclidean_cost(a: &[f64], b: &[f64]) -> Vec<f64> {
    let mut c = Vec::new();
    for p in a.chunks(3) {
        for q in b.chunks(3) {
            let d2: f64 = p.iter().zip(q).map(|(x, y)| (x - y) * (x - y)).sum();
            c.push(d2.sqrt());
        }
    }
    c
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn matches_brute_force_real_costs(
        (rows, cols, cost) in (1usize..=6, 0usize..=2).prop_flat_map(|(r, extra)| {
            let c = r + extra;
            (Just(r), Just(c), proptest::collection::vec(0.0f64..10.0, r * c))
        })
    ) {
        let mut s = LsapSolver::new();
        let a = s.solve(&cost, rows, cols).unwrap().to_vec();
        assert_injective(&a, cols);
        let best = brute_force(&cost, rows, cols);
        prop_assert!((total(&cost, cols, &a) - best).abs() <= 1e-9 * (1.0 + best));
        assert_certificate(&s, &cost, rows, cols, 1e-9);
    }

    /// Small integer costs produce many ties, the hard case for the tie handling.
    #[test]
    fn matches_brute_force_tied_costs(
        (rows, cols, cost) in (1usize..=6, 0usize..=2).prop_flat_map(|(r, extra)| {
            let c = r + extra;
            (Just(r), Just(c), proptest::collection::vec(0u8..4, r * c))
        })
    ) {
        let cost: Vec<f64> = cost.into_iter().map(f64::from).collect();
        let mut s = LsapSolver::new();
        let a = s.solve(&cost, rows, cols).unwrap().to_vec();
        assert_injective(&a, cols);
        prop_assert_eq!(total(&cost, cols, &a), brute_force(&cost, rows, cols));
    }

    #[test]
    fn reused_solver_gives_same_result(seed in 0u64..1000, n in 2usize..40) {
        let cost = uniform(seed, n * n);
        let fresh = linear_sum_assignment(&cost, n, n).unwrap();
        let mut s = LsapSolver::new();
        // Dirty the scratch with a different (rectangular) problem first.
        s.solve(&uniform(seed + 1, 3 * (n + 5)), 3, n + 5).unwrap();
        let again: Vec<usize> = s.solve(&cost, n, n).unwrap().iter().map(|&j| j as usize).collect();
        prop_assert_eq!(fresh, again);
    }
}

#[test]
fn certificate_on_larger_euclidean_problems() {
    let mut s = LsapSolver::new();
    for (seed, rows, cols) in [(1, 300, 300), (2, 200, 300), (3, 299, 300), (4, 1, 50)] {
        let a = uniform(seed, 3 * rows);
        let b = uniform(seed + 100, 3 * cols);
        let cost = euclidean_cost(&a, &b);
        let x = s.solve(&cost, rows, cols).unwrap().to_vec();
        assert_injective(&x, cols);
        assert_certificate(&s, &cost, rows, cols, 1e-9);
    }
}

#[test]
fn certificate_on_uniform_random_costs() {
    let mut s = LsapSolver::new();
    for (seed, n) in [(7, 250), (8, 64)] {
        let cost = uniform(seed, n * n);
        let x = s.solve(&cost, n, n).unwrap().to_vec();
        assert_injective(&x, n);
        assert_certificate(&s, &cost, n, n, 1e-9);
    }
}

#[test]
fn all_equal_costs() {
    let n = 50;
    let cost = vec![1.5; n * n];
    let x = linear_sum_assignment(&cost, n, n).unwrap();
    let mut seen = vec![false; n];
    for j in x {
        assert!(!seen[j]);
        seen[j] = true;
    }
}

#[test]
fn rejects_bad_input() {
    let mut s = LsapSolver::new();
    assert!(matches!(
        s.solve(&[1.0; 5], 2, 3),
        Err(MetricsError::InvalidCostMatrix(_))
    ));
    assert!(matches!(
        s.solve(&[1.0; 6], 3, 2),
        Err(MetricsError::InvalidCostMatrix(_))
    ));
    assert!(matches!(
        s.solve(&[1.0, f64::NAN, 0.0, 0.0], 2, 2),
        Err(MetricsError::InvalidCostMatrix(m)) if m.contains("row 0, column 1")
    ));
    assert_eq!(s.solve(&[], 0, 4).unwrap(), &[] as &[u32]);
}
