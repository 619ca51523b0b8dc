//! Shared fixtures of the residual tests.
#![allow(dead_code)]

use std::path::PathBuf;

use dataset::Split;
use dataset::{Dataset, Episode};
use residual::{History, ResidualNet, TrainSet};
use scene::{Protocol, Scene, SceneConfig};
use springs::{Backbone, SpringParams};

pub fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../fixtures")
        .join(name)
}

/// Scene, episode, history and backbone (reference rope parameters) of one fixture episode.
pub fn scene(name: &str, episode: usize) -> (Dataset, Episode, Scene, History, Backbone) {
    let data = Dataset::open(fixture(name)).unwrap();
    let ep = data.load_episode(episode).unwrap();
    let window = Protocol::Paper.window(ep.frames()).unwrap();
    let scene = Scene::new(&data.meta, &ep, window, &SceneConfig::default()).unwrap();
    let history = History::from_episode(&scene, &ep, data.meta.fps).unwrap();
    let bb = scene
        .backbone(
            &SpringParams::reference_rope(),
            &scene.sim_config(),
            Default::default(),
        )
        .unwrap();
    (data, ep, scene, history, bb)
}

/// The rope fixture's training split with the reference rope parameters.
pub fn rope_train_set() -> TrainSet {
    train_set(&Dataset::open(fixture("rope")).unwrap())
}

/// `data`'s training split with the reference rope parameters and the default scenes.
pub fn train_set(data: &Dataset) -> TrainSet {
    TrainSet::new(
        data,
        Split::Train,
        &SpringParams::reference_rope(),
        &SceneConfig::default(),
    )
    .unwrap()
}

pub fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("pgrd-residual-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Every parameter of `net`, flattened, in `named_vars` order.
pub fn weights(net: &ResidualNet) -> Vec<Vec<f32>> {
    net.named_vars()
        .iter()
        .map(|(_, v)| {
            v.as_tensor()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
        })
        .collect()
}
