//! Spring topology: limits, agreement with a brute-force O(N^2) construction, bad input.

mod common;

use glam::{Vec3, Vec3A};
use proptest::prelude::*;
use springs::{AnchorSprings, PairFilter, SimError, Topology};

/// A symmetric filter that rejects about a third of the pairs, pseudo-randomly by `salt`.
#[derive(Debug)]
struct Sieve(u64);

impl Sieve {
    fn keeps(&self, a: usize, b: usize) -> bool {
        let (lo, hi) = (a.min(b) as u64, a.max(b) as u64);
        let h = (lo.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ hi.wrapping_mul(0xC2B2_AE3D_27D4_EB4F))
            .wrapping_add(self.0)
            .wrapping_mul(0x1656_67B1_9E37_79F9);
        (h >> 33) % 3 != 0
    }
}

impl PairFilter for Sieve {
    fn keep(&self, a: usize, b: usize, _threshold: f32) -> bool {
        self.keeps(a, b)
    }
}

/// Independent O(N^2) implementation of the reference rule (see `Topology::build`).
fn brute_force(x: &[Vec3], threshold: f32, max_springs: u32) -> Vec<([u32; 2], f32)> {
    brute_force_keeping(x, threshold, max_springs, &|_, _| true)
}

/// The same, joining only pairs `keep` accepts (see `Topology::build_with`).
fn brute_force_keeping(
    x: &[Vec3],
    threshold: f32,
    max_springs: u32,
    keep: &dyn Fn(usize, usize) -> bool,
) -> Vec<([u32; 2], f32)> {
    let n = x.len();
    let d2 = |i: usize, j: usize| (Vec3A::from(x[j]) - Vec3A::from(x[i])).length_squared();
    let mut cands = Vec::new();
    for i in 0..n {
        let mut near: Vec<(f32, usize)> = (0..n)
            .filter(|&j| j != i && d2(i, j) <= threshold * threshold && keep(i, j))
            .map(|j| (d2(i, j), j))
            .collect();
        near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        near.truncate(max_springs as usize + 3);
        for (d, j) in near {
            cands.push((d, i.min(j), i.max(j)));
        }
    }
    cands.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    cands.dedup_by(|a, b| a.1 == b.1 && a.2 == b.2);
    let mut count = vec![0u32; n];
    let mut out = Vec::new();
    for (_, a, b) in cands {
        if count[a] < max_springs && count[b] < max_springs {
            count[a] += 1;
            count[b] += 1;
            out.push((
                [a as u32, b as u32],
                (Vec3A::from(x[b]) - Vec3A::from(x[a])).length(),
            ));
        }
    }
    out
}

