//! Training: segment sampling, multi-step rollout loss, Adam with cosine decay and gradient
//! clipping, resumable checkpoints.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Tensor, Var};
use dataset::{Dataset, Episode, Split, Structure};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use scene::{Protocol, Scene, SceneConfig, Window};
use serde::{Deserialize, Serialize};
use springs::{Backbone, BackboneOptions, SpringParams, State};

mod batch_grads;
mod holdout;
mod oracle;

pub use holdout::{clearly_better, paired_difference};

use crate::augment::{rotate_history, rotate_scene};
use crate::loss::TrainLoss;
use crate::{
    History, ResidualError, ResidualNet, Result, RolloutOptions, SimGradient, hybrid_rollout,
};

/// Optimisation settings (saved in `train.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Optimiser steps.
    pub iterations: usize,
    /// Model steps per training rollout (5 in the paper).
    pub rollout_steps: usize,
    /// Rollouts per optimiser step.
    pub batch: usize,
    /// Initial learning rate.
    pub lr: f64,
    /// Final learning rate of the cosine decay (kept constant afterwards).
    pub lr_min: f64,
    /// Steps of the cosine decay.
    pub decay_steps: usize,
    /// Gradient-norm clip.
    pub clip: f64,
    /// Random rotation about z per rollout.
    pub augment: bool,
    /// Seed of sampling, augmentation and curve shuffling (initialisation uses it too).
    pub seed: u64,
    /// Where training segments start.
    #[serde(default)]
    pub start_from: StartFrom,
    /// With [`StartFrom::Rollout`]: re-run the hybrid model over every training episode each
    /// this many optimiser steps, so segments start where the current model actually goes
    /// (0: keep the backbone's rollout).
    #[serde(default)]
    pub refresh_every: usize,
    /// Loss of each rollout step (configurations written before this option trained with
    /// [`TrainLoss::Mse`]).
    #[serde(default)]
    pub loss: TrainLoss,
    /// How gradients cross the backbone's steps (configurations written before this option
    /// trained with [`SimGradient::Detached`]).
    #[serde(default)]
    pub sim_gradient: SimGradient,
    /// Decay of the exponential moving average of the weights (0: off). With it on, the
    /// averaged network, which starts at the step-0 weights, is what [`Trainer::with_averaged`]
    /// evaluates: the average damps the step-to-step jumps of single Adam iterates.
    #[serde(default)]
    pub ema_decay: f64,
    /// Score the backbone alone on the optimiser step's segments (the yardstick
    /// [`StepStats::backbone_loss`]) every this many steps, from step 0 (0: never). It costs a
    /// second backbone rollout per segment (4-22 % of a step, docs/BENCHMARKS.md) and changes
    /// nothing that is learned. Configurations written before this option scored every step.
    #[serde(default = "every_step")]
    pub yardstick_every: usize,
    /// Decoupled weight decay per unit learning rate (AdamW: each step multiplies every weight
    /// by `1 − lr · weight_decay` before the Adam update; 0: off, as every configuration
    /// written before this option).
    #[serde(default)]
    pub weight_decay: f64,
    /// Standard deviation of Gaussian noise added to every free particle's start position and
    /// its two history positions (each frame drawn independently) of each training segment,
    /// metres (0: off, as every configuration written before this option). The targets stay
    /// the recorded frames, so the network is taught to pull a perturbed state back, as it must
    /// in long rollouts whose state drifts from the recordings (the noise of graph network
    /// simulators, Sanchez-Gonzalez et al. 2020). Drawn from a stream of its own, so the
    /// segments sampled are those of the same run without it.
    #[serde(default)]
    pub input_noise_m: f32,
    /// Roll out and differentiate the batch's segments each on a rayon thread of its own and
    /// sum their gradients in the batch's order, instead of differentiating their summed loss
    /// once on the calling thread (false, as every configuration written before this option).
    /// The same mean loss, its gradient added in another order: weights agree with the
    /// one-graph way to rounding, and are the same bits on any number of threads. Faster when
    /// the pool has a thread per segment to spare (docs/BENCHMARKS.md).
    #[serde(default)]
    pub parallel_batch: bool,
}

fn every_step() -> usize {
    1
}

