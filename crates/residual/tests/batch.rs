//! `predict_batch` (one network call per step for many rollouts) predicts what `predict` does
//! for each rollout alone, and a failing rollout fails alone.

mod common;

use glam::Vec3;
use residual::{
    Combine, EncoderKind, History, ModelConfig, PredictJob, ResidualKind, ResidualNet, predict,
    predict_batch,
};
use springs::{Actions, Backbone, State};

/// `actions` with every gripper moved by `k · step` at frame `k` (another candidate path).
fn shifted(actions: &Actions, step: Vec3) -> Actions {
    let (mut pos, mut closed) = (Vec::new(), Vec::new());
    for t in 0..actions.num_frames() {
        let f = actions.frame(t).unwrap();
        pos.push(f.positions.iter().map(|p| *p + step * t as f32).collect());
        closed.push(f.closed.to_vec());
    }
    Actions::new(pos, closed).unwrap()
}

struct Case {
    backbone: Backbone,
    init: State,
    history: History,
    actions: Actions,
}

impl Case {
    fn job(&self, steps: usize) -> PredictJob<'_> {
        PredictJob {
            backbone: &self.backbone,
            init: &self.init,
            history: &self.history,
            actions: &self.actions,
            steps,
        }
    }
}

/// A straight chain of `n` particles 6 mm apart, its first particle held by a gripper that
/// moves by `step` per frame.
fn chain(n: usize, step: Vec3) -> Case {
    let x: Vec<Vec3> = (0..n)
        .map(|i| Vec3::new(0.006 * i as f32, 0.01 * (i as f32 * 0.3).sin(), 0.02))
        .collect();
    let held: Vec<i32> = (0..n).map(|i| if i < 3 { 0 } else { -1 }).collect();
    let params = springs::SpringParams {
        threshold: 0.02,
        ..springs::SpringParams::reference_rope()
    };
    let backbone = Backbone::new(&x, &held, params, springs::SimConfig::default()).unwrap();
    let frames = 8;
    let actions = Actions::new(
        (0..frames).map(|t| vec![x[0] + step * t as f32]).collect(),
        vec![vec![true]; frames],
    )
    .unwrap();
    let init = State::at_rest(x);
    Case {
        history: History::extrapolated(&init, backbone.config().step_dt),
        init,
        backbone,
        actions,
    }
}

fn case(name: &str, episode: usize, shift: Vec3) -> Case {
    let (_, _, scene, history, backbone) = common::scene(name, episode);
    Case {
        actions: shifted(&scene.actions, shift),
        init: scene.init,
        history,
        backbone,
    }
}

/// Largest distance between corresponding points of two rollouts, m.
fn worst(a: &[Vec<Vec3>], b: &[Vec<Vec3>]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .flat_map(|(p, q)| {
            assert_eq!(p.len(), q.len());
            p.iter().zip(q).map(|(p, q)| (*p - *q).length())
        })
        .fold(0.0, f32::max)
}

/// Compares every job of a batch with its own `predict`. The residual moves points by
/// millimetres per step (checked against the backbone alone, so the comparison can fail);
/// batched and single predictions must agree to float rounding (1 µm).
fn assert_batch_matches(net: &ResidualNet, cases: &[&Case], steps: &[usize]) {
    let jobs: Vec<PredictJob<'_>> = cases.iter().zip(steps).map(|(c, &s)| c.job(s)).collect();
    let batch = predict_batch(net, &jobs).unwrap();
    assert_eq!(batch.len(), jobs.len());
    for ((c, &s), b) in cases.iter().zip(steps).zip(batch) {
        let b = b.unwrap();
        let single = predict(net, &c.backbone, &c.init, &c.history, &c.actions, s).unwrap();
        let physics = c.backbone.rollout(&c.init, &c.actions).unwrap().positions;
        let residual = worst(&single, &physics[1..=s]);
        assert!(
            residual > 1e-4,
            "the network moves points by only {residual} m"
        );
        let diff = worst(&b, &single);
        assert!(
            diff <= 1e-6,
            "batched and single predictions differ by {diff} m (residual effect {residual} m)"
        );
    }
}

