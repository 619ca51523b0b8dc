//! Properties of the point metrics (proptest) and comparisons with brute force.

use metrics::{Cloud, EmdSolver, MetricsError, PointIndex, chamfer, chamfer_manhattan, emd, mde};
use proptest::prelude::*;

type P = [f64; 3];

fn d(a: P, b: P) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn brute_one_sided(q: &[P], r: &[P], dist: impl Fn(P, P) -> f64) -> f64 {
    q.iter()
        .map(|&p| r.iter().map(|&s| dist(p, s)).fold(f64::INFINITY, f64::min))
        .sum::<f64>()
        / q.len() as f64
}

/// Optimal partial matching of the smaller cloud into the larger, by exhaustive search.
fn brute_emd(a: &[P], b: &[P]) -> f64 {
    let (s, l) = if a.len() <= b.len() { (a, b) } else { (b, a) };
    fn rec(s: &[P], l: &[P], i: usize, used: &mut Vec<bool>) -> f64 {
        if i == s.len() {
            return 0.0;
        }
        let mut best = f64::INFINITY;
        for j in 0..l.len() {
            if !used[j] {
                used[j] = true;
                best = best.min(d(s[i], l[j]) + rec(s, l, i + 1, used));
                used[j] = false;
            }
        }
        best
    }
    rec(s, l, 0, &mut vec![false; l.len()]) / s.len() as f64
}

fn close(a: f64, b: f64, rel: f64) -> bool {
    (a - b).abs() <= rel * a.abs().max(b.abs()) + 1e-14
}

fn point() -> impl Strategy<Value = P> {
    [-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0]
}

fn cloud(sizes: std::ops::RangeInclusive<usize>) -> impl Strategy<Value = Vec<P>> {
    proptest::collection::vec(point(), sizes)
}

/// Coordinates from {0, 0.5, 1}: many duplicate points and ties, more points than a k-d leaf.
fn lattice_cloud(sizes: std::ops::RangeInclusive<usize>) -> impl Strategy<Value = Vec<P>> {
    proptest::collection::vec([0u8..3, 0u8..3, 0u8..3], sizes).prop_map(|v| {
        v.into_iter()
            .map(|p| p.map(|c| f64::from(c) * 0.5))
            .collect()
    })
}

/// A permutation of 0..n from a seed (Fisher-Yates on a splitmix64 stream).
fn permutation(n: usize, seed: u64) -> Vec<usize> {
    let mut s = seed;
    let mut next = || {
        s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    let mut p: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        p.swap(i, (next() % (i as u64 + 1)) as usize);
    }
    p
}

