//! Dataset generation: recordings in parallel, cut into overlapping episodes, written in the pgrd
//! format with a `truth.json` beside it.

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

use dataset::{Dataset, DatasetMeta, DatasetWriter, Episode, Manipulation, Split, Structure};
use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::build::{Blueprint, Resolution, blueprint};
use crate::motion::MotionStyle;
use crate::record::{PUSH_RADIUS, Recording, SETTLE_S, STEP_S, Scene, record};
use crate::rng::{stream, tag};
use crate::truth_gaussians::{self, TruthGaussians};
use crate::{EffectKind, Effects, Error, ObjectKind, Observation};

/// Stored frames per second (one model step is 0.1 s).
pub const FPS: f32 = 10.0;
/// Frames per episode (4 s).
pub const FRAMES_PER_EPISODE: usize = 40;
/// Frames between the starts of consecutive episodes of a recording (2 s).
pub const EPISODE_STRIDE: usize = 20;
/// History frames before the rollout starts (frames 0 and 1).
pub const HISTORY_FRAMES: usize = 2;
/// Model steps in the evaluation window (frames 3..=39, rolled out from frame 2).
pub const EVAL_STEPS: usize = 37;

/// What to generate.
#[derive(Clone, Debug, PartialEq)]
pub struct GenConfig {
    /// The object.
    pub object: ObjectKind,
    /// Effects that are on, with their parameters.
    pub effects: Effects,
    /// The tracker model.
    pub observation: Observation,
    /// Training episodes.
    pub train_episodes: usize,
    /// Validation episodes (from recordings disjoint from the training ones).
    pub val_episodes: usize,
    /// Episodes cut from one continuous recording (its length is `20 (e + 1)` frames).
    pub episodes_per_recording: usize,
    /// Tracked particles exported per frame.
    pub tracked: usize,
    /// Fine model resolution.
    pub resolution: Resolution,
    /// Seed of every random choice.
    pub seed: u64,
    /// At most this many fine surface particles carry ground-truth Gaussians, written as
    /// `truth_ep_NNNN.safetensors` beside each episode ([`TruthGaussians`]); 0 writes none.
    pub gaussian_particles: usize,
    /// How the gripper moves.
    pub motion: MotionStyle,
    /// Gripper continuations of every recording (1: none). With `b > 1` (planning motions of a
    /// grasped object) each recording yields `b` recordings that share the object, its start
    /// and the first 40 % or so of the gripper path, then move on differently: the same state
    /// under different actions. Each yields `episodes_per_recording` episodes, so a recording
    /// gives up to `b × episodes_per_recording`.
    pub branches: usize,
    /// Gauss–Seidel sweeps over the links per XPBD substep (1, the default, is the world every
    /// dataset so far was made with; `docs/world.md`, "Solver"). More sweeps bring the solve
    /// closer to the nominal material, which matters where one sweep does not converge, e.g. a
    /// sheet with a large mass contrast. At most [`MAX_LINK_SWEEPS`].
    pub link_sweeps: usize,
}

/// The most link sweeps per substep [`GenConfig::validate`] accepts.
pub const MAX_LINK_SWEEPS: usize = 64;

/// Default cap on the fine particles carrying ground-truth Gaussians in a full dataset.
pub const DEFAULT_GAUSSIAN_PARTICLES: usize = 600;
/// The cap in the fixtures (kept small: fixtures are committed).
pub const FIXTURE_GAUSSIAN_PARTICLES: usize = 300;

/// Default number of tracked particles of each object's full dataset.
pub fn default_tracked(object: ObjectKind) -> usize {
    match object {
        ObjectKind::Rope | ObjectKind::Duster => 250,
        ObjectKind::Paper | ObjectKind::Flag => 350,
        ObjectKind::Sloth => 400,
        ObjectKind::Teddy => 300,
    }
}

impl GenConfig {
    /// The full default dataset: default effects and observation, 100 train + 20 val episodes of
    /// 10-episode recordings, full resolution, seed 0, ground-truth Gaussians on at most 600
    /// fine particles.
    pub fn new(object: ObjectKind) -> Self {
        GenConfig {
            object,
            effects: Effects::defaults(object),
            observation: Observation::default(),
            train_episodes: 100,
            val_episodes: 20,
            episodes_per_recording: 10,
            tracked: default_tracked(object),
            resolution: Resolution::Full,
            seed: 0,
            gaussian_particles: DEFAULT_GAUSSIAN_PARTICLES,
            motion: MotionStyle::Everyday,
            branches: 1,
            link_sweeps: 1,
        }
    }