#[test]
fn a_batch_predicts_what_each_rollout_predicts_alone() {
    let a = case("rope", 0, Vec3::ZERO);
    let b = case("rope", 1, Vec3::new(0.003, -0.002, 0.001));
    let c = chain(97, Vec3::new(0.0, 0.01, 0.02));
    assert_ne!(a.init.x.len(), c.init.x.len(), "point counts should differ");
    let gripper = ModelConfig {
        gripper_inputs: true,
        ground_inputs: true,
        rest_inputs: true,
        ..ModelConfig::tiny()
    };
    let held = ModelConfig {
        held_residual: true,
        ..ModelConfig::tiny()
    };
    // The ablations `eval` scores through this path too (`docs/residual.md`, "Ablations").
    let ablations = [
        ModelConfig {
            encoder: EncoderKind::Pointnet,
            ..ModelConfig::tiny()
        },
        ModelConfig {
            decoder: false,
            ..ModelConfig::tiny()
        },
        ModelConfig {
            combine: Combine::None,
            ..ModelConfig::tiny()
        },
        ModelConfig {
            combine: Combine::Add,
            ..ModelConfig::tiny()
        },
        ModelConfig {
            residual: ResidualKind::Position,
            ..ModelConfig::tiny()
        },
    ];
    for cfg in [ModelConfig::tiny(), ModelConfig::default(), gripper, held]
        .into_iter()
        .chain(ablations)
    {
        let net = ResidualNet::new(&cfg, 4).unwrap();
        assert_batch_matches(&net, &[&a], &[5]);
        // Different clouds, point counts, actions and lengths (the short one leaves early).
        assert_batch_matches(&net, &[&a, &b, &c], &[5, 3, 5]);
        // More particles than one group holds: several groups, evaluated in parallel.
        assert_batch_matches(&net, &[&a, &b, &c, &a, &b], &[5, 3, 5, 2, 4]);
    }
    // An ensemble: every member's window drops the rows of a rollout that leaves early.
    let cfg = ModelConfig::tiny();
    let ens = ResidualNet::ensemble(vec![
        ResidualNet::new(&cfg, 4).unwrap(),
        ResidualNet::new(&cfg, 5).unwrap(),
    ])
    .unwrap();
    assert_batch_matches(&ens, &[&a, &b, &c], &[5, 3, 5]);
    // Two copies of one network and another, of the default size: they agree enough for the
    // shrunk residual to move points (two random tiny members disagree so much it would not).
    let cfg = ModelConfig::default();
    let agreeing = ResidualNet::ensemble(vec![
        ResidualNet::new(&cfg, 4).unwrap(),
        ResidualNet::new(&cfg, 4).unwrap(),
        ResidualNet::new(&cfg, 5).unwrap(),
    ])
    .unwrap()
    .with_ensemble_rule(residual::EnsembleRule::Agreement);
    assert_batch_matches(&agreeing, &[&a, &b, &c], &[5, 3, 5]);
}

/// Largest distance between the particles `idx` of two rollouts, m.
fn worst_of(a: &[Vec<Vec3>], b: &[Vec<Vec3>], idx: std::ops::Range<usize>) -> f32 {
    a.iter()
        .zip(b)
        .flat_map(|(p, q)| idx.clone().map(move |i| (p[i] - q[i]).length()))
        .fold(0.0, f32::max)
}

#[test]
fn held_particles_get_a_residual_only_when_asked() {
    let c = chain(40, Vec3::new(0.0, 0.01, 0.02));
    let physics = c.backbone.rollout(&c.init, &c.actions).unwrap().positions;
    for held_residual in [false, true] {
        let cfg = ModelConfig {
            held_residual,
            ..ModelConfig::tiny()
        };
        let net = ResidualNet::new(&cfg, 4).unwrap();
        let single = predict(&net, &c.backbone, &c.init, &c.history, &c.actions, 5).unwrap();
        let jobs = [c.job(5)];
        let batch = predict_batch(&net, &jobs).unwrap().remove(0).unwrap();
        for out in [&single, &batch] {
            // The chain's first three particles are held; the free ones move either way.
            let held = worst_of(out, &physics[1..=5], 0..3);
            let free = worst_of(out, &physics[1..=5], 3..40);
            assert!(free > 1e-4, "the residual moves free particles by {free} m");
            if held_residual {
                assert!(held > 1e-5, "held particles moved by only {held} m");
            } else {
                assert!(held <= 1e-6, "held particles moved by {held} m");
            }
        }
    }
}

