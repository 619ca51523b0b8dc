//! The moving average of the weights (`TrainConfig::ema_decay`): it starts at the initial
//! weights, follows each optimiser step by the decay, leaves the trained weights untouched,
//! and survives a checkpoint.

mod common;

use common::weights;
use residual::{ModelConfig, ResidualNet, TrainConfig, Trainer};

fn trainer(decay: f64) -> Trainer {
    let cfg = TrainConfig {
        iterations: 4,
        batch: 1,
        seed: 5,
        ema_decay: decay,
        ..TrainConfig::default()
    };
    Trainer::new(ResidualNet::new(&ModelConfig::tiny(), 5).unwrap(), cfg).unwrap()
}

#[test]
fn the_average_follows_each_step_by_the_decay() {
    let set = common::rope_train_set();
    let d = 0.9;
    let mut t = trainer(d);
    let w0 = weights(&t.net);
    assert_eq!(t.with_averaged(weights).unwrap(), w0);
    t.train_step(&set).unwrap();
    let w1 = weights(&t.net);
    assert_ne!(w1, w0, "the step changed nothing");
    let avg = t.with_averaged(weights).unwrap();
    let mut moved = 0;
    for ((a, x0), x1) in avg
        .iter()
        .flatten()
        .zip(w0.iter().flatten())
        .zip(w1.iter().flatten())
    {
        let want = d as f32 * x0 + (1.0 - d as f32) * x1;
        assert!(
            (a - want).abs() <= 1e-6 * (1.0 + want.abs()),
            "{a} vs {want}"
        );
        moved += usize::from(x1 != x0);
    }
    assert!(moved > 0);
    // Evaluating the average put the trained weights back.
    assert_eq!(weights(&t.net), w1);
}

#[test]
fn without_averaging_the_current_weights_are_used() {
    let set = common::rope_train_set();
    let mut t = trainer(0.0);
    t.train_step(&set).unwrap();
    assert_eq!(t.with_averaged(weights).unwrap(), weights(&t.net));
}

#[test]
fn the_average_survives_a_checkpoint() {
    let set = common::rope_train_set();
    let mut a = trainer(0.8);
    for _ in 0..2 {
        a.train_step(&set).unwrap();
    }
    let dir = common::temp_dir("averaging");
    let ckpt = dir.join("ckpt.safetensors");
    a.save_checkpoint(&ckpt).unwrap();
    let mut b = trainer(0.8);
    b.load_checkpoint(&ckpt).unwrap();
    assert_eq!(
        b.with_averaged(weights).unwrap(),
        a.with_averaged(weights).unwrap()
    );
    a.train_step(&set).unwrap();
    b.train_step(&set).unwrap();
    assert_eq!(
        b.with_averaged(weights).unwrap(),
        a.with_averaged(weights).unwrap()
    );
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn decays_outside_zero_to_one_are_errors() {
    for d in [-0.1, 1.0, f64::NAN] {
        let cfg = TrainConfig {
            ema_decay: d,
            ..TrainConfig::default()
        };
        let net = ResidualNet::new(&ModelConfig::tiny(), 1).unwrap();
        assert!(Trainer::new(net, cfg).is_err(), "{d}");
    }
}
