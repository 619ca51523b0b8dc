//! Batched rollouts: input order, equality with single rollouts, independence of thread count.

mod common;

use glam::Vec3;
use springs::{Actions, Backbone, RolloutJob, SimConfig, SpringParams, State, rollout_batch};

#[test]
fn batch_is_identical_for_any_thread_count() {
    let mut rng = common::Rng::new(11);
    // Different objects and parameters, one shared set of gripper actions.
    let scenes: Vec<(Backbone, State)> = (0..6)
        .map(|i| {
            let x = common::blob(&mut rng, 60 + 10 * i, 0.03, Vec3::new(0.0, 0.0, 0.04));
            let held: Vec<i32> = x.iter().map(|p| if p.x < -0.02 { 0 } else { -1 }).collect();
            let params = SpringParams {
                stiffness: 2000.0 * (i + 1) as f32,
                ..SpringParams::reference_rope()
            };
            let bb = Backbone::new(&x, &held, params, SimConfig::default()).unwrap();
            let mut st = State::at_rest(x);
            st.v.iter_mut().for_each(|v| *v = rng.vec3(0.05));
            (bb, st)
        })
        .collect();
    let frames: Vec<Vec<Vec3>> = (0..5)
        .map(|t| vec![Vec3::new(-0.03, 0.0, 0.04 + 0.02 * t as f32)])
        .collect();
    let actions = Actions::new(frames, vec![vec![true]; 5]).unwrap();
    let jobs: Vec<RolloutJob<'_>> = scenes
        .iter()
        .map(|(bb, st)| RolloutJob {
            backbone: bb,
            init: st,
            actions: &actions,
        })
        .collect();

    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| rollout_batch(&jobs))
    };
    let one = run(1);
    let two = run(2);
    assert_eq!(one.len(), jobs.len());
    for (a, b) in one.iter().zip(&two) {
        // Bit-identical, not just close.
        let (a, b) = (a.as_ref().unwrap(), b.as_ref().unwrap());
        let bits = |r: &springs::Rollout| -> Vec<u32> {
            r.positions
                .iter()
                .chain(&r.velocities)
                .flatten()
                .flat_map(|p| p.to_array().map(f32::to_bits))
                .collect()
        };
        assert_eq!(bits(a), bits(b));
    }
    // Results come back in input order and equal the single rollouts.
    for (job, r) in jobs.iter().zip(&one) {
        assert_eq!(
            r.as_ref().unwrap(),
            &job.backbone.rollout(job.init, job.actions).unwrap()
        );
    }
}

#[test]
fn batch_reports_errors_per_job() {
    let x = common::lattice(2, 2, 2, 0.01, Vec3::ZERO);
    let bb = Backbone::new(
        &x,
        &[],
        SpringParams::reference_rope(),
        SimConfig::default(),
    )
    .unwrap();
    let good = State::at_rest(x.clone());
    let bad = State::at_rest(x[..3].to_vec());
    let actions = Actions::without_grippers(3);
    let jobs = [
        RolloutJob {
            backbone: &bb,
            init: &good,
            actions: &actions,
        },
        RolloutJob {
            backbone: &bb,
            init: &bad,
            actions: &actions,
        },
    ];
    let out = rollout_batch(&jobs);
    assert!(out[0].is_ok() && out[1].is_err());
}