    /// The small dataset kept in `fixtures/<object>/`: 3 train + 2 val episodes, 150 tracked
    /// particles, coarse resolution, default effects and observation, seed 0, ground-truth
    /// Gaussians on at most 300 fine particles.
    pub fn fixture(object: ObjectKind) -> Self {
        GenConfig {
            train_episodes: 3,
            val_episodes: 2,
            tracked: 150,
            resolution: Resolution::Coarse,
            gaussian_particles: FIXTURE_GAUSSIAN_PARTICLES,
            ..GenConfig::new(object)
        }
    }

    /// Checks the configuration (sizes and every parameter).
    pub fn validate(&self) -> Result<(), Error> {
        if self.train_episodes + self.val_episodes == 0 {
            return Err(Error::Config("at least one episode is needed".into()));
        }
        if self.episodes_per_recording == 0 {
            return Err(Error::Config("episodes per recording must be >= 1".into()));
        }
        if self.branches == 0 {
            return Err(Error::Config("branches must be >= 1".into()));
        }
        if self.branches > 1 && (self.object.is_push() || self.motion != MotionStyle::Planning) {
            return Err(Error::Config(format!(
                "branched recordings need planning motions of a grasped object (got {} motions \
                 of the {})",
                self.motion, self.object
            )));
        }
        if !(1..=MAX_LINK_SWEEPS).contains(&self.link_sweeps) {
            return Err(Error::Config(format!(
                "link sweeps must be in 1..={MAX_LINK_SWEEPS} (got {})",
                self.link_sweeps
            )));
        }
        if self.tracked == 0 {
            return Err(Error::Config(
                "at least one tracked particle is needed".into(),
            ));
        }
        self.effects.validate()?;
        self.observation.validate()
    }
}

/// One recording's place in the dataset.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RecordingInfo {
    /// Recording index (seeds its placement, motion and observation).
    pub index: usize,
    /// Split of all its episodes.
    pub split: Split,
    /// Stored frames.
    pub frames: usize,
    /// Dataset indices of its episodes, in time order.
    pub episodes: Vec<usize>,
    /// Its other gripper continuations ([`GenConfig::branches`]), if any.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub branches: Vec<BranchInfo>,
}

/// One gripper continuation of a branched recording.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BranchInfo {
    /// The branch frame: the last frame it shares with the recording (state, gripper and
    /// observations are identical up to and including it); the gripper paths part after it.
    pub from_frame: usize,
    /// Dataset indices of its episodes, in time order.
    pub episodes: Vec<usize>,
}

/// Nominal material values of the fine model (effects off).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaterialInfo {
    /// Total mass, kg.
    pub total_mass_kg: f32,
    /// Ground friction coefficient with the friction effect off.
    pub base_friction: f32,
    /// Kelvin–Voigt retardation time of the links, s.
    pub damping_time_s: f32,
    /// Particle contact radius, m.
    pub contact_radius_m: f32,
    /// Nominal fine spacing, m.
    pub spacing_m: f32,
}

/// Episode timing of the dataset.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TimingInfo {
    /// Stored frames per second.
    pub fps: f32,
    /// Frames per episode.
    pub frames_per_episode: usize,
    /// Frames between consecutive episode starts within a recording.
    pub stride_frames: usize,
    /// History frames before the rollout.
    pub history_frames: usize,
    /// Model steps in the evaluation window.
    pub eval_steps: usize,
    /// XPBD substeps per model step.
    pub substeps_per_step: usize,
    /// Unrecorded settling before each recording, s.
    pub settle_s: f32,
    /// Gauss–Seidel sweeps over the links per substep (written only when not 1, so datasets
    /// made with the default have the same `truth.json` as before the setting existed).
    #[serde(default = "one_sweep", skip_serializing_if = "is_one_sweep")]
    pub link_sweeps: usize,
}

fn one_sweep() -> usize {
    1
}

fn is_one_sweep(n: &usize) -> bool {
    *n == 1
}