/// The state a training segment starts from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StartFrom {
    /// The model's own rollout from the evaluation start (the state distribution evaluation
    /// meets: a backbone with springs built at the start frame, then free-running).
    Rollout,
    /// The recorded (tracked, noisy) frame, as the reference code does.
    Recorded,
    #[default]
    /// Half the segments from a guided backbone rollout that stays near the truth (each step
    /// the backbone's state is pulled toward the recorded frame by a velocity change bounded
    /// like the residual, i.e. the states a good residual model visits), half from the
    /// model's own rollout (refreshed every `refresh_every` steps).
    Guided,
    /// Half the segments from the guided backbone rollout (as [`StartFrom::Guided`]), half
    /// from recorded frames (as [`StartFrom::Recorded`]), by position in the batch as in
    /// [`StartFrom::Guided`] (with a batch of one, every segment is guided). Measured on the
    /// full datasets, each of those two wins on some objects and loses on others
    /// (docs/residual-log.md, Status).
    GuidedRecorded,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            iterations: 2000,
            rollout_steps: 5,
            batch: 2,
            lr: 1e-3,
            lr_min: 1e-5,
            decay_steps: 2000,
            clip: 1.0,
            augment: true,
            seed: 0,
            start_from: StartFrom::Guided,
            refresh_every: 0,
            loss: TrainLoss::Mse,
            sim_gradient: SimGradient::Detached,
            ema_decay: 0.0,
            yardstick_every: 10,
            weight_decay: 0.0,
            input_noise_m: 0.0,
            parallel_batch: false,
        }
    }
}

impl TrainConfig {
    /// Learning rate at optimiser step `t` (0-based).
    pub fn lr_at(&self, t: usize) -> f64 {
        if t >= self.decay_steps {
            return self.lr_min;
        }
        let c = (std::f64::consts::PI * t as f64 / self.decay_steps.max(1) as f64).cos();
        self.lr_min + 0.5 * (self.lr - self.lr_min) * (1.0 + c)
    }
}

/// One training episode: the evaluation scene's backbone (springs from the protocol's start
/// frame, as at evaluation) and the recorded frames.
struct TrainEpisode {
    /// Index of the episode in its dataset.
    index: usize,
    episode: Episode,
    base: Scene,
    backbone: Backbone,
    history: History,
}

/// A model's states along an episode's evaluation window: entries 0 and 1 are the history
/// frames `start − 2`, `start − 1`, entry `k + 2` the state `k` steps after the start.
#[derive(Clone, Debug)]
pub(crate) struct Trajectory {
    x: Vec<Vec<Vec3>>,
    v: Vec<Vec<Vec3>>,
}

impl Trajectory {
    /// The history frames and the start state of `ep`'s evaluation window.
    fn start(ep: &TrainEpisode) -> Self {
        let (h, init) = (&ep.history, &ep.base.init);
        Trajectory {
            x: vec![h.x[1].clone(), h.x[0].clone(), init.x.clone()],
            v: vec![h.v[1].clone(), h.v[0].clone(), init.v.clone()],
        }
    }
}

/// Builds the options (extra force terms, masses) of every backbone a [`TrainSet`] makes.
pub type BackboneOptionsFn = std::sync::Arc<dyn Fn() -> BackboneOptions + Send + Sync>;

/// The training episodes of a dataset with the fitted backbone.
pub struct TrainSet {
    episodes: Vec<TrainEpisode>,
    meta: dataset::DatasetMeta,
    params: SpringParams,
    scene_cfg: SceneConfig,
    options: BackboneOptionsFn,
}

/// One training rollout: a scene over a short window, its history and its backbone.
pub struct Sample {
    /// The scene (possibly rotated).
    pub scene: Scene,
    /// The history frames (rotated like the scene).
    pub history: History,
    /// Backbone for this segment when it could not reuse the episode's (a recorded start on
    /// a filled volume, whose interior is filled afresh, or another particle count), else
    /// `None`.
    backbone: Option<Backbone>,
    episode: usize,
}

impl TrainSet {
    /// Loads the `split` episodes of `data` and builds their backbones from `params`, with
    /// the paper protocol's evaluation window.
    pub fn new(
        data: &Dataset,
        split: Split,
        params: &SpringParams,
        scene_cfg: &SceneConfig,
    ) -> Result<Self> {
        Self::with_protocol(data, split, params, scene_cfg, Protocol::Paper)
    }

