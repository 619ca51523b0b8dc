use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::{Episode, Error, Result, write_atomic};

/// The format tag this crate reads and writes in `dataset.json`.
pub const FORMAT_VERSION: &str = "pgrd-dataset/1";

pub(crate) const INDEX_FILE: &str = "dataset.json";

/// How grippers act on the object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Manipulation {
    /// Prehensile: held particles follow their gripper rigidly while it is closed.
    Grasp,
    /// Non-prehensile: grippers are spheres of `gripper_radius` that push particles.
    Push,
    /// Each gripper is a particle of the model, moving with it and joined by springs to the
    /// object particles near it at a rollout's start (PhysTwin's controller points); no object
    /// particle is held.
    Attach,
}

/// How an `attach` dataset's grippers (controller points) are joined to the object: each to
/// up to `max_springs` of the nearest object particles within `radius_m` at a rollout's start,
/// PhysTwin's `controller_radius` and `controller_max_neighbours`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControllerSprings {
    /// How far a controller point reaches, m.
    pub radius_m: f32,
    /// Most springs one controller point gets.
    pub max_springs: u32,
}

impl ControllerSprings {
    /// PhysTwin's defaults: 0.04 m and 50 springs.
    pub const PHYSTWIN: ControllerSprings = ControllerSprings {
        radius_m: 0.04,
        max_springs: 50,
    };
}

/// Which part of an experiment an episode belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    /// Used to fit parameters and train networks.
    Train,
    /// Held out: used to evaluate and to choose between models.
    Val,
    /// Held out and untouched until final reporting.
    Test,
}

impl std::str::FromStr for Split {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "train" => Ok(Split::Train),
            "val" => Ok(Split::Val),
            "test" => Ok(Split::Test),
            other => Err(format!(
                "unknown split '{other}' (expected train, val or test)"
            )),
        }
    }
}

impl std::fmt::Display for Split {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        })
    }
}

/// A hint about the tracked points' geometry, used to build the simulated object.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Structure {
    /// Dense tracked points; simulate them as they are (the default).
    #[default]
    Points,
    /// Sparse markers ordered along a linear object (cable, rope): the model may insert hidden
    /// particles between consecutive markers.
    Chain,
    /// Points on the surface of a solid: the model may fill the inside with interior particles.
    Volume,
}

/// One entry of the episode list in `dataset.json`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct EpisodeEntry {
    /// File name of the episode, relative to the dataset directory.
    pub file: String,
    /// The split the episode belongs to.
    pub split: Split,
}

/// The content of `dataset.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DatasetMeta {
    /// Must equal [`FORMAT_VERSION`].
    pub format: String,
    /// Free-text name of the object ("rope", "DLO1", ...).
    pub object: String,
    /// Stored frames per second; one model step is `1 / fps` seconds.
    pub fps: f32,
    /// Gravity in m/s², z up.
    pub gravity: [f32; 3],
    /// Height of the ground plane in metres, or `None` for no ground.
    #[serde(default)]
    pub ground_z: Option<f32>,
    /// How grippers act on the object.
    pub manipulation: Manipulation,
    /// Gripper radius in metres (grasp capture radius, or pushing sphere radius).
    pub gripper_radius: f32,
    /// Geometry hint for building the simulated object (optional, default `points`).
    #[serde(default)]
    pub structure: Structure,
    /// `attach` only: the controller points' own spring rule. Absent, they are joined like
    /// any particle, by the object's fitted threshold and spring count.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub controller_springs: Option<ControllerSprings>,
    /// The episodes, in order.
    pub episodes: Vec<EpisodeEntry>,
}

impl DatasetMeta {
    /// Indices of the episodes in `split`, in file order.
    pub fn split_indices(&self, split: Split) -> Vec<usize> {
        (self.episodes.iter().enumerate())
            .filter(|(_, e)| e.split == split)
            .map(|(i, _)| i)
            .collect()
    }

    /// Metadata with the format's defaults: gravity −9.81 m/s² along z, ground at z = 0,
    /// gripper radius 0.04 m, point structure, no episodes yet.
    pub fn new(object: &str, fps: f32, manipulation: Manipulation) -> Self {
        DatasetMeta {
            format: FORMAT_VERSION.to_string(),
            object: object.to_string(),
            fps,
            gravity: [0.0, 0.0, -9.81],
            ground_z: Some(0.0),
            manipulation,
            gripper_radius: 0.04,
            structure: Structure::Points,
            controller_springs: None,
            episodes: Vec::new(),
        }
    }

    /// Seconds per stored frame, i.e. per model step.
    pub fn step_dt(&self) -> f32 {
        1.0 / self.fps
    }

    fn validate(&self, path: &Path) -> Result<()> {
        let bad = |m: String| Err(Error::invalid(path, m));
        if self.format != FORMAT_VERSION {
            return bad(format!(
                "unsupported format '{}' (this version of pgrd reads '{FORMAT_VERSION}')",
                self.format
            ));
        }
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return bad(format!("fps must be a positive number, got {}", self.fps));
        }
        if !self.gravity.iter().all(|g| g.is_finite()) {
            return bad("gravity must be finite".into());
        }
        if self.ground_z.is_some_and(|z| !z.is_finite()) {
            return bad("ground_z must be finite or null".into());
        }
        if !(self.gripper_radius.is_finite() && self.gripper_radius >= 0.0) {
            return bad(format!(
                "gripper_radius must be a non-negative number of metres, got {}",
                self.gripper_radius
            ));
        }
        if let Some(c) = self.controller_springs {
            if self.manipulation != Manipulation::Attach {
                return bad("controller_springs applies to manipulation 'attach' only".into());
            }
            if !(c.radius_m.is_finite() && c.radius_m > 0.0) {
                return bad(format!(
                    "controller_springs.radius_m must be a positive number of metres, got {}",
                    c.radius_m
                ));
            }
        }
        let mut listed: std::collections::HashMap<&str, usize> = Default::default();
        for (i, e) in self.episodes.iter().enumerate() {
            // One file in two entries would be trained on and scored as held out at once.
            if let Some(j) = listed.insert(e.file.as_str(), i) {
                return bad(format!(
                    "episode {i}: file '{}' is already listed as episode {j}",
                    e.file
                ));
            }
            let p = Path::new(&e.file);
            let plain = p.components().count() == 1
                && matches!(p.components().next(), Some(std::path::Component::Normal(_)));
            if !plain {
                return bad(format!(
                    "episode {i}: file '{}' must be a plain file name inside the dataset directory",
                    e.file
                ));
            }
        }
        Ok(())
    }
}