/// Random points; with `grid` they sit on a 5 mm grid, which creates many equal distances.
fn points(seed: u64, n: usize, grid: bool) -> Vec<Vec3> {
    let mut rng = common::Rng::new(seed);
    (0..n)
        .map(|_| {
            let p = rng.vec3(0.03);
            if grid { (p / 0.005).round() * 0.005 } else { p }
        })
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn matches_brute_force(seed in any::<u64>(), n in 0usize..160, grid in any::<bool>(),
                           threshold in 0.002f32..0.03, max_springs in 0u32..40) {
        let x = points(seed, n, grid);
        let topo = Topology::build(&x, threshold, max_springs).unwrap();
        let expected = brute_force(&x, threshold, max_springs);
        let got: Vec<([u32; 2], f32)> =
            topo.springs.iter().copied().zip(topo.rest_lengths.iter().copied()).collect();
        prop_assert_eq!(got, expected);
    }

    #[test]
    fn a_filter_matches_brute_force_without_the_rejected_pairs(
        seed in any::<u64>(), salt in any::<u64>(), n in 0usize..120, grid in any::<bool>(),
        threshold in 0.002f32..0.03, max_springs in 0u32..40,
    ) {
        let x = points(seed, n, grid);
        let sieve = Sieve(salt);
        let topo = Topology::build_with(&x, threshold, max_springs, Some(&sieve)).unwrap();
        let expected = brute_force_keeping(&x, threshold, max_springs, &|a, b| sieve.keeps(a, b));
        let got: Vec<([u32; 2], f32)> =
            topo.springs.iter().copied().zip(topo.rest_lengths.iter().copied()).collect();
        prop_assert_eq!(got, expected);
        // No filter and a filter that keeps everything are the reference rule.
        #[derive(Debug)]
        struct All;
        impl PairFilter for All {
            fn keep(&self, _: usize, _: usize, _: f32) -> bool { true }
        }
        prop_assert_eq!(
            Topology::build_with(&x, threshold, max_springs, Some(&All)).unwrap(),
            Topology::build(&x, threshold, max_springs).unwrap()
        );
    }

    #[test]
    fn anchors_join_by_their_own_rule_and_leave_the_object_as_it_was(
        seed in any::<u64>(), n in 2usize..120, grid in any::<bool>(), picks in 1usize..6,
        threshold in 0.002f32..0.03, max_springs in 0u32..40,
        radius in 0.002f32..0.06, anchor_max in 0u32..60,
    ) {
        let x = points(seed, n, grid);
        // Anchors spread over the indices, as controller points appended to an object would
        // not be: the rule must not depend on where they sit.
        let mut anchors: Vec<u32> = (0..picks).map(|k| ((k * 37 + seed as usize % 11) % n) as u32).collect();
        anchors.sort_unstable();
        anchors.dedup();
        let is_anchor = |i: usize| anchors.contains(&(i as u32));
        let rule = AnchorSprings { particles: anchors.clone().into(), radius_m: radius, max_springs: anchor_max };
        let topo = Topology::build_anchored(&x, threshold, max_springs, None, Some(&rule)).unwrap();
        let got: Vec<([u32; 2], f32)> =
            topo.springs.iter().copied().zip(topo.rest_lengths.iter().copied()).collect();
        // First the object's springs, as if the anchors did not take part ...
        let mut expected =
            brute_force_keeping(&x, threshold, max_springs, &|a, b| !is_anchor(a) && !is_anchor(b));
        // ... then every anchor's nearest non-anchors within its radius, by brute force.
        for &a in &anchors {
            let d2 = |j: usize| (Vec3A::from(x[j]) - Vec3A::from(x[a as usize])).length_squared();
            let mut near: Vec<(f32, usize)> = (0..n)
                .filter(|&j| !is_anchor(j) && d2(j) <= radius * radius)
                .map(|j| (d2(j), j))
                .collect();
            near.sort_by(|p, q| p.0.total_cmp(&q.0).then(p.1.cmp(&q.1)));
            for &(_, j) in near.iter().take(anchor_max as usize) {
                let (lo, hi) = ((a as usize).min(j), (a as usize).max(j));
                expected.push(([lo as u32, hi as u32], (Vec3A::from(x[hi]) - Vec3A::from(x[lo])).length()));
            }
        }
        prop_assert_eq!(got, expected);
    }

    #[test]
    fn respects_limits(seed in any::<u64>(), n in 2usize..200, threshold in 0.002f32..0.05,
                       max_springs in 1u32..30) {
        let x = points(seed, n, false);
        let topo = Topology::build(&x, threshold, max_springs).unwrap();
        for (&[a, b], &l) in topo.springs.iter().zip(&topo.rest_lengths) {
            prop_assert!(a < b && (b as usize) < n);
            prop_assert!(l <= threshold * (1.0 + 1e-6));
            prop_assert!((l - x[a as usize].distance(x[b as usize])).abs() <= 1e-6);
        }
        prop_assert!(topo.springs_per_particle(n).iter().all(|&c| c <= max_springs));
        let mut pairs = topo.springs.clone();
        pairs.sort();
        pairs.dedup();
        prop_assert_eq!(pairs.len(), topo.springs.len(), "duplicate springs");
    }
}

