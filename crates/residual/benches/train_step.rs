//! Cost of one optimiser step on a batch of four 5-step training rollouts of the flag fixture
//! (default `ModelConfig`), with the batch differentiated as one graph (the default) and per
//! rollout in parallel (`TrainConfig::parallel_batch`), and of the two-stage network as one
//! graph.
//!
//! `RAYON_NUM_THREADS=2 cargo bench -p pgrd-residual --bench train_step` (and with 1)

use std::path::Path;

use criterion::Criterion;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use residual::{ModelConfig, ResidualNet, Sample, TrainConfig, TrainSet, Trainer};

fn flag_set() -> TrainSet {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/flag");
    let data = dataset::Dataset::open(dir).unwrap();
    TrainSet::new(
        &data,
        dataset::Split::Train,
        &springs::SpringParams::reference_rope(),
        &scene::SceneConfig::default(),
    )
    .unwrap()
}

fn bench(c: &mut Criterion) {
    let set = flag_set();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let samples: Vec<Sample> = (0..4)
        .map(|_| set.sample(&mut rng, 5, true).unwrap())
        .collect();
    let mut g = c.benchmark_group("train_step_batch_4");
    g.sample_size(10);
    for (name, parallel) in [("one_graph", false), ("parallel_batch", true)] {
        let cfg = TrainConfig {
            batch: 4,
            parallel_batch: parallel,
            ..TrainConfig::default()
        };
        let net = ResidualNet::new(&ModelConfig::default(), 0).unwrap();
        let mut trainer = Trainer::new(net, cfg).unwrap();
        g.bench_function(name, |b| {
            b.iter(|| trainer.train_on(&set, &samples).unwrap())
        });
    }
    // The two-stage network that trains the rope's row recipe as well as the default
    // (`docs/residual-log.md`, "Smaller, wider and deeper networks"), the batch as one graph.
    let two_stages = ModelConfig {
        enc_channels: vec![16, 32],
        enc_depths: vec![1, 1],
        dec_channels: vec![32],
        dec_depths: vec![1],
        ..ModelConfig::default()
    };
    let cfg = TrainConfig {
        batch: 4,
        ..TrainConfig::default()
    };
    let mut trainer = Trainer::new(ResidualNet::new(&two_stages, 0).unwrap(), cfg).unwrap();
    g.bench_function("one_graph_two_stages_16_32", |b| {
        b.iter(|| trainer.train_on(&set, &samples).unwrap())
    });
    g.finish();
}

// Written out instead of `criterion_group!`, whose generated function has no doc comment.
fn main() {
    let mut c = Criterion::default().configure_from_args();
    bench(&mut c);
    c.final_summary();
}
