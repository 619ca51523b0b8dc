//! A training set built with backbone options (a backbone with effects, e.g. from a diagnosis)
//! trains on that backbone: its samples roll out differently from the plain set's, and held-out
//! episodes keep the options.

mod common;

use dataset::{Dataset, Split};
use glam::Vec3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use residual::{BackboneOptionsFn, TrainSet};
use scene::{Protocol, SceneConfig};
use springs::{AirDrag, BackboneOptions, SpringParams};

fn set(options: BackboneOptionsFn) -> TrainSet {
    let data = Dataset::open(common::fixture("rope")).unwrap();
    TrainSet::with_backbone_options(
        &data,
        Split::Train,
        &SpringParams::reference_rope(),
        &SceneConfig::default(),
        Protocol::Paper,
        options,
    )
    .unwrap()
}

/// The final positions of one 5-step sample of `set` (same seed, so the same segment).
fn end_of_sample(set: &TrainSet) -> Vec<Vec3> {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let s = set.sample(&mut rng, 5, false).unwrap();
    let r = set
        .backbone(&s)
        .rollout(&s.scene.init, &s.scene.actions)
        .unwrap();
    r.positions.last().unwrap().clone()
}

#[test]
fn the_options_reach_every_backbone_of_the_set() {
    let plain = set(std::sync::Arc::new(BackboneOptions::default));
    let drag: BackboneOptionsFn = std::sync::Arc::new(|| BackboneOptions {
        masses: None,
        effects: vec![Box::new(AirDrag { coefficient: 5.0 })],
        ..Default::default()
    });
    let mut dragged = set(drag);
    let (a, b) = (end_of_sample(&plain), end_of_sample(&dragged));
    let moved = a
        .iter()
        .zip(&b)
        .map(|(p, q)| (*p - *q).length())
        .fold(0.0f32, f32::max);
    assert!(moved > 1e-4, "drag changed the rollout by only {moved} m");
    // Equal options give equal rollouts (the difference above is the effect, not noise).
    let again = set(std::sync::Arc::new(BackboneOptions::default));
    assert_eq!(end_of_sample(&plain), end_of_sample(&again));
    // Held-out episodes are rolled out with the same backbone options.
    let held = dragged.hold_out(1).unwrap();
    let plain_held = set(std::sync::Arc::new(BackboneOptions::default))
        .hold_out(1)
        .unwrap();
    assert_ne!(end_of_sample(&held), end_of_sample(&plain_held));
}
