//! A few hundred tiny training steps on a fixture reduce the rollout loss substantially;
//! resuming from a checkpoint continues exactly.

mod common;

use dataset::{Dataset, Split};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use residual::{
    ModelConfig, ResidualNet, RolloutOptions, Sample, TrainConfig, TrainSet, Trainer,
    hybrid_rollout,
};
use scene::SceneConfig;
use springs::SpringParams;

fn set() -> TrainSet {
    let data = Dataset::open(common::fixture("rope")).unwrap();
    TrainSet::new(
        &data,
        Split::Train,
        &SpringParams::reference_rope(),
        &SceneConfig::default(),
    )
    .unwrap()
}

/// Mean rollout loss of `samples` (cm²).
fn loss_of(net: &ResidualNet, set: &TrainSet, samples: &[Sample], steps: usize) -> f64 {
    let opts = RolloutOptions {
        steps,
        train: true,
        ..Default::default()
    };
    let total: f64 = samples
        .iter()
        .map(|s| {
            let out = hybrid_rollout(net, set.backbone(s), &s.scene, &s.history, opts).unwrap();
            f64::from(out.loss.unwrap().to_scalar::<f32>().unwrap())
        })
        .sum();
    total / samples.len() as f64
}

/// The whole training path (rollout graph, gradients, clipping, Adam, schedule) fits two
/// fixed fixture segments: their loss falls by more than half in 70 steps. (The backbone here
/// uses unfitted reference parameters, so the residual bound is raised to 0.5 m/s to leave room
/// for the correction.)
#[test]
fn training_reduces_the_loss() {
    let set = set();
    let steps = 3;
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let samples: Vec<Sample> = (0..2)
        .map(|_| set.sample(&mut rng, steps, false).unwrap())
        .collect();
    let cfg = TrainConfig {
        iterations: 70,
        rollout_steps: steps,
        batch: 2,
        lr: 3e-3,
        decay_steps: 70,
        seed: 2,
        ..TrainConfig::default()
    };
    let model = ModelConfig {
        residual_scale: 0.5,
        ..ModelConfig::tiny()
    };
    let mut trainer = Trainer::new(ResidualNet::new(&model, 2).unwrap(), cfg).unwrap();
    let before = loss_of(&trainer.net, &set, &samples, steps);
    for _ in 0..70 {
        let s = trainer.train_on(&set, &samples).unwrap();
        assert!(s.loss.is_finite() && s.grad_norm.is_finite());
    }
    let after = loss_of(&trainer.net, &set, &samples, steps);
    assert!(after < 0.5 * before, "loss {before:.4} -> {after:.4} cm²");
}

#[test]
fn resuming_continues_exactly() {
    let set = set();
    let cfg = TrainConfig {
        iterations: 6,
        batch: 1,
        seed: 3,
        ..TrainConfig::default()
    };
    let mut a = Trainer::new(
        ResidualNet::new(&ModelConfig::tiny(), 3).unwrap(),
        cfg.clone(),
    )
    .unwrap();
    for _ in 0..3 {
        a.train_step(&set).unwrap();
    }
    let dir = common::temp_dir("resume");
    let ckpt = dir.join("ckpt.safetensors");
    a.save_checkpoint(&ckpt).unwrap();
    let mut b = Trainer::new(ResidualNet::new(&ModelConfig::tiny(), 99).unwrap(), cfg).unwrap();
    b.load_checkpoint(&ckpt).unwrap();
    assert_eq!(b.step, 3);
    for _ in 0..3 {
        let (sa, sb) = (a.train_step(&set).unwrap(), b.train_step(&set).unwrap());
        assert_eq!(sa.loss, sb.loss);
    }
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn cosine_schedule() {
    let c = TrainConfig {
        lr: 1e-3,
        lr_min: 1e-5,
        decay_steps: 100,
        ..TrainConfig::default()
    };
    assert!((c.lr_at(0) - 1e-3).abs() < 1e-12);
    assert!((c.lr_at(50) - (1e-5 + 0.5 * (1e-3 - 1e-5))).abs() < 1e-9);
    assert_eq!(c.lr_at(100), 1e-5);
    assert_eq!(c.lr_at(1000), 1e-5);
}