    /// As [`TrainSet::new`] with the evaluation window of `protocol` (the window training
    /// segments of [`StartFrom::Rollout`] / [`StartFrom::Guided`] are drawn from).
    pub fn with_protocol(
        data: &Dataset,
        split: Split,
        params: &SpringParams,
        scene_cfg: &SceneConfig,
        protocol: Protocol,
    ) -> Result<Self> {
        let options: BackboneOptionsFn = std::sync::Arc::new(BackboneOptions::default);
        Self::with_backbone_options(data, split, params, scene_cfg, protocol, options)
    }

    /// As [`TrainSet::with_protocol`] for a backbone with extra force terms: `options` builds
    /// them for every backbone the set makes (a backbone with effects from a diagnosis).
    pub fn with_backbone_options(
        data: &Dataset,
        split: Split,
        params: &SpringParams,
        scene_cfg: &SceneConfig,
        protocol: Protocol,
        options: BackboneOptionsFn,
    ) -> Result<Self> {
        let mut episodes = Vec::new();
        for i in data.split_indices(split) {
            let episode = data.load_episode(i)?;
            let window = protocol.window(episode.frames())?;
            let base = Scene::new(&data.meta, &episode, window, scene_cfg)?;
            let backbone = base.backbone(params, &base.sim_config(), options())?;
            let history = History::from_episode(&base, &episode, data.meta.fps)?;
            episodes.push(TrainEpisode {
                index: i,
                episode,
                base,
                backbone,
                history,
            });
        }
        if episodes.is_empty() {
            return Err(ResidualError::Input(format!(
                "no '{split}' episodes in {}",
                data.root.display()
            )));
        }
        Ok(TrainSet {
            episodes,
            meta: data.meta.clone(),
            params: *params,
            scene_cfg: scene_cfg.clone(),
            options,
        })
    }

    /// Number of episodes.
    pub fn len(&self) -> usize {
        self.episodes.len()
    }

    /// Whether there are no episodes.
    pub fn is_empty(&self) -> bool {
        self.episodes.is_empty()
    }

    /// Every episode's trajectory over its evaluation window: the hybrid model's when `net`
    /// is given (the backbone's where the hybrid diverges), else the backbone's.
    pub(crate) fn trajectories(&self, net: Option<&ResidualNet>) -> Result<Vec<Trajectory>> {
        self.episodes
            .iter()
            .map(|ep| {
                let hybrid = match net {
                    Some(net) => match hybrid_rollout(
                        net,
                        &ep.backbone,
                        &ep.base,
                        &ep.history,
                        RolloutOptions::default(),
                    ) {
                        Ok(r) => Some((r.positions, r.velocities)),
                        Err(ResidualError::Diverged { .. }) => None,
                        Err(e) => return Err(e),
                    },
                    None => None,
                };
                let (px, pv) = match hybrid {
                    Some(r) => r,
                    None => {
                        let r = ep.backbone.rollout(&ep.base.init, &ep.base.actions)?;
                        let mut x = r.positions;
                        let mut v = r.velocities;
                        x.remove(0);
                        v.remove(0);
                        (x, v)
                    }
                };
                let mut traj = Trajectory::start(ep);
                traj.x.extend(px);
                traj.v.extend(pv);
                Ok(traj)
            })
            .collect()
    }

    /// Every episode's guided backbone trajectory: after each backbone step, every free
    /// tracked particle seen in the next recorded frame gets the velocity change (bounded by
    /// `bound` m/s per axis) that moves it toward that frame. An episode whose guided
    /// trajectory diverges (a stiff backbone nudged hard) gets the backbone's own trajectory
    /// instead; the second value counts those episodes.
    pub(crate) fn guided_trajectories(&self, bound: f32) -> Result<(Vec<Trajectory>, usize)> {
        let mut fallbacks = 0;
        let trajectories = self
            .episodes
            .iter()
            .map(|ep| match self.guided_trajectory(ep, bound) {
                Err(ResidualError::Sim(springs::SimError::Diverged { .. })) => {
                    fallbacks += 1;
                    self.guided_trajectory(ep, 0.0)
                }
                other => other,
            })
            .collect::<Result<Vec<_>>>()?;
        Ok((trajectories, fallbacks))
    }

