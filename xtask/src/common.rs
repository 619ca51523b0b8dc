//! Pieces the pipelines share: loading scenes of a split, the run directory's files.

use std::path::{Path, PathBuf};

use anyhow::Context;
use dataset::{Dataset, Split};
use scene::{Protocol, Scene, SceneConfig};
use serde::{Deserialize, Serialize};

/// `--protocol` on the command line.
#[derive(Clone, Copy, Debug, Default, clap::ValueEnum)]
pub enum ProtocolArg {
    /// Paper: 2 history frames, 37 predicted steps.
    #[default]
    Paper,
    /// DEFORM: start from frames 0-1, predict every remaining frame.
    Deform,
}

impl From<ProtocolArg> for Protocol {
    fn from(p: ProtocolArg) -> Self {
        match p {
            ProtocolArg::Paper => Protocol::Paper,
            ProtocolArg::Deform => Protocol::Deform,
        }
    }
}

/// Loads every episode of `split` and builds its scene. Returns (episode index, scene) pairs.
pub fn load_scenes(
    data: &Dataset,
    split: Split,
    protocol: Protocol,
    config: &SceneConfig,
) -> anyhow::Result<Vec<(usize, Scene)>> {
    let indices = data.split_indices(split);
    anyhow::ensure!(
        !indices.is_empty(),
        "{} has no '{split}' episodes",
        data.root.display()
    );
    indices
        .into_iter()
        .map(|i| {
            let ep = data.load_episode(i)?;
            let window = protocol.window(ep.frames())?;
            let scene = Scene::new(&data.meta, &ep, window, config)
                .with_context(|| format!("episode {i} of {}", data.root.display()))?;
            Ok((i, scene))
        })
        .collect()
}

/// The fitted backbone of a run: `<run>/backbone.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BackboneFile {
    /// Model name ("spring-mass").
    pub model: String,
    /// Dataset it was fitted on.
    pub dataset: String,
    /// Protocol of the training windows.
    pub protocol: String,
    /// The fitted parameters.
    pub params: springs::SpringParams,
    /// The fit's history and settings.
    pub fit: fit::FitOutcome,
    /// Fit settings.
    pub config: fit::FitConfig,
    /// Wall time of all generations, s (summed over resumed sessions).
    pub wall_s: f64,
    /// Wall time of the command that wrote this file (loading included), s.
    pub session_wall_s: f64,
}

/// Path of the backbone file in a run directory.
pub fn backbone_path(run: &Path) -> PathBuf {
    run.join("backbone.json")
}

/// Reads `<run>/backbone.json`.
pub fn read_backbone(run: &Path) -> anyhow::Result<BackboneFile> {
    let path = backbone_path(run);
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("reading {} (run `cargo xtask fit` first)", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}