fn permuted(v: &[P], seed: u64) -> Vec<P> {
    permutation(v.len(), seed)
        .into_iter()
        .map(|i| v[i])
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn identical_clouds_give_zero(a in cloud(1..=120)) {
        let c = chamfer(&a, &a).unwrap();
        prop_assert_eq!(c.two_sided_sum(), 0.0);
        prop_assert_eq!(c.two_sided_squared_sum(), 0.0);
        prop_assert_eq!(emd(&a, &a).unwrap(), 0.0);
        prop_assert_eq!(mde(&a, &a).unwrap(), 0.0);
        // Order does not matter for the set metrics.
        let b = permuted(&a, 7);
        prop_assert_eq!(chamfer(&a, &b).unwrap().two_sided_sum(), 0.0);
        prop_assert_eq!(emd(&a, &b).unwrap(), 0.0);
    }

    #[test]
    fn chamfer_matches_brute_force(a in cloud(1..=150), b in cloud(1..=150)) {
        let c = chamfer(&a, &b).unwrap();
        prop_assert!(close(c.pred_to_gt, brute_one_sided(&a, &b, d), 1e-12));
        prop_assert!(close(c.gt_to_pred, brute_one_sided(&b, &a, d), 1e-12));
        let sq = |p, q| d(p, q).powi(2);
        prop_assert!(close(c.pred_to_gt_squared, brute_one_sided(&a, &b, sq), 1e-12));
        prop_assert!(close(c.gt_to_pred_squared, brute_one_sided(&b, &a, sq), 1e-12));
        let l1 = |p: P, q: P| (p[0] - q[0]).abs() + (p[1] - q[1]).abs() + (p[2] - q[2]).abs();
        prop_assert!(close(chamfer_manhattan(&a, &b).unwrap(), brute_one_sided(&a, &b, l1), 1e-12));
    }

    #[test]
    fn chamfer_with_duplicates_matches_brute_force(a in lattice_cloud(1..=200), b in lattice_cloud(1..=200)) {
        let c = chamfer(&a, &b).unwrap();
        prop_assert!(close(c.pred_to_gt, brute_one_sided(&a, &b, d), 1e-12));
        prop_assert!(close(c.gt_to_pred, brute_one_sided(&b, &a, d), 1e-12));
        prop_assert!(close(emd(&a, &b).unwrap(), emd(&b, &a).unwrap(), 1e-12));
    }

    #[test]
    fn emd_matches_brute_force(a in cloud(1..=6), b in cloud(1..=6)) {
        let mut s = EmdSolver::new();
        let e = s.solve(&a, &b).unwrap();
        prop_assert!(close(e.mean, brute_emd(&a, &b), 1e-12));
        // The returned pairs are a valid matching that attains the value.
        prop_assert_eq!(e.pairs.len(), a.len().min(b.len()));
        let mut used_a = vec![false; a.len()];
        let mut used_b = vec![false; b.len()];
        let mut sum = 0.0;
        for &(i, j) in &e.pairs {
            prop_assert!(!used_a[i] && !used_b[j]);
            used_a[i] = true;
            used_b[j] = true;
            sum += d(a[i], b[j]);
        }
        prop_assert!(close(sum / e.pairs.len() as f64, e.mean, 1e-12));
    }

    #[test]
    fn symmetry_and_order_invariance(a in cloud(1..=80), b in cloud(1..=80), seed in 0u64..1000) {
        let ab = chamfer(&a, &b).unwrap();
        let ba = chamfer(&b, &a).unwrap();
        prop_assert!(close(ab.pred_to_gt, ba.gt_to_pred, 1e-12));
        prop_assert!(close(ab.gt_to_pred, ba.pred_to_gt, 1e-12));
        prop_assert!(close(ab.two_sided_sum(), ba.two_sided_sum(), 1e-12));
        let e = emd(&a, &b).unwrap();
        prop_assert!(close(e, emd(&b, &a).unwrap(), 1e-9));
        let (pa, pb) = (permuted(&a, seed), permuted(&b, seed + 1));
        let pc = chamfer(&pa, &pb).unwrap();
        prop_assert!(close(ab.pred_to_gt, pc.pred_to_gt, 1e-12));
        prop_assert!(close(ab.gt_to_pred, pc.gt_to_pred, 1e-12));
        prop_assert!(close(e, emd(&pa, &pb).unwrap(), 1e-9));
    }

    /// For equal sizes every point's matched distance is at least its nearest-neighbour
    /// distance, so EMD >= both one-sided means; the identity matching is feasible, so
    /// EMD <= MDE; and MDE >= both one-sided means.
    #[test]
    fn ordering_equal_sizes((a, b) in (1usize..=100).prop_flat_map(|n| (cloud(n..=n), cloud(n..=n)))) {
        let c = chamfer(&a, &b).unwrap();
        let e = emd(&a, &b).unwrap();
        let m = mde(&a, &b).unwrap();
        let eps = 1e-12;
        prop_assert!(e + eps >= c.pred_to_gt.max(c.gt_to_pred));
        prop_assert!(e <= m + eps);
        prop_assert!(m + eps >= c.pred_to_gt);
        prop_assert!(m + eps >= c.gt_to_pred);
        // Same-index distances are not order invariant: MDE is only symmetric in its arguments.
        prop_assert!(close(m, mde(&b, &a).unwrap(), 1e-12));
    }

    /// Different sizes: only the smaller cloud's points are all matched, so EMD bounds the
    /// one-sided mean from the smaller cloud (not the other direction).
    #[test]
    fn ordering_rectangular(a in cloud(1..=60), b in cloud(61..=90)) {
        let c = chamfer(&a, &b).unwrap();
        prop_assert!(emd(&a, &b).unwrap() + 1e-12 >= c.pred_to_gt);
    }

    #[test]
    fn translation_invariance(a in cloud(1..=60), b in cloud(1..=60), t in point()) {
        let shift = |v: &[P]| -> Vec<P> { v.iter().map(|p| [p[0] + t[0], p[1] + t[1], p[2] + t[2]]).collect() };
        let (sa, sb) = (shift(&a), shift(&b));
        prop_assert!(close(chamfer(&a, &b).unwrap().two_sided_sum(), chamfer(&sa, &sb).unwrap().two_sided_sum(), 1e-9));
        prop_assert!(close(emd(&a, &b).unwrap(), emd(&sa, &sb).unwrap(), 1e-9));
    }
}