    /// `ep`'s guided backbone trajectory (see [`TrainSet::guided_trajectories`]); a bound of 0
    /// gives the backbone's own rollout.
    fn guided_trajectory(&self, ep: &TrainEpisode, bound: f32) -> Result<Trajectory> {
        let dt = 1.0 / self.meta.fps;
        let base = &ep.base;
        let Trajectory { mut x, mut v } = Trajectory::start(ep);
        let mut state = base.init.clone();
        let mut scratch = ep.backbone.scratch();
        for step in 0..base.window.steps {
            let (Some(from), Some(to)) = (base.actions.frame(step), base.actions.frame(step + 1))
            else {
                break;
            };
            ep.backbone.step(&mut state, from, to, &mut scratch)?;
            let seen = &base.visible[step];
            let targets = base.truth[step].iter().zip(seen).zip(&base.held);
            for (i, ((target, &seen), &g)) in targets.enumerate() {
                let held = g >= 0 && from.closed.get(g as usize).copied().unwrap_or(false);
                if held || !seen {
                    continue;
                }
                let dv =
                    ((*target - state.x[i]) / dt).clamp(Vec3::splat(-bound), Vec3::splat(bound));
                state.x[i] += dv * dt;
                state.v[i] += dv;
            }
            x.push(state.x.clone());
            v.push(state.v.clone());
        }
        Ok(Trajectory { x, v })
    }

    /// A random segment of `steps` steps from a recorded frame with two recorded history
    /// frames before it, rotated by a random angle about z when `augment` (the reference
    /// code's sampling, [`StartFrom::Recorded`]).
    pub fn sample(&self, rng: &mut ChaCha8Rng, steps: usize, augment: bool) -> Result<Sample> {
        self.sample_from(rng, steps, augment, None)
    }

    /// A random segment of `steps` steps, rotated by a random angle about z when `augment`.
    /// With `starts` it begins at a random step of the episode's evaluation window from the
    /// state of that trajectory; without, at a random frame with two recorded history frames
    /// from the recorded state.
    pub(crate) fn sample_from(
        &self,
        rng: &mut ChaCha8Rng,
        steps: usize,
        augment: bool,
        starts: Option<&[Trajectory]>,
    ) -> Result<Sample> {
        let e = rng.random_range(0..self.episodes.len());
        let ep = &self.episodes[e];
        let (scene, history, backbone) = match starts.and_then(|s| s.get(e)) {
            Some(traj) => {
                let span = ep.base.window.steps;
                if span < steps {
                    return Err(ResidualError::Input(format!(
                        "evaluation window of {span} steps is too short for {steps}-step segments"
                    )));
                }
                let k = rng.random_range(0..=span - steps);
                let init = State {
                    x: traj.x[k + 2].clone(),
                    v: traj.v[k + 2].clone(),
                };
                let history = History {
                    x: [traj.x[k + 1].clone(), traj.x[k].clone()],
                    v: [traj.v[k + 1].clone(), traj.v[k].clone()],
                };
                (ep.base.segment(k, steps, init)?, history, None)
            }
            None => {
                let frames = ep.episode.frames();
                let first = ep.base.window.start.max(2);
                if frames < first + steps + 1 {
                    return Err(ResidualError::Input(format!(
                        "episode of {frames} frames is too short for {steps}-step segments"
                    )));
                }
                let start = rng.random_range(first..=frames - steps - 1);
                let scene = Scene::new(
                    &self.meta,
                    &ep.episode,
                    Window { start, steps },
                    &self.scene_cfg,
                )?;
                // A volume's interior is not tracked: the fill at this frame is other
                // material points than the start frame's, even when it happens to have as
                // many (1-3 % of the sloth's and teddy's frames), so the start frame's springs
                // would join the wrong particles. Such a scene gets a backbone of its own.
                // (Carrying the start frame's interior along with the surface instead, so the
                // evaluation's backbone could run here, trained worse networks:
                // docs/residual-log.md, "Carried interiors".)
                let fresh_interior =
                    self.meta.structure == Structure::Volume && scene.particles() > scene.tracked;
                let backbone = if scene.particles() == ep.base.particles() && !fresh_interior {
                    None
                } else {
                    Some(scene.backbone(&self.params, &scene.sim_config(), (self.options)())?)
                };
                let history = History::from_episode(&scene, &ep.episode, self.meta.fps)?;
                (scene, history, backbone)
            }
        };
        let angle = if augment {
            rng.random_range(0.0..std::f32::consts::TAU)
        } else {
            0.0
        };
        let (scene, history) = if angle != 0.0 {
            (
                rotate_scene(&scene, angle)?,
                rotate_history(&history, angle),
            )
        } else {
            (scene, history)
        };
        Ok(Sample {
            scene,
            history,
            backbone,
            episode: e,
        })
    }

