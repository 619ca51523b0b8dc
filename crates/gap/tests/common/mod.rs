//! Shared by the integration tests: the rope fixture's scenes of one split.

use scene::{Protocol, Scene, SceneConfig};

/// The rope fixture's episodes of `split` as paper-protocol scenes.
pub fn scenes(split: dataset::Split) -> Vec<Scene> {
    scenes_with(split, &SceneConfig::default())
}

/// [`scenes`] with other scene settings.
#[allow(dead_code)] // not every test file uses it
pub fn scenes_with(split: dataset::Split, config: &SceneConfig) -> Vec<Scene> {
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../../fixtures/rope");
    let data = dataset::Dataset::open(root).unwrap();
    data.split_indices(split)
        .into_iter()
        .map(|i| {
            let ep = data.load_episode(i).unwrap();
            let w = Protocol::Paper.window(ep.frames()).unwrap();
            Scene::new(&data.meta, &ep, w, config).unwrap()
        })
        .collect()
}

/// The rope backbone the tests diagnose: the reference rope's parameters with the fixture's
/// spring threshold, m, and springs per particle.
#[allow(dead_code)] // not every test file uses it
pub fn backbone() -> springs::SpringParams {
    springs::SpringParams {
        threshold: 0.03,
        max_springs: 20,
        ..springs::SpringParams::reference_rope()
    }
}