/// Ground truth about a generated dataset, written as `truth.json` beside `dataset.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Truth {
    /// Generator name and version.
    pub generator: String,
    /// The object.
    pub object: ObjectKind,
    /// The seed.
    pub seed: u64,
    /// Fine model resolution.
    pub resolution: Resolution,
    /// Names of the effects that are on.
    pub effects_enabled: Vec<EffectKind>,
    /// Of those, the ones outside the diagnosis library.
    pub out_of_library: Vec<EffectKind>,
    /// Parameters of the effects that are on.
    pub effects: Effects,
    /// The tracker model.
    pub observation: Observation,
    /// Nominal material values.
    pub material: MaterialInfo,
    /// Timing.
    pub timing: TimingInfo,
    /// Particles of the fine model.
    pub fine_particles: usize,
    /// Fine indices of the tracked particles, in export order.
    pub tracked_indices: Vec<u32>,
    /// Fine particles held by the gripper (0 for pushed objects).
    pub held_fine_particles: usize,
    /// Fine particles carrying ground-truth Gaussians in `truth_ep_NNNN.safetensors` (0: no
    /// such files).
    #[serde(default)]
    pub gaussian_particles: usize,
    /// How the gripper moved (written only when not everyday, so everyday datasets and those
    /// written before styles existed have the same `truth.json`).
    #[serde(default, skip_serializing_if = "MotionStyle::is_everyday")]
    pub motion: MotionStyle,
    /// The recordings.
    pub recordings: Vec<RecordingInfo>,
}

/// A generated dataset in memory.
#[derive(Clone, Debug)]
pub struct GeneratedDataset {
    /// The dataset index (episode list filled by [`GeneratedDataset::write`]).
    pub meta: DatasetMeta,
    /// Episodes with their split, in dataset order.
    pub episodes: Vec<(Episode, Split)>,
    /// Ground truth.
    pub truth: Truth,
    /// Ground-truth Gaussians of each episode, in dataset order (empty when
    /// [`GenConfig::gaussian_particles`] is 0).
    pub gaussians: Vec<TruthGaussians>,
}

impl GeneratedDataset {
    /// Writes `dataset.json`, the episodes, `truth.json` and the episodes' ground-truth
    /// Gaussians (`truth_ep_NNNN.safetensors`) into `dir` (created if needed).
    pub fn write(&self, dir: impl AsRef<Path>) -> Result<Dataset, Error> {
        let dir = dir.as_ref();
        let mut writer = DatasetWriter::create(dir, self.meta.clone())?;
        for (ep, split) in &self.episodes {
            writer.add_episode(ep, *split)?;
        }
        let data = writer.finish()?;
        let path = dir.join("truth.json");
        let mut text = serde_json::to_string_pretty(&self.truth).map_err(|e| Error::Write {
            path: path.clone(),
            message: e.to_string(),
        })?;
        text.push('\n');
        dataset::write_atomic(&path, text.as_bytes())?;
        for (index, g) in self.gaussians.iter().enumerate() {
            g.write(TruthGaussians::path(dir, index))?;
        }
        Ok(data)
    }
}

/// Generates the dataset described by `cfg`.
///
/// ```
/// use world::{GenConfig, ObjectKind, Observation, Effects};
/// let mut cfg = GenConfig::fixture(ObjectKind::Rope);
/// (cfg.train_episodes, cfg.val_episodes, cfg.tracked) = (1, 0, 40);
/// cfg.effects = Effects::none();
/// cfg.observation = Observation::none();
/// let data = world::generate(&cfg)?;
/// assert_eq!(data.episodes.len(), 1);
/// assert_eq!(data.episodes[0].0.frames(), 40);
/// assert_eq!(data.episodes[0].0.particles(), 40);
/// # Ok::<(), world::Error>(())
/// ```
pub fn generate(cfg: &GenConfig) -> Result<GeneratedDataset, Error> {
    generate_with_progress(cfg, &|_, _| {})
}