    /// The backbone a sample runs with.
    pub fn backbone<'a>(&'a self, sample: &'a Sample) -> &'a Backbone {
        sample
            .backbone
            .as_ref()
            .unwrap_or(&self.episodes[sample.episode].backbone)
    }
}

/// Statistics of one optimiser step.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct StepStats {
    /// Mean rollout loss: sum over steps of the per-step loss ([`TrainConfig::loss`]; cm² or cm).
    pub loss: f64,
    /// Mean loss of the backbone alone on the same segments (same start, no residual), in the
    /// same unit: `loss / backbone_loss` below 1 means the network improves on the backbone
    /// where it is trained. NaN when no segment was scored, and on the steps
    /// [`TrainConfig::yardstick_every`] skips.
    pub backbone_loss: f64,
    /// Gradient norm before clipping.
    pub grad_norm: f64,
    /// Learning rate used.
    pub lr: f64,
    /// Rollouts of the batch that diverged (skipped).
    pub diverged: usize,
}

/// Adam state and the training loop's position.
pub struct Trainer {
    /// The network being trained.
    pub net: ResidualNet,
    /// Settings.
    pub cfg: TrainConfig,
    /// Optimiser steps done.
    pub step: usize,
    vars: Vec<(String, Var)>,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
    /// Moving average of the weights, when `cfg.ema_decay > 0`.
    ema: Option<Vec<Tensor>>,
    starts: Option<Vec<Trajectory>>,
    guided: Option<Vec<Trajectory>>,
    /// Episodes whose guided trajectory diverged and which start from the backbone's own.
    guided_fallbacks: usize,
}

const BETA1: f64 = 0.9;
const BETA2: f64 = 0.999;
const EPS: f64 = 1e-8;

impl Trainer {
    /// A trainer for `net` (Adam moments at zero).
    pub fn new(net: ResidualNet, cfg: TrainConfig) -> Result<Self> {
        if net.ensemble_size() > 1 {
            return Err(ResidualError::Config(format!(
                "an ensemble of {} networks cannot be trained as a whole: train its members, \
                 then combine them",
                net.ensemble_size()
            )));
        }
        let vars = net.named_vars();
        let m = vars
            .iter()
            .map(|(_, v)| v.zeros_like())
            .collect::<candle_core::Result<Vec<_>>>()?;
        let v = m.clone();
        if !(cfg.ema_decay.is_finite() && (0.0..1.0).contains(&cfg.ema_decay)) {
            return Err(ResidualError::Input(format!(
                "ema_decay {} is not in [0, 1)",
                cfg.ema_decay
            )));
        }
        // A NaN or negative rate would train on and save a network of NaN weights (every later
        // rollout then diverges, which a step tolerates), and a zero clip would never move it.
        let positive = |x: f64| x.is_finite() && x > 0.0;
        let non_negative = |x: f64| x.is_finite() && x >= 0.0;
        if !positive(cfg.lr) || !non_negative(cfg.lr_min) {
            return Err(ResidualError::Input(format!(
                "learning rates must be finite, lr > 0 and lr_min >= 0 (got lr {}, lr_min {})",
                cfg.lr, cfg.lr_min
            )));
        }
        if !positive(cfg.clip) {
            return Err(ResidualError::Input(format!(
                "the gradient clip must be finite and > 0, got {}",
                cfg.clip
            )));
        }
        if !non_negative(cfg.weight_decay) || !non_negative(f64::from(cfg.input_noise_m)) {
            return Err(ResidualError::Input(format!(
                "weight_decay and input_noise_m must be finite and >= 0 (got {} and {})",
                cfg.weight_decay, cfg.input_noise_m
            )));
        }
        if cfg.rollout_steps == 0 || cfg.batch == 0 {
            return Err(ResidualError::Input(format!(
                "rollout_steps ({}) and batch ({}) must be at least 1",
                cfg.rollout_steps, cfg.batch
            )));
        }
        let ema = (cfg.ema_decay > 0.0)
            .then(|| {
                vars.iter()
                    .map(|(_, v)| v.as_tensor().copy())
                    .collect::<candle_core::Result<Vec<_>>>()
            })
            .transpose()?;
        Ok(Trainer {
            net,
            cfg,
            step: 0,
            vars,
            m,
            v,
            ema,
            starts: None,
            guided: None,
            guided_fallbacks: 0,
        })
    }

