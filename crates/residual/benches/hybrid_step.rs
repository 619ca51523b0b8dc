//! Cost of one hybrid step (backbone + residual network, and with an ensemble of four, averaged
//! or by the agreement rule) and of
//! one training rollout (5 steps, forward and backward) for a 1000-particle cloth.
//!
//! `RAYON_NUM_THREADS=1 cargo bench -p pgrd-residual --bench hybrid_step`

use criterion::Criterion;
use dataset::{DatasetMeta, Episode, Manipulation};
use glam::Vec3;
use residual::{History, ModelConfig, ResidualNet, RolloutOptions, hybrid_rollout};
use scene::{Scene, SceneConfig, Window};
use springs::SpringParams;

/// A 40 × 25 cloth (1000 particles, 1.5 cm spacing) lying 5 cm above the ground, its corner
/// grasped and lifted 2 cm per frame.
fn cloth_scene() -> (Scene, History) {
    let (w, h, s, frames) = (40, 25, 0.015f32, 12);
    let rest: Vec<Vec3> = (0..w * h)
        .map(|k| Vec3::new((k % w) as f32 * s, (k / w) as f32 * s, 0.05))
        .collect();
    let mut positions = Vec::new();
    let mut grippers = Vec::new();
    for t in 0..frames {
        positions.extend(rest.iter().map(|p| *p + Vec3::Z * (0.001 * t as f32)));
        grippers.push(Vec3::new(0.0, 0.0, 0.05 + 0.02 * t as f32));
    }
    let mut held = vec![-1; w * h];
    held[0] = 0;
    let ep = Episode::new(frames, w * h, 1, positions, grippers)
        .unwrap()
        .with_held(held)
        .unwrap();
    let meta = DatasetMeta::new("bench-cloth", 10.0, Manipulation::Grasp);
    let scene = Scene::new(
        &meta,
        &ep,
        Window { start: 2, steps: 8 },
        &SceneConfig::default(),
    )
    .unwrap();
    let history = History::from_episode(&scene, &ep, meta.fps).unwrap();
    (scene, history)
}

fn bench(c: &mut Criterion) {
    let (scene, history) = cloth_scene();
    let params = SpringParams {
        threshold: 0.02,
        ..SpringParams::reference_rope()
    };
    let bb = scene
        .backbone(&params, &scene.sim_config(), Default::default())
        .unwrap();
    let net = ResidualNet::new(&ModelConfig::default(), 0).unwrap();
    let mut g = c.benchmark_group("hybrid_1000");
    g.sample_size(20);
    g.bench_function("backbone_step", |b| {
        b.iter(|| {
            let mut sc = bb.scratch();
            let mut st = scene.init.clone();
            let (f, t) = (
                scene.actions.frame(0).unwrap(),
                scene.actions.frame(1).unwrap(),
            );
            bb.step(&mut st, f, t, &mut sc).unwrap();
            st
        })
    });
    g.bench_function("hybrid_step", |b| {
        let opts = RolloutOptions {
            steps: 1,
            ..Default::default()
        };
        b.iter(|| hybrid_rollout(&net, &bb, &scene, &history, opts).unwrap())
    });
    // Other sizes than the default (`train --enc-channels ... --dec-depths`): four times the
    // channels' products, twice the blocks, and two smaller ones (`docs/residual-log.md`, "Smaller,
    // wider and deeper networks").
    let sized = [
        (
            "hybrid_step_wide_32_64_128",
            ModelConfig {
                enc_channels: vec![32, 64, 128],
                dec_channels: vec![64, 64],
                ..ModelConfig::default()
            },
        ),
        (
            "hybrid_step_deep_2_blocks",
            ModelConfig {
                enc_depths: vec![2, 2, 2],
                dec_depths: vec![2, 2],
                ..ModelConfig::default()
            },
        ),
        (
            "hybrid_step_small_16_16_32",
            ModelConfig {
                enc_channels: vec![16, 16, 32],
                dec_channels: vec![16, 16],
                ..ModelConfig::default()
            },
        ),
        (
            "hybrid_step_two_stages_16_32",
            ModelConfig {
                enc_channels: vec![16, 32],
                enc_depths: vec![1, 1],
                dec_channels: vec![32],
                dec_depths: vec![1],
                ..ModelConfig::default()
            },
        ),
    ];
    for (name, cfg) in sized {
        let net = ResidualNet::new(&cfg, 0).unwrap();
        let opts = RolloutOptions {
            steps: 1,
            ..Default::default()
        };
        g.bench_function(name, |b| {
            b.iter(|| hybrid_rollout(&net, &bb, &scene, &history, opts).unwrap())
        });
    }
    // An ensemble evaluates every member each step (`docs/residual.md`, "Ensembles").
    let four = || {
        ResidualNet::ensemble(
            (0..4)
                .map(|seed| ResidualNet::new(&ModelConfig::default(), seed).unwrap())
                .collect(),
        )
        .unwrap()
    };
    let ensemble = four();
    g.bench_function("hybrid_step_ensemble_of_4", |b| {
        let opts = RolloutOptions {
            steps: 1,
            ..Default::default()
        };
        b.iter(|| hybrid_rollout(&ensemble, &bb, &scene, &history, opts).unwrap())
    });
    // The agreement rule adds per-particle arithmetic over the members' residuals.
    let agreeing = ensemble.with_ensemble_rule(residual::EnsembleRule::Agreement);
    g.bench_function("hybrid_step_ensemble_of_4_agreement", |b| {
        let opts = RolloutOptions {
            steps: 1,
            ..Default::default()
        };
        b.iter(|| hybrid_rollout(&agreeing, &bb, &scene, &history, opts).unwrap())
    });
    // The forward-only path (`predict_batch`, the fused inference kernels: what interactive
    // use and the planner run) for one 1000-particle prediction of one step, with the row
    // networks' shapes: one network, an ensemble of four by the mean (DLO1's and DLO3's rows)
    // and by the agreement rule (the sloth's).
    let forward_only = [
        (
            "infer_step",
            ResidualNet::new(&ModelConfig::default(), 0).unwrap(),
        ),
        ("infer_step_ensemble_of_4", four()),
        (
            "infer_step_ensemble_of_4_agreement",
            four().with_ensemble_rule(residual::EnsembleRule::Agreement),
        ),
    ];
    let job = residual::PredictJob {
        backbone: &bb,
        init: &scene.init,
        history: &history,
        actions: &scene.actions,
        steps: 1,
    };
    for (name, n) in &forward_only {
        g.bench_function(*name, |b| {
            b.iter(|| residual::predict_batch(n, &[job]).unwrap())
        });
    }
    g.sample_size(10);
    g.bench_function("train_rollout_5_steps_fwd_bwd", |b| {
        let opts = RolloutOptions {
            steps: 5,
            train: true,
            ..Default::default()
        };
        b.iter(|| {
            let out = hybrid_rollout(&net, &bb, &scene, &history, opts).unwrap();
            out.loss.unwrap().backward().unwrap()
        })
    });
    g.finish();
}

// Written out instead of `criterion_group!`, whose generated function has no doc comment.
fn main() {
    let mut c = Criterion::default().configure_from_args();
    bench(&mut c);
    c.final_summary();
}
