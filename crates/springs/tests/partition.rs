//! Split rollouts (`SimConfig::partitions`): the same model as an unsplit one, and bit-identical
//! for any thread count.

mod common;

use glam::Vec3;
use springs::{Actions, Backbone, Dashpot, SimConfig, SpringParams, State};

/// A 300-particle rope lifted by one end while the other end is pushed along the ground, so
/// that springs stretch, the ground acts and the kinematic set is non-empty.
fn scene(partitions: u32, dashpot: Dashpot) -> (Backbone, State, Actions) {
    let x = common::rope(300, 0.5, 0.005, 0.006);
    let held: Vec<i32> = x.iter().map(|p| if p.x < 0.01 { 0 } else { -1 }).collect();
    let cfg = SimConfig {
        partitions,
        dashpot,
        ..SimConfig::default()
    };
    let bb = Backbone::new(&x, &held, SpringParams::reference_rope(), cfg).unwrap();
    let frames: Vec<Vec<Vec3>> = (0..8)
        .map(|t| {
            vec![Vec3::new(
                0.02 * t as f32,
                0.01 * t as f32,
                0.006 + 0.04 * t as f32,
            )]
        })
        .collect();
    let actions = Actions::new(frames, vec![vec![true]; 8]).unwrap();
    (bb, State::at_rest(x), actions)
}

fn bits(r: &springs::Rollout) -> Vec<u32> {
    r.positions
        .iter()
        .chain(&r.velocities)
        .flatten()
        .flat_map(|p| p.to_array().map(f32::to_bits))
        .collect()
}

#[test]
fn split_rollouts_are_identical_for_any_thread_count() {
    for dashpot in [Dashpot::Implicit, Dashpot::Explicit] {
        let (bb, init, actions) = scene(3, dashpot);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| bb.rollout(&init, &actions).unwrap())
        };
        let one = run(1);
        assert_eq!(bits(&one), bits(&run(2)), "{dashpot:?}");
        assert_eq!(bits(&one), bits(&run(3)), "{dashpot:?}");
    }
}

/// Largest distance between corresponding particles over a rollout, m.
fn max_gap(a: &springs::Rollout, b: &springs::Rollout) -> f32 {
    a.positions
        .iter()
        .flatten()
        .zip(b.positions.iter().flatten())
        .map(|(p, q)| p.distance(*q))
        .fold(0.0, f32::max)
}

#[test]
fn split_rollouts_follow_the_same_model() {
    // Explicit dashpot: the split only reorders sums, so the paths agree to float noise.
    let (whole, init, actions) = scene(1, Dashpot::Explicit);
    let reference = whole.rollout(&init, &actions).unwrap();
    for partitions in [2, 4] {
        let (split, _, _) = scene(partitions, Dashpot::Explicit);
        assert_eq!(split.springs().len(), whole.springs().len());
        assert_eq!(split.substeps(), whole.substeps());
        let out = split.rollout(&init, &actions).unwrap();
        assert!(max_gap(&out, &reference) < 1e-6, "{partitions} slabs");
        // The split really changes the order of operations (the bound above would hold
        // trivially if it were ignored).
        assert_ne!(bits(&out), bits(&reference));
    }
    // Implicit dashpot: the Gauss–Seidel order is part of the method (docs/physics.md), so the
    // split changes the result by more than float noise, but the object still follows the
    // same motion: within 8 % of the largest displacement in this violent lift.
    let (whole, init, actions) = scene(1, Dashpot::Implicit);
    let reference = whole.rollout(&init, &actions).unwrap();
    let moved = reference.positions[7]
        .iter()
        .zip(&init.x)
        .map(|(p, q)| p.distance(*q))
        .fold(0.0f32, f32::max);
    for partitions in [2, 4] {
        let (split, _, _) = scene(partitions, Dashpot::Implicit);
        let out = split.rollout(&init, &actions).unwrap();
        let gap = max_gap(&out, &reference);
        assert!(
            gap < 0.08 * moved,
            "{partitions} slabs: {gap} m of {moved} m"
        );
    }
}

#[test]
fn partitions_out_of_range_are_rejected() {
    let x = common::rope(20, 0.1, 0.0, 0.01);
    for bad in [0, 65] {
        let cfg = SimConfig {
            partitions: bad,
            ..SimConfig::default()
        };
        assert!(Backbone::new(&x, &[], SpringParams::reference_rope(), cfg).is_err());
    }
    // More slabs than particles is allowed (some are empty).
    let cfg = SimConfig {
        partitions: 32,
        ..SimConfig::default()
    };
    let bb = Backbone::new(&x, &[], SpringParams::reference_rope(), cfg).unwrap();
    bb.rollout(&State::at_rest(x), &Actions::without_grippers(3))
        .unwrap();
}

#[test]
fn split_of_disconnected_objects_is_bit_identical() {
    // Two ropes 0.5 m apart along x: the slabs are the ropes, no spring crosses, and every
    // particle sees the same springs in the same order as without the split. Any slip in the
    // gather/scatter or sweep bookkeeping would show here.
    let a = common::rope(150, 0.3, 0.005, 0.006);
    let x: Vec<Vec3> = a
        .iter()
        .copied()
        .chain(a.iter().map(|p| *p + Vec3::new(0.8, 0.02, 0.0)))
        .collect();
    let held: Vec<i32> = x.iter().map(|p| if p.x < 0.01 { 0 } else { -1 }).collect();
    let frames: Vec<Vec<Vec3>> = (0..6)
        .map(|t| vec![Vec3::new(0.02 * t as f32, 0.0, 0.006 + 0.04 * t as f32)])
        .collect();
    let actions = Actions::new(frames, vec![vec![true]; 6]).unwrap();
    let run = |partitions| {
        let cfg = SimConfig {
            partitions,
            ..SimConfig::default()
        };
        let bb = Backbone::new(&x, &held, SpringParams::reference_rope(), cfg).unwrap();
        bb.rollout(&State::at_rest(x.clone()), &actions).unwrap()
    };
    assert_eq!(bits(&run(1)), bits(&run(2)));
}

#[test]
fn a_split_rollout_that_blows_up_returns_an_error() {
    // Far too long a fixed substep: the crew must stop and the error come back (no hang).
    let x = common::lattice(6, 3, 3, 0.01, Vec3::new(0.0, 0.0, 0.05));
    let cfg = SimConfig {
        partitions: 2,
        substep: springs::Substep::Fixed { dt: 0.01 },
        ground_z: None,
        ..SimConfig::default()
    };
    let params = SpringParams {
        stiffness: 5e4,
        damping: 0.0,
        threshold: 0.015,
        ..SpringParams::reference_rope()
    };
    let bb = Backbone::new(&x, &[], params, cfg).unwrap();
    let mut init = State::at_rest(x);
    init.x[0].x += 0.003;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let err = pool
        .install(|| bb.rollout(&init, &Actions::without_grippers(200)))
        .unwrap_err();
    assert!(matches!(err, springs::SimError::Diverged { .. }), "{err}");
}
