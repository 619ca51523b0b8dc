//! PGRD evaluates a planner's population in one batched pass through its network: the same
//! predictions as one rollout per candidate, a failing candidate fails alone, and the plan does
//! not depend on the thread count.

use std::sync::Arc;

use glam::Vec3;
use plan::{ForwardModel, ModelState, Mppi, MppiConfig, Objective, Pgrd, Workspace};
use residual::ResidualNet;
use springs::{Actions, Backbone, SimConfig, SpringParams};

/// A 40-particle chain 6 mm apart on the table, its first three particles held by gripper 0.
fn chain() -> (Backbone, ModelState) {
    let x: Vec<Vec3> = (0..40)
        .map(|i| Vec3::new(0.006 * i as f32, 0.01 * (i as f32 * 0.3).sin(), 0.01))
        .collect();
    let held: Vec<i32> = (0..40).map(|i| if i < 3 { 0 } else { -1 }).collect();
    let params = SpringParams {
        threshold: 0.02,
        ..SpringParams::reference_rope()
    };
    let backbone = Backbone::new(&x, &held, params, SimConfig::default()).unwrap();
    (backbone, ModelState::at_rest(x))
}

/// The chain with a tiny network of seed `seed`.
fn net(seed: u64) -> ResidualNet {
    ResidualNet::new(&residual::ModelConfig::tiny(), seed).unwrap()
}

fn model() -> (Pgrd, ModelState) {
    let (backbone, state) = chain();
    (Pgrd::new(backbone, Arc::new(net(1))), state)
}

/// The gripper moving from `from` by `step` per frame, `steps` steps.
fn path(from: Vec3, step: Vec3, steps: usize) -> Actions {
    Actions::new(
        (0..=steps).map(|t| vec![from + step * t as f32]).collect(),
        vec![vec![true]; steps + 1],
    )
    .unwrap()
}

#[test]
fn batched_candidates_match_single_rollouts_and_fail_alone() {
    let (model, state) = model();
    let g = state.x[0];
    let candidates = vec![
        path(g, Vec3::new(0.0, 0.0, 0.01), 6),
        path(g, Vec3::new(0.01, 0.005, 0.0), 6),
        // No gripper, but particles held by gripper 0: the backbone refuses this candidate.
        Actions::without_grippers(7),
        path(g, Vec3::new(-0.005, 0.01, 0.005), 4),
    ];
    let batch = model.rollout_batch(&state, &candidates);
    assert_eq!(batch.len(), candidates.len());
    let err = batch[2].as_ref().unwrap_err().to_string();
    assert!(err.contains("gripper"), "{err}");
    for k in [0, 1, 3] {
        let single = model.rollout(&state, &candidates[k]).unwrap();
        let b = batch[k].as_ref().unwrap();
        assert_eq!(b.len(), single.len());
        let worst = b
            .iter()
            .flatten()
            .zip(single.iter().flatten())
            .map(|(p, q)| p.distance(*q))
            .fold(0.0, f32::max);
        assert!(worst <= 1e-6, "candidate {k}: {worst} m apart");
    }
    // The candidates do differ (the comparison above could fail).
    let a = batch[0].as_ref().unwrap();
    let b = batch[1].as_ref().unwrap();
    assert!(a[5][20].distance(b[5][20]) > 1e-4);
}

#[test]
fn pgrd_plans_the_same_for_any_thread_count() {
    let (model, state) = model();
    let ws = Workspace {
        min: Vec3::new(-1.0, -1.0, 0.005),
        max: Vec3::splat(1.0),
    };
    let target: Vec<Vec3> = state
        .x
        .iter()
        .map(|p| *p + Vec3::new(0.0, 0.1, 0.05))
        .collect();
    let objective = Objective::new(&target, ws).unwrap();
    let cfg = MppiConfig {
        samples: 5,
        horizon: 4,
        iterations: 2,
        ..MppiConfig::simple()
    };
    let plan = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let mut mppi = Mppi::new(cfg, 1).unwrap();
                mppi.plan(&model, &state, &[state.x[0]], &objective)
                    .unwrap()
            })
    };
    let one = plan(1);
    assert_eq!(one.failed, 0);
    assert_eq!(one, plan(2));
}

/// With member trajectories, an ensemble's members each predict every candidate exactly as
/// that network alone would (a failing candidate fails under every member); without, the
/// ensemble is one member, its own batched prediction.
#[test]
fn member_trajectories_are_each_member_alone() {
    let (backbone, state) = chain();
    let ens = Arc::new(ResidualNet::ensemble(vec![net(1), net(2)]).unwrap());
    let apart = Pgrd::with_member_trajectories(backbone, ens.clone()).unwrap();
    assert_eq!(apart.members(), 2);
    assert_eq!(apart.name(), "pgrd-members");
    let g = state.x[0];
    let candidates = vec![
        path(g, Vec3::new(0.0, 0.0, 0.01), 6),
        Actions::without_grippers(7),
        path(g, Vec3::new(0.01, 0.005, 0.0), 6),
    ];
    let members = apart.rollout_members_batch(&state, &candidates);
    assert_eq!(members.len(), 3);
    assert!(members[1].is_err());
    for (k, seed) in [1, 2].into_iter().enumerate() {
        let (backbone, _) = chain();
        let alone = Pgrd::new(backbone, Arc::new(net(seed))).rollout_batch(&state, &candidates);
        for c in [0, 2] {
            let m = members[c].as_ref().unwrap();
            assert_eq!(m.len(), 2);
            assert_eq!(
                &m[k],
                alone[c].as_ref().unwrap(),
                "member {k}, candidate {c}"
            );
        }
    }
    // The members differ, so the comparison above can fail.
    let m = members[0].as_ref().unwrap();
    assert!(m[0][5][20].distance(m[1][5][20]) > 1e-6);

    let (backbone, _) = chain();
    let together = Pgrd::new(backbone, ens);
    assert_eq!(together.members(), 1);
    assert_eq!(together.name(), "pgrd");
    let one = together.rollout_members_batch(&state, &candidates);
    let batch = together.rollout_batch(&state, &candidates);
    for c in [0, 2] {
        let m = one[c].as_ref().unwrap();
        assert_eq!(m.len(), 1);
        assert_eq!(&m[0], batch[c].as_ref().unwrap());
    }
}