/// [`generate`], calling `progress(done, total)` after each recording (from worker threads).
pub fn generate_with_progress(
    cfg: &GenConfig,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<GeneratedDataset, Error> {
    cfg.validate()?;
    let mut bp = blueprint(cfg.object, cfg.resolution, cfg.seed);
    bp.link_sweeps = cfg.link_sweeps;
    let tracked = select_tracked(&bp, cfg.tracked, cfg.seed)?;
    let gaussian_particles = truth_gaussians::select(&bp, cfg.gaussian_particles);

    // Recordings: training ones first, then validation ones; indices are global so splits never
    // share a recording.
    let mut plans: Vec<(usize, Split, usize)> = Vec::new();
    for (split, total) in [
        (Split::Train, cfg.train_episodes),
        (Split::Val, cfg.val_episodes),
    ] {
        let mut left = total;
        while left > 0 {
            let e = left.min(cfg.episodes_per_recording * cfg.branches);
            plans.push((plans.len(), split, e));
            left -= e;
        }
    }
    let scene = Scene {
        kind: cfg.object,
        bp: &bp,
        effects: &cfg.effects,
        observation: &cfg.observation,
        tracked: &tracked,
        gaussian_particles: &gaussian_particles,
        seed: cfg.seed,
        motion: cfg.motion,
    };
    let done = AtomicUsize::new(0);
    // Episodes per branch of each recording (all of them when it is not branched).
    let per_branch = |e: usize| e.min(cfg.episodes_per_recording);
    let recordings: Vec<Vec<Recording>> = plans
        .par_iter()
        .map(|&(index, _, e)| {
            let frames = FRAMES_PER_EPISODE + EPISODE_STRIDE * (per_branch(e) - 1);
            let r = record(&scene, index as u64, frames, e.div_ceil(per_branch(e)));
            progress(done.fetch_add(1, Ordering::SeqCst) + 1, plans.len());
            r
        })
        .collect::<Result<_, _>>()?;

    let held_set: std::collections::HashSet<u32> = bp.held.iter().copied().collect();
    let held: Vec<i32> = tracked
        .iter()
        .map(|i| if held_set.contains(i) { 0 } else { -1 })
        .collect();
    let colors: Vec<[f32; 3]> = tracked.iter().map(|&i| bp.colors[i as usize]).collect();
    let n = tracked.len();
    let sigmas = truth_gaussians::sigmas(&bp, &gaussian_particles);
    let mut gaussians = Vec::new();
    let mut episodes = Vec::new();
    let mut infos = Vec::new();
    for ((index, split, e), branches) in plans.iter().zip(&recordings) {
        let mut left = *e;
        let mut info = RecordingInfo {
            index: *index,
            split: *split,
            frames: branches[0].grippers.len(),
            episodes: Vec::new(),
            branches: Vec::new(),
        };
        for rec in branches {
            let cut = left.min(per_branch(*e));
            left -= cut;
            if !gaussian_particles.is_empty() {
                let starts: Vec<usize> = (0..cut).map(|j| j * EPISODE_STRIDE).collect();
                gaussians.extend(truth_gaussians::episodes(
                    &bp,
                    &gaussian_particles,
                    &sigmas,
                    &rec.fine,
                    &starts,
                    FRAMES_PER_EPISODE,
                )?);
            }
            let mut ids = Vec::new();
            for j in 0..cut {
                let f0 = j * EPISODE_STRIDE;
                let frames = f0..f0 + FRAMES_PER_EPISODE;
                let pos = rec.observed[frames.start * n..frames.end * n].to_vec();
                let grip = rec.grippers[frames.clone()].to_vec();
                let vis = rec.visible[frames.start * n..frames.end * n].to_vec();
                let mut ep = Episode::new(FRAMES_PER_EPISODE, n, 1, pos, grip)?
                    .with_held(held.clone())?
                    .with_colors(colors.clone())?
                    .with_visible(vis)?;
                if !cfg.object.is_push() {
                    ep = ep.with_closed(vec![1; FRAMES_PER_EPISODE])?;
                }
                ids.push(episodes.len());
                episodes.push((ep, *split));
            }
            match rec.branch_frame {
                None => info.episodes = ids,
                Some(from_frame) => info.branches.push(BranchInfo {
                    from_frame,
                    episodes: ids,
                }),
            }
        }
        infos.push(info);
    }

    let mut meta = DatasetMeta::new(
        cfg.object.name(),
        FPS,
        if cfg.object.is_push() {
            Manipulation::Push
        } else {
            Manipulation::Grasp
        },
    );
    meta.gripper_radius = match cfg.object {
        ObjectKind::Rope | ObjectKind::Sloth => 0.03,
        ObjectKind::Paper => 0.025,
        ObjectKind::Flag => 0.01,
        ObjectKind::Duster => 0.04,
        ObjectKind::Teddy => PUSH_RADIUS,
    };
    meta.structure = if cfg.object.is_volumetric() {
        Structure::Volume
    } else {
        Structure::Points
    };
    let enabled = cfg.effects.enabled();
    let truth = Truth {
        generator: format!("pgrd-world {}", env!("CARGO_PKG_VERSION")),
        object: cfg.object,
        seed: cfg.seed,
        resolution: cfg.resolution,
        out_of_library: enabled
            .iter()
            .copied()
            .filter(|k| !k.in_library())
            .collect(),
        effects_enabled: enabled,
        effects: cfg.effects.clone(),
        observation: cfg.observation,
        material: MaterialInfo {
            total_mass_kg: bp.total_mass,
            base_friction: bp.base_friction,
            damping_time_s: bp.damping_time_s,
            contact_radius_m: bp.contact_radius,
            spacing_m: bp.spacing,
        },
        timing: TimingInfo {
            fps: FPS,
            frames_per_episode: FRAMES_PER_EPISODE,
            stride_frames: EPISODE_STRIDE,
            history_frames: HISTORY_FRAMES,
            eval_steps: EVAL_STEPS,
            substeps_per_step: bp.substeps,
            link_sweeps: cfg.link_sweeps,
            settle_s: SETTLE_S,
        },
        fine_particles: bp.len(),
        tracked_indices: tracked,
        held_fine_particles: bp.held.len(),
        gaussian_particles: gaussian_particles.len(),
        motion: cfg.motion,
        recordings: infos,
    };
    debug_assert!((STEP_S * FPS - 1.0).abs() < 1e-6);
    Ok(GeneratedDataset {
        meta,
        episodes,
        truth,
        gaussians,
    })
}

/// Chooses `count` surface particles spread evenly (farthest-point sampling in the rest
/// configuration), starting with a few of the held ones so the grasp is visible in the data.
fn select_tracked(bp: &Blueprint, count: usize, seed: u64) -> Result<Vec<u32>, Error> {
    let candidates: Vec<u32> = (0..bp.len() as u32)
        .filter(|&i| bp.surface[i as usize])
        .collect();
    if count > candidates.len() {
        return Err(Error::Config(format!(
            "{count} tracked particles requested but this object's fine model has only {} surface \
             particles",
            candidates.len()
        )));
    }
    let mut rng = stream(seed, &[tag::TRACKED]);
    let pts: Vec<Vec3> = candidates.iter().map(|&i| bp.rest[i as usize]).collect();
    let mut dist = vec![f32::INFINITY; pts.len()];
    let mut chosen = vec![false; pts.len()];
    let mut picked = Vec::with_capacity(count);
    let take = |k: usize, dist: &mut Vec<f32>, chosen: &mut Vec<bool>, picked: &mut Vec<u32>| {
        chosen[k] = true;
        picked.push(candidates[k]);
        for (d, p) in dist.iter_mut().zip(&pts) {
            *d = d.min(p.distance_squared(pts[k]));
        }
    };
    let held: std::collections::HashSet<u32> = bp.held.iter().copied().collect();
    let held_candidates: Vec<usize> = (0..pts.len())
        .filter(|&k| held.contains(&candidates[k]))
        .collect();
    let first = if held_candidates.is_empty() {
        rand::Rng::random_range(&mut rng, 0..pts.len())
    } else {
        held_candidates[rand::Rng::random_range(&mut rng, 0..held_candidates.len())]
    };
    take(first, &mut dist, &mut chosen, &mut picked);
    // A few more held particles, spread over the grasp region.
    let want_held = (count / 25).min(held_candidates.len());
    while picked.len() < want_held {
        let k = held_candidates
            .iter()
            .copied()
            .filter(|&k| !chosen[k])
            .max_by(|&a, &b| dist[a].total_cmp(&dist[b]))
            .expect("fewer held picked than held candidates");
        take(k, &mut dist, &mut chosen, &mut picked);
    }
    while picked.len() < count {
        let k = (0..pts.len())
            .filter(|&k| !chosen[k])
            .max_by(|&a, &b| dist[a].total_cmp(&dist[b]))
            .expect("fewer picked than candidates");
        take(k, &mut dist, &mut chosen, &mut picked);
    }
    picked.sort_unstable();
    Ok(picked)
}