#[test]
fn same_numbers_with_any_thread_count() {
    let a: Vec<P> = (0..1500)
        .map(|i| {
            let t = i as f64 * 0.37;
            [t.sin(), (1.3 * t).cos(), (0.7 * t).sin() * 0.5]
        })
        .collect();
    let b: Vec<P> = (0..1100)
        .map(|i| {
            let t = i as f64 * 0.53;
            [(t + 0.1).sin(), (1.1 * t).cos(), (0.9 * t).cos() * 0.4]
        })
        .collect();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            (
                chamfer(&a, &b).unwrap(),
                emd(&a, &b).unwrap(),
                chamfer_manhattan(&a, &b).unwrap(),
            )
        })
    };
    let one = run(1);
    assert_eq!(one, run(2));
    assert_eq!(one, run(3));
}

#[test]
fn point_index_is_reusable() {
    let gt: Vec<P> = (0..300).map(|i| [i as f64 * 0.01, 0.0, 0.0]).collect();
    let index = PointIndex::new(&gt).unwrap();
    assert_eq!(index.len(), 300);
    for k in 0..5 {
        let pred: Vec<P> = (0..200)
            .map(|i| [i as f64 * 0.013, 0.001 * k as f64, 0.0])
            .collect();
        assert_eq!(index.chamfer(&pred).unwrap(), chamfer(&pred, &gt).unwrap());
        // Same value; the summation order may differ (tree order vs input order).
        let one = index.one_sided(&pred).unwrap();
        assert!(close(
            one.mean,
            chamfer(&pred, &gt).unwrap().pred_to_gt,
            1e-12
        ));
    }
    let (i, d2) = index.nearest([0.052, 0.0, 0.0]);
    assert_eq!(i, 5);
    assert!((d2 - 0.002f64.powi(2)).abs() < 1e-15);
}

#[test]
fn clear_errors() {
    let good = [[0.0f64, 0.0, 0.0]];
    let empty: [P; 0] = [];
    let nan = [[0.0, 0.0, 0.0], [0.0, f64::NAN, 0.0]];
    let inf = [[f64::INFINITY, 0.0, 0.0]];
    assert_eq!(
        chamfer(&empty, &good).unwrap_err(),
        MetricsError::Empty(Cloud::Pred)
    );
    assert_eq!(
        chamfer(&good, &empty).unwrap_err(),
        MetricsError::Empty(Cloud::Gt)
    );
    assert_eq!(
        emd(&good, &empty).unwrap_err(),
        MetricsError::Empty(Cloud::Gt)
    );
    assert_eq!(
        emd(&nan, &good).unwrap_err(),
        MetricsError::NonFinite {
            cloud: Cloud::Pred,
            index: 1
        }
    );
    assert_eq!(
        chamfer(&good, &inf).unwrap_err(),
        MetricsError::NonFinite {
            cloud: Cloud::Gt,
            index: 0
        }
    );
    assert_eq!(
        mde(&nan, &good).unwrap_err(),
        MetricsError::LengthMismatch { pred: 2, gt: 1 }
    );
    assert!(PointIndex::new(&empty).is_err());
    let msg = emd(&nan, &good).unwrap_err().to_string();
    assert!(
        msg.contains("prediction") && msg.contains("point 1"),
        "{msg}"
    );
}
