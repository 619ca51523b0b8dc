//! Training: segment sampling, multi-step rollout loss, Adam with cosine decay and gradient
//! clipping, resumable checkpoints.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Tensor, Var};
use dataset::{Dataset, Episode, Split};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use scene::{Protocol, Scene, SceneConfig, Window};
use serde::{Deserialize, Serialize};
use springs::{Backbone, SpringParams};

use crate::augment::{rotate_history, rotate_scene};
use crate::{History, ResidualError, ResidualNet, Result, RolloutOptions, hybrid_rollout};

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
    episode: Episode,
    base: Scene,
    backbone: Backbone,
}

/// The training episodes of a dataset with the fitted backbone.
pub struct TrainSet {
    episodes: Vec<TrainEpisode>,
    meta: dataset::DatasetMeta,
    params: SpringParams,
    scene_cfg: SceneConfig,
}

/// One training rollout: a scene over a short window, its history and its backbone.
pub struct Sample {
    /// The scene (possibly rotated).
    pub scene: Scene,
    /// The history frames (rotated like the scene).
    pub history: History,
    /// Backbone for this segment when it could not reuse the episode's (interior fill
    /// differs between frames), else `None`.
    backbone: Option<Backbone>,
    episode: usize,
}

impl TrainSet {
    /// Loads the `split` episodes of `data` and builds their backbones from `params`.
    pub fn new(
        data: &Dataset,
        split: Split,
        params: &SpringParams,
        scene_cfg: &SceneConfig,
    ) -> Result<Self> {
        let mut episodes = Vec::new();
        for i in data.split_indices(split) {
            let episode = data.load_episode(i)?;
            let window = Protocol::Paper.window(episode.frames())?;
            let base = Scene::new(&data.meta, &episode, window, scene_cfg)?;
            let backbone = base.backbone(params, &base.sim_config(), Default::default())?;
            episodes.push(TrainEpisode {
                episode,
                base,
                backbone,
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

    /// A random segment of `steps` steps starting at a frame with two recorded history frames,
    /// rotated by a random angle about z when `augment`.
    pub fn sample(&self, rng: &mut ChaCha8Rng, steps: usize, augment: bool) -> Result<Sample> {
        let e = rng.random_range(0..self.episodes.len());
        let ep = &self.episodes[e];
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
        let backbone = if scene.particles() == ep.base.particles() {
            None
        } else {
            Some(scene.backbone(&self.params, &scene.sim_config(), Default::default())?)
        };
        let history = History::from_episode(&scene, &ep.episode, self.meta.fps)?;
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
    /// Mean rollout loss (sum over steps of the mean squared distance, cm²).
    pub loss: f64,
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
}

const BETA1: f64 = 0.9;
const BETA2: f64 = 0.999;
const EPS: f64 = 1e-8;

impl Trainer {
    /// A trainer for `net` (Adam moments at zero).
    pub fn new(net: ResidualNet, cfg: TrainConfig) -> Result<Self> {
        let vars = net.named_vars();
        let m = vars
            .iter()
            .map(|(_, v)| v.zeros_like())
            .collect::<candle_core::Result<Vec<_>>>()?;
        let v = m.clone();
        Ok(Trainer {
            net,
            cfg,
            step: 0,
            vars,
            m,
            v,
        })
    }

    /// The random generator of optimiser step `t`: derived from the seed and the step alone,
    /// so a resumed run draws the same samples as an uninterrupted one.
    pub fn rng_at(&self, t: usize) -> ChaCha8Rng {
        ChaCha8Rng::seed_from_u64(self.cfg.seed ^ (t as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
    }

    /// One optimiser step on a batch drawn from `set`.
    pub fn train_step(&mut self, set: &TrainSet) -> Result<StepStats> {
        let mut rng = self.rng_at(self.step);
        let samples = (0..self.cfg.batch)
            .map(|_| set.sample(&mut rng, self.cfg.rollout_steps, self.cfg.augment))
            .collect::<Result<Vec<_>>>()?;
        self.train_on(set, &samples)
    }

    /// One optimiser step on the given samples (drawn from `set`).
    pub fn train_on(&mut self, set: &TrainSet, samples: &[Sample]) -> Result<StepStats> {
        let mut rng = self.rng_at(self.step);
        let mut total: Option<Tensor> = None;
        let (mut used, mut diverged) = (0usize, 0usize);
        for sample in samples {
            let mut curves = [0usize, 1, 2, 3];
            for i in (1..curves.len()).rev() {
                curves.swap(i, rng.random_range(0..=i));
            }
            let opts = RolloutOptions {
                steps: self.cfg.rollout_steps,
                train: true,
                curves,
            };
            match hybrid_rollout(
                &self.net,
                set.backbone(sample),
                &sample.scene,
                &sample.history,
                opts,
            ) {
                Ok(out) => {
                    let l = out
                        .loss
                        .ok_or_else(|| ResidualError::Input("no loss".into()))?;
                    total = Some(match total {
                        Some(t) => (t + l)?,
                        None => l,
                    });
                    used += 1;
                }
                Err(ResidualError::Diverged { .. }) => diverged += 1,
                Err(e) => return Err(e),
            }
        }
        let lr = self.cfg.lr_at(self.step);
        self.step += 1;
        let Some(total) = total else {
            return Ok(StepStats {
                loss: f64::NAN,
                grad_norm: f64::NAN,
                lr,
                diverged,
            });
        };
        let loss = (total / used as f64)?;
        let value = f64::from(loss.to_scalar::<f32>()?);
        if !value.is_finite() {
            return Err(ResidualError::Diverged {
                step: self.step,
                what: format!("training loss {value}"),
            });
        }
        let grads = loss.backward()?;
        let g: Vec<Option<Tensor>> = self
            .vars
            .iter()
            .map(|(_, v)| grads.get(v.as_tensor()).cloned())
            .collect();
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
            var.set(&(var.as_tensor() - (update * lr)?)?)?;
        }
        Ok(StepStats {
            loss: value,
            grad_norm: norm,
            lr,
            diverged,
        })
    }

    /// Writes parameters and Adam moments to `path` (safetensors) and the step count beside it
    /// (`path` with extension `json`).
    pub fn save_checkpoint(&self, path: &Path) -> Result<()> {
        let mut map: HashMap<String, Tensor> = HashMap::new();
        for (i, (name, var)) in self.vars.iter().enumerate() {
            map.insert(format!("param.{name}"), var.as_tensor().clone());
            map.insert(format!("adam_m.{name}"), self.m[i].clone());
            map.insert(format!("adam_v.{name}"), self.v[i].clone());
        }
        let tmp = path.with_extension("tmp");
        candle_core::safetensors::save(&map, &tmp)?;
        std::fs::rename(&tmp, path).map_err(|source| ResidualError::Io {
            path: path.display().to_string(),
            source,
        })?;
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
        }
        let json = path.with_extension("json");
        let text = std::fs::read_to_string(&json).map_err(|source| ResidualError::Io {
            path: json.display().to_string(),
            source,
        })?;
        let v: serde_json::Value =
            serde_json::from_str(&text).map_err(|source| ResidualError::Json {
                path: json.display().to_string(),
                source,
            })?;
        self.step = v["step"].as_u64().unwrap_or(0) as usize;
        Ok(())
    }
}