#[test]
fn chain_and_cap() {
    // Five points 1 cm apart: threshold 1.5 cm links neighbours only; 2.5 cm also links i, i+2.
    let x: Vec<Vec3> = (0..5)
        .map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.0))
        .collect();
    let sorted = |t: Topology| {
        let mut s = t.springs;
        s.sort();
        s
    };
    let neighbours = vec![[0, 1], [1, 2], [2, 3], [3, 4]];
    assert_eq!(sorted(Topology::build(&x, 0.015, 10).unwrap()), neighbours);
    assert_eq!(Topology::build(&x, 0.025, 10).unwrap().len(), 7);
    // Max 2 per point: the four short links fill points 1..3, so no 2 cm link fits.
    assert_eq!(sorted(Topology::build(&x, 0.025, 2).unwrap()), neighbours);
    // Max 3: (0,2) and (1,3) fit; (2,4) does not (point 2 is full).
    assert_eq!(
        sorted(Topology::build(&x, 0.025, 3).unwrap()),
        vec![[0, 1], [0, 2], [1, 2], [1, 3], [2, 3], [3, 4]]
    );
}

#[test]
fn many_coincident_points() {
    // A tracker can report many points at one place; more than a k-d tree bucket's worth (32)
    // must still build, and by the same rule (zero-length springs are allowed).
    let mut x = vec![Vec3::new(0.01, 0.02, 0.0); 40];
    x.extend((0..30).map(|i| Vec3::X * (i as f32 * 0.004)));
    for max_springs in [3, 50] {
        let topo = Topology::build(&x, 0.01, max_springs).unwrap();
        let got: Vec<([u32; 2], f32)> = topo
            .springs
            .iter()
            .copied()
            .zip(topo.rest_lengths.iter().copied())
            .collect();
        assert_eq!(got, brute_force(&x, 0.01, max_springs));
    }
}

#[test]
fn bad_input() {
    let x = vec![Vec3::ZERO, Vec3::X];
    assert!(matches!(
        Topology::build(&x, 0.0, 4),
        Err(SimError::InvalidParameter {
            name: "threshold",
            ..
        })
    ));
    assert!(matches!(
        Topology::build(&x, f32::NAN, 4),
        Err(SimError::InvalidParameter { .. })
    ));
    let bad = vec![Vec3::ZERO, Vec3::new(0.0, f32::INFINITY, 0.0)];
    assert_eq!(
        Topology::build(&bad, 0.1, 4),
        Err(SimError::NonFinite {
            what: "positions",
            index: 1
        })
    );
    assert!(Topology::build(&[], 0.1, 4).unwrap().is_empty());
    let x: Vec<Vec3> = (0..3).map(|i| Vec3::X * i as f32 * 0.01).collect();
    let anchored = |particles: Vec<u32>, radius_m: f32| {
        let rule = AnchorSprings {
            particles: particles.into(),
            radius_m,
            max_springs: 4,
        };
        Topology::build_anchored(&x, 0.015, 4, None, Some(&rule))
    };
    for (particles, radius) in [
        (vec![3], 0.04),
        (vec![1, 1], 0.04),
        (vec![1], 0.0),
        (vec![1], f32::NAN),
    ] {
        assert!(
            matches!(
                anchored(particles.clone(), radius),
                Err(SimError::InvalidParameter { .. })
            ),
            "{particles:?} {radius}"
        );
    }
}

#[test]
fn unconnected_free_particles_are_counted() {
    use springs::{Backbone, SimConfig, SpringParams};
    // Points 1 cm apart, then one 10 cm away (free) and one 20 cm away (held).
    let mut x: Vec<Vec3> = (0..4)
        .map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.5))
        .collect();
    x.push(Vec3::new(0.13, 0.0, 0.5));
    x.push(Vec3::new(0.33, 0.0, 0.5));
    let held = vec![0, -1, -1, -1, -1, 0];
    let params = |threshold| SpringParams {
        stiffness: 1000.0,
        damping: 1.0,
        threshold,
        max_springs: 10,
        ground_friction: 0.5,
    };
    let count = |threshold| {
        Backbone::new(&x, &held, params(threshold), SimConfig::default())
            .unwrap()
            .unconnected_free_particles()
    };
    // 1.5 cm links the first four; the lone free point is counted, the lone held one is not.
    assert_eq!(count(0.015), 1);
    // Below the spacing nothing is linked: three free points of the chain plus the lone one.
    assert_eq!(count(0.005), 4);
    // 15 cm reaches the lone free point too.
    assert_eq!(count(0.15), 0);
}