/// An opened dataset: its directory and validated metadata. Episodes are loaded on demand.
#[derive(Clone, Debug)]
pub struct Dataset {
    /// The dataset directory.
    pub root: PathBuf,
    /// The validated content of `dataset.json`.
    pub meta: DatasetMeta,
}

impl Dataset {
    /// Reads and validates `<dir>/dataset.json`.
    pub fn open(dir: impl AsRef<Path>) -> Result<Self> {
        let root = dir.as_ref().to_path_buf();
        let path = root.join(INDEX_FILE);
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let meta: DatasetMeta = serde_json::from_str(&text)
            .map_err(|e| Error::invalid(&path, format!("not a valid dataset index: {e}")))?;
        meta.validate(&path)?;
        Ok(Dataset { root, meta })
    }

    /// Indices of the episodes in `split`, in file order.
    pub fn split_indices(&self, split: Split) -> Vec<usize> {
        self.meta.split_indices(split)
    }

    /// Path of episode `index`.
    pub fn episode_path(&self, index: usize) -> Result<PathBuf> {
        let entry = self.meta.episodes.get(index).ok_or_else(|| {
            Error::invalid(
                self.root.join(INDEX_FILE),
                format!(
                    "episode index {index} out of range ({} episodes)",
                    self.meta.episodes.len()
                ),
            )
        })?;
        Ok(self.root.join(&entry.file))
    }

    /// Loads and validates episode `index`.
    pub fn load_episode(&self, index: usize) -> Result<Episode> {
        Episode::read(&self.episode_path(index)?)
    }

    /// Which particles are held by which gripper in `episode` (−1 for free): the stored `held`
    /// when present; otherwise, under `grasp`, particles within `gripper_radius` of a gripper at
    /// frame 0 (the nearest one); under `push`, none.
    pub fn held(&self, episode: &Episode) -> Vec<i32> {
        episode.held_or_default(self.meta.manipulation, self.meta.gripper_radius)
    }
}

/// Writes a dataset: episodes as they come, then `dataset.json` on [`DatasetWriter::finish`].
/// Every file is written atomically, so an interrupted writer never leaves a corrupt index.
#[derive(Debug)]
pub struct DatasetWriter {
    root: PathBuf,
    meta: DatasetMeta,
}

impl DatasetWriter {
    /// Creates the directory (and parents) for a new dataset described by `meta`; episodes
    /// already listed in `meta` are dropped.
    pub fn create(dir: impl AsRef<Path>, mut meta: DatasetMeta) -> Result<Self> {
        let root = dir.as_ref().to_path_buf();
        meta.validate(&root.join(INDEX_FILE))?;
        meta.episodes.clear();
        std::fs::create_dir_all(&root).map_err(|e| Error::io(&root, e))?;
        Ok(DatasetWriter { root, meta })
    }

    /// Opens the existing dataset at `dir` to add episodes after its own; its index is
    /// rewritten only on [`DatasetWriter::finish`], so until then readers see the old one.
    pub fn append(dir: impl AsRef<Path>) -> Result<Self> {
        let data = Dataset::open(dir)?;
        Ok(DatasetWriter {
            root: data.root,
            meta: data.meta,
        })
    }

    /// The metadata so far (the episodes added, or kept by [`DatasetWriter::append`]).
    pub fn meta(&self) -> &DatasetMeta {
        &self.meta
    }

    /// Writes `episode` as `ep_NNNN.safetensors` in `split` (NNNN its index, or the next
    /// number whose file name the index does not list yet); returns its index.
    pub fn add_episode(&mut self, episode: &Episode, split: Split) -> Result<usize> {
        let index = self.meta.episodes.len();
        // An appended dataset may name its files otherwise (an importer's names); never let a
        // new file replace a listed one.
        let mut k = index;
        let file = loop {
            let f = format!("ep_{k:04}.safetensors");
            if self.meta.episodes.iter().all(|e| e.file != f) {
                break f;
            }
            k += 1;
        };
        episode.write(&self.root.join(&file))?;
        self.meta.episodes.push(EpisodeEntry { file, split });
        Ok(index)
    }

    /// Writes `dataset.json` and returns the opened dataset.
    pub fn finish(self) -> Result<Dataset> {
        write_index(&self.root, &self.meta)?;
        Ok(Dataset {
            root: self.root,
            meta: self.meta,
        })
    }
}

/// Writes `meta` as `<root>/dataset.json`, atomically.
pub(crate) fn write_index(root: &Path, meta: &DatasetMeta) -> Result<()> {
    let path = root.join(INDEX_FILE);
    let text = serde_json::to_string_pretty(meta)
        .map_err(|e| Error::invalid(&path, format!("cannot serialise index: {e}")))?;
    write_atomic(&path, text.as_bytes())
}