#[test]
fn a_failing_rollout_fails_alone() {
    let a = case("rope", 0, Vec3::ZERO);
    let net = ResidualNet::new(&ModelConfig::tiny(), 4).unwrap();
    let mut short = a.history.clone();
    short.x[1].pop();
    let mut nan = a.init.clone();
    nan.x[7] = Vec3::NAN;
    let jobs = [
        a.job(4),
        PredictJob {
            history: &short,
            ..a.job(4)
        },
        a.job(1000),
        PredictJob {
            init: &nan,
            ..a.job(4)
        },
        a.job(0),
        a.job(2),
    ];
    let out = predict_batch(&net, &jobs).unwrap();
    assert_eq!(out.len(), jobs.len());
    let single = predict(&net, &a.backbone, &a.init, &a.history, &a.actions, 4).unwrap();
    let ok = out[0].as_ref().unwrap();
    assert!(worst(ok, &single) <= 1e-6);
    let msg = |k: usize| out[k].as_ref().unwrap_err().to_string();
    assert!(msg(1).contains("history"), "{}", msg(1));
    assert!(msg(2).contains("action frames"), "{}", msg(2));
    assert!(
        msg(3).contains("backbone") || msg(3).contains("diverged"),
        "{}",
        msg(3)
    );
    assert!(out[4].as_ref().unwrap().is_empty());
    assert!(worst(out[5].as_ref().unwrap(), &single[..2]) <= 1e-6);
    // Nothing to run is not an error.
    assert!(predict_batch(&net, &[]).unwrap().is_empty());
}

/// A saved and reloaded network predicts exactly what it did on the forward-only path `eval`
/// and the planner take (the autograd path's reload is tested in `network.rs`).
#[test]
fn a_reloaded_checkpoint_predicts_identically_on_the_forward_only_path() {
    let a = case("rope", 1, Vec3::ZERO);
    let b = case("rope", 1, Vec3::new(0.002, 0.0, 0.001));
    let net = ResidualNet::new(&ModelConfig::tiny(), 5).unwrap();
    let dir = common::temp_dir("ckpt-forward");
    let path = dir.join("residual.safetensors");
    net.save(&path).unwrap();
    let back = ResidualNet::load(&path).unwrap();
    let jobs = [a.job(4), b.job(4)];
    let positions = |n: &ResidualNet| -> Vec<Vec<Vec<Vec3>>> {
        predict_batch(n, &jobs)
            .unwrap()
            .into_iter()
            .map(|r| r.unwrap())
            .collect()
    };
    assert_eq!(positions(&net), positions(&back));
    // Another network predicts otherwise, so the comparison can fail.
    let other = ResidualNet::new(&ModelConfig::tiny(), 6).unwrap();
    assert_ne!(positions(&net), positions(&other));
    std::fs::remove_dir_all(&dir).ok();
}

/// A state the backbone carries beyond its divergence limit is a diverged rollout, as a NaN
/// is, on the forward-only path and the autograd one: training skips such a rollout and
/// evaluation counts it, where before a run stopped with the backbone's error.
#[test]
fn a_rollout_beyond_the_divergence_limit_is_a_diverged_rollout() {
    let (_, _, mut scene, history, backbone) = common::scene("rope", 0);
    // A particle twice the limit away: no backbone step may carry it on.
    scene.init.x[7] = Vec3::X * 2.0 * springs::DIVERGENCE_LIMIT;
    let net = ResidualNet::new(&ModelConfig::tiny(), 4).unwrap();
    let job = PredictJob {
        backbone: &backbone,
        init: &scene.init,
        history: &history,
        actions: &scene.actions,
        steps: 4,
    };
    let out = predict_batch(&net, &[job]).unwrap();
    assert!(
        matches!(out[0], Err(residual::ResidualError::Diverged { .. })),
        "{:?}",
        out[0].as_ref().err()
    );
    let opts = residual::RolloutOptions {
        steps: 4,
        ..Default::default()
    };
    let autograd = residual::hybrid_rollout(&net, &backbone, &scene, &history, opts);
    assert!(
        matches!(autograd, Err(residual::ResidualError::Diverged { .. })),
        "{:?}",
        autograd.err()
    );
}
