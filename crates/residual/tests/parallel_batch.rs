//! `TrainConfig::parallel_batch`: the batch's rollouts differentiated one per rayon thread.
//! A trained network is the same on any number of threads, and its first step's loss is the
//! one-graph way's (the same segments, the same forward arithmetic).

mod common;

use residual::{ModelConfig, ResidualNet, TrainConfig, Trainer};

/// Trains four steps with a batch of three on a pool of `threads`; the step losses and the
/// trained weights.
fn train(parallel: bool, threads: usize) -> (Vec<f64>, Vec<Vec<f32>>) {
    let set = common::rope_train_set();
    let model = ModelConfig {
        residual_scale: 0.5,
        ..ModelConfig::tiny()
    };
    let cfg = TrainConfig {
        iterations: 4,
        rollout_steps: 3,
        batch: 3,
        decay_steps: 4,
        lr: 3e-3,
        seed: 6,
        parallel_batch: parallel,
        ..TrainConfig::default()
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| {
        let mut trainer = Trainer::new(ResidualNet::new(&model, 6).unwrap(), cfg).unwrap();
        let losses = (0..4)
            .map(|_| trainer.train_step(&set).unwrap().loss)
            .collect();
        (losses, common::weights(&trainer.net))
    })
}

#[test]
fn parallel_batch_trains_the_same_network_on_any_thread_count() {
    let (losses_1, weights_1) = train(true, 1);
    let (losses_3, weights_3) = train(true, 3);
    assert_eq!(losses_1, losses_3);
    assert!(
        weights_1 == weights_3,
        "weights differ between 1 and 3 threads"
    );
    // Wired through the trainer: the first step rolls out the same segments as the one-graph
    // way, so its loss is the same; the weights after four steps are not bit for bit.
    let (losses_one_graph, _) = train(false, 1);
    assert_eq!(losses_1[0], losses_one_graph[0]);
    assert!(losses_1.iter().all(|l| l.is_finite()));
}