    /// The random generator of optimiser step `t`: derived from the seed and the step alone,
    /// so a resumed run draws the same samples as an uninterrupted one.
    pub fn rng_at(&self, t: usize) -> ChaCha8Rng {
        ChaCha8Rng::seed_from_u64(self.cfg.seed ^ (t as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
    }

    /// The generator of step `t`'s input noise: a stream apart from [`Trainer::rng_at`], so
    /// turning the noise on leaves the sampled segments as they were.
    fn noise_rng_at(&self, t: usize) -> ChaCha8Rng {
        let mut rng = self.rng_at(t);
        rng.set_stream(1);
        rng
    }

    /// How many training episodes' guided trajectories diverged, so that their guided
    /// segments start from the backbone's own trajectory ([`StartFrom::Guided`],
    /// [`StartFrom::GuidedRecorded`]; 0 until the first step builds them).
    pub fn guided_fallbacks(&self) -> usize {
        self.guided_fallbacks
    }

    /// One optimiser step on a batch drawn from `set`.
    pub fn train_step(&mut self, set: &TrainSet) -> Result<StepStats> {
        let guided = matches!(
            self.cfg.start_from,
            StartFrom::Guided | StartFrom::GuidedRecorded
        );
        if guided && self.guided.is_none() {
            let (trajectories, fallbacks) =
                set.guided_trajectories(self.net.config().residual_scale)?;
            self.guided = Some(trajectories);
            self.guided_fallbacks = fallbacks;
        }
        if matches!(self.cfg.start_from, StartFrom::Rollout | StartFrom::Guided) {
            let every = self.cfg.refresh_every;
            if every > 0 && self.step > 0 && self.step.is_multiple_of(every) {
                self.starts = Some(set.trajectories(Some(&self.net))?);
            } else if self.starts.is_none() {
                self.starts = Some(set.trajectories(None)?);
            }
        }
        let mut rng = self.rng_at(self.step);
        let samples = (0..self.cfg.batch)
            .map(|b| {
                let starts = match self.cfg.start_from {
                    StartFrom::Rollout => self.starts.as_deref(),
                    StartFrom::Guided if b % 2 == 0 => self.guided.as_deref(),
                    StartFrom::Guided => self.starts.as_deref(),
                    StartFrom::GuidedRecorded if b % 2 == 0 => self.guided.as_deref(),
                    StartFrom::GuidedRecorded | StartFrom::Recorded => None,
                };
                set.sample_from(&mut rng, self.cfg.rollout_steps, self.cfg.augment, starts)
            })
            .collect::<Result<Vec<_>>>()?;
        let samples = if self.cfg.input_noise_m > 0.0 {
            let mut noise = self.noise_rng_at(self.step);
            samples
                .into_iter()
                .map(|s| perturbed(s, self.cfg.input_noise_m, &mut noise))
                .collect::<Result<Vec<_>>>()?
        } else {
            samples
        };
        self.train_on(set, &samples)
    }

    /// One optimiser step on the given samples (drawn from `set`).
    pub fn train_on(&mut self, set: &TrainSet, samples: &[Sample]) -> Result<StepStats> {
        let mut rng = self.rng_at(self.step);
        // Drawn in the batch's order before any rollout runs, so both ways of computing the
        // gradients roll out the same segments with the same curve orders.
        let opts: Vec<RolloutOptions> = samples
            .iter()
            .map(|_| {
                let mut curves = [0usize, 1, 2, 3];
                for i in (1..curves.len()).rev() {
                    curves.swap(i, rng.random_range(0..=i));
                }
                RolloutOptions {
                    steps: self.cfg.rollout_steps,
                    train: true,
                    curves,
                    sim_gradient: self.cfg.sim_gradient,
                }
            })
            .collect();
        let yardstick =
            self.cfg.yardstick_every > 0 && self.step.is_multiple_of(self.cfg.yardstick_every);
        let batch = batch_grads::Batch {
            net: &self.net,
            vars: &self.vars,
            set,
            cfg: &self.cfg,
            yardstick,
        };
        let out = batch.grads(samples, &opts)?;
        let lr = self.cfg.lr_at(self.step);
        self.step += 1;
        let Some(out) = out else {
            return Ok(StepStats {
                loss: f64::NAN,
                backbone_loss: f64::NAN,
                grad_norm: f64::NAN,
                lr,
                diverged: samples.len(),
            });
        };
        let value = f64::from(out.loss.to_scalar::<f32>()?);
        if !value.is_finite() {
            return Err(ResidualError::Diverged {
                step: self.step,
                what: format!("training loss {value}"),
            });
        }
        let (base_sum, base_n) = out.backbone;
        let diverged = out.diverged;
        let g = out.grads;
        let mut sq = 0f64;
        for t in g.iter().flatten() {
            sq += f64::from(t.sqr()?.sum_all()?.to_scalar::<f32>()?);
        }
        let norm = sq.sqrt();
        if !norm.is_finite() {
            return Err(ResidualError::Diverged {
                step: self.step,
                what: format!("gradient norm {norm}"),
            });
        }
        let scale = if norm > self.cfg.clip {
            self.cfg.clip / norm
        } else {
            1.0
        };
        let t = self.step as i32;
        let (c1, c2) = (1.0 - BETA1.powi(t), 1.0 - BETA2.powi(t));
        for (i, grad) in g.iter().enumerate() {
            let Some(grad) = grad else { continue };
            let grad = (grad * scale)?;
            self.m[i] = ((&self.m[i] * BETA1)? + (&grad * (1.0 - BETA1))?)?;
            self.v[i] = ((&self.v[i] * BETA2)? + (grad.sqr()? * (1.0 - BETA2))?)?;
            let update = ((&self.m[i] / c1)? / ((&self.v[i] / c2)?.sqrt()? + EPS)?)?;
            let var = &self.vars[i].1;
            let decayed = if self.cfg.weight_decay > 0.0 {
                (var.as_tensor() * (1.0 - lr * self.cfg.weight_decay))?
            } else {
                var.as_tensor().clone()
            };
            var.set(&(decayed - (update * lr)?)?)?;
            if let Some(ema) = &mut self.ema {
                let d = self.cfg.ema_decay;
                ema[i] = ((&ema[i] * d)? + (var.as_tensor() * (1.0 - d))?)?;
            }
        }
        Ok(StepStats {
            loss: value,
            backbone_loss: if base_n > 0 {
                base_sum / base_n as f64
            } else {
                f64::NAN
            },
            grad_norm: norm,
            lr,
            diverged,
        })
    }

    /// Runs `f` on the network with the moving-average weights (`ema_decay > 0`) or, with the
    /// average off, on the current weights; the current weights are restored afterwards.
    pub fn with_averaged<R>(&self, f: impl FnOnce(&ResidualNet) -> R) -> Result<R> {
        let Some(ema) = &self.ema else {
            return Ok(f(&self.net));
        };
        let current = self
            .vars
            .iter()
            .map(|(_, v)| v.as_tensor().copy())
            .collect::<candle_core::Result<Vec<_>>>()?;
        for ((_, var), avg) in self.vars.iter().zip(ema) {
            var.set(avg)?;
        }
        let out = f(&self.net);
        for ((_, var), cur) in self.vars.iter().zip(&current) {
            var.set(cur)?;
        }
        Ok(out)
    }

    /// Writes parameters and Adam moments to `path` (safetensors) and the step count beside it
    /// (`path` with extension `json`).
    pub fn save_checkpoint(&self, path: &Path) -> Result<()> {
        let mut map: HashMap<String, Tensor> = HashMap::new();
        for (i, (name, var)) in self.vars.iter().enumerate() {
            map.insert(format!("param.{name}"), var.as_tensor().clone());
            map.insert(format!("adam_m.{name}"), self.m[i].clone());
            map.insert(format!("adam_v.{name}"), self.v[i].clone());
            if let Some(ema) = &self.ema {
                map.insert(format!("ema.{name}"), ema[i].clone());
            }
        }
        // The segment starts are part of the state: a resumed run must sample from the same
        // trajectories as an uninterrupted one.
        for (e, traj) in self.starts.iter().flatten().enumerate() {
            map.insert(format!("start.{e}.x"), stack(&traj.x, self.net.device())?);
            map.insert(format!("start.{e}.v"), stack(&traj.v, self.net.device())?);
        }
        crate::model::save_tensors_atomic(&map, path)?;
        let json = path.with_extension("json");
        let text =
            serde_json::json!({ "step": self.step, "model": self.net.config(), "train": self.cfg })
                .to_string();
        dataset::write_atomic(&json, text.as_bytes())?;
        Ok(())
    }

    /// Restores parameters, Adam moments and the step count written by
    /// [`Trainer::save_checkpoint`].
    pub fn load_checkpoint(&mut self, path: &Path) -> Result<()> {
        let map = candle_core::safetensors::load(path, self.net.device())?;
        let get = |k: String| {
            map.get(&k)
                .cloned()
                .ok_or_else(|| ResidualError::Input(format!("checkpoint lacks {k}")))
        };
        for (i, (name, var)) in self.vars.iter().enumerate() {
            var.set(&get(format!("param.{name}"))?)?;
            self.m[i] = get(format!("adam_m.{name}"))?;
            self.v[i] = get(format!("adam_v.{name}"))?;
            if let Some(ema) = &mut self.ema {
                ema[i] = get(format!("ema.{name}"))?;
            }
        }
        let mut starts = Vec::new();
        while let (Some(x), Some(v)) = (
            map.get(&format!("start.{}.x", starts.len())),
            map.get(&format!("start.{}.v", starts.len())),
        ) {
            starts.push(Trajectory {
                x: unstack(x)?,
                v: unstack(v)?,
            });
        }
        self.starts = (!starts.is_empty()).then_some(starts);
        let json = path.with_extension("json");
        let text = std::fs::read_to_string(&json).map_err(|source| ResidualError::Io {
            path: json.display().to_string(),
            cause: source,
        })?;
        let v: serde_json::Value =
            serde_json::from_str(&text).map_err(|source| ResidualError::Json {
                path: json.display().to_string(),
                cause: source,
            })?;
        self.step = v["step"].as_u64().unwrap_or(0) as usize;
        Ok(())
    }
}

/// `sample` with Gaussian noise of `sigma_m` metres per axis on every free particle's start
/// position and history positions ([`TrainConfig::input_noise_m`]). Held particles follow their
/// gripper and keep their positions.
fn perturbed(mut sample: Sample, sigma_m: f32, rng: &mut ChaCha8Rng) -> Result<Sample> {
    let normal = rand_distr::Normal::new(0.0f32, sigma_m)
        .map_err(|e| ResidualError::Input(format!("input noise {sigma_m} m: {e}")))?;
    let held = &sample.scene.held;
    let frames = std::iter::once(&mut sample.scene.init.x).chain(sample.history.x.iter_mut());
    for x in frames {
        for (i, p) in x.iter_mut().enumerate() {
            if held.get(i).is_none_or(|&g| g < 0) {
                *p += Vec3::new(rng.sample(normal), rng.sample(normal), rng.sample(normal));
            }
        }
    }
    Ok(sample)
}

/// `(T, N, 3)` tensor of a sequence of particle arrays.
fn stack(frames: &[Vec<Vec3>], dev: &candle_core::Device) -> Result<Tensor> {
    let n = frames.first().map_or(0, Vec::len);
    let flat: Vec<f32> = frames
        .iter()
        .flat_map(|f| f.iter().flat_map(|p| p.to_array()))
        .collect();
    Ok(Tensor::from_vec(flat, (frames.len(), n, 3), dev)?)
}

/// Inverse of [`stack`].
fn unstack(t: &Tensor) -> Result<Vec<Vec<Vec3>>> {
    let (_, n, _) = t.dims3()?;
    let flat: Vec<f32> = t.flatten_all()?.to_vec1()?;
    Ok(flat
        .chunks_exact(3 * n.max(1))
        .map(|f| {
            f.chunks_exact(3)
                .map(|c| Vec3::new(c[0], c[1], c[2]))
                .collect()
        })
        .collect())
}
