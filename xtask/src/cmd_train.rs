//! `cargo xtask train`: train PGRD's residual network on top of the run's fitted backbone.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use dataset::{Dataset, Split};
use indicatif::{ProgressBar, ProgressStyle};
use residual::{
    Combine, EncoderKind, ModelConfig, ResidualError, ResidualKind, ResidualNet, SimGradient,
    StartFrom, TrainConfig, TrainLoss, TrainSet, Trainer, clearly_better,
};
use serde::{Deserialize, Serialize};

use crate::common::{ProtocolArg, read_backbone};
use crate::report::write_json;

/// Training stops, with status `diverged`, after this many optimiser steps in a row in which
/// every rollout diverged (each such step leaves the network unchanged).
const STALLED_STEPS: usize = 10;

/// `--encoder`.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum EncoderArg {
    /// Serialized point transformer (PTv3-style), the paper's.
    Ptv3,
    /// PointNet++-style set abstraction (ablation).
    Pointnet,
}

/// `--start-from`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum StartArg {
    /// The model's own rollout states (what evaluation meets).
    Rollout,
    /// The recorded frames (the reference code's sampling).
    Recorded,
    /// Half from a guided backbone rollout near the truth, half from the model's own.
    Guided,
    /// Half from the guided backbone rollout, half from the recorded frames.
    GuidedRecorded,
}

/// `--loss`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LossArg {
    /// Mean squared distance to the truth, cm² (the paper's).
    Mse,
    /// Mean Euclidean distance to the truth, cm (the evaluation's MDE).
    Distance,
}

/// `--sim-gradient`.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum SimGradientArg {
    /// None: a step's residual is scored on that step only (the paper's training).
    Detached,
    /// Through free flight: later steps charge a velocity residual for the motion it keeps
    /// causing.
    FreeFlight,
    /// Through the backbone step's own adjoint (springs, dashpots, ground, grasp): later steps
    /// charge a residual for what the backbone actually does with it.
    Adjoint,
}

/// Arguments of `train`.
#[derive(Clone, clap::Args)]
pub struct TrainArgs {
    /// Dataset directory (its train split is used).
    #[arg(long)]
    pub data: PathBuf,
    /// Run directory holding backbone.json; gets residual.safetensors, residual.json,
    /// train.json and a resumable checkpoint (train_ckpt.*).
    #[arg(long)]
    pub run: PathBuf,
    /// Optimiser steps.
    #[arg(long, default_value_t = 2000)]
    pub iterations: usize,
    /// Rollouts per optimiser step (>= 1).
    #[arg(long, default_value_t = 2, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub batch: usize,
    /// Model steps per training rollout.
    #[arg(long, default_value_t = 5)]
    pub rollout_steps: usize,
    /// Initial learning rate (cosine decay to --lr-min over the iterations).
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Final learning rate.
    #[arg(long, default_value_t = 1e-5)]
    pub lr_min: f64,
    /// Gradient-norm clip (of the loss in cm² or cm, see --loss).
    #[arg(long, default_value_t = 1.0)]
    pub clip: f64,
    /// Seed of initialisation, sampling and augmentation.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Disable the random rotation about the vertical axis.
    #[arg(long)]
    pub no_augment: bool,
    /// Worker threads for candle and rayon (1 was fastest for this network on 2 cores).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Save a resumable checkpoint every this many steps.
    #[arg(long, default_value_t = 100)]
    pub checkpoint_every: usize,
    /// Also keep the network every this many steps as
    /// `<run>/snapshots/step_<N>/residual.safetensors` (0: never), e.g. to evaluate how the
    /// rollout error moves along training.
    #[arg(long, default_value_t = 0)]
    pub snapshot_every: usize,
    /// Hold this many training episodes out of the optimiser's sampling (the last ones of the
    /// split: whole recordings, as the val split) and choose the network by its rollout MDE
    /// over their full evaluation windows: the backbone itself (the step-0 network without its
    /// residual; with --init-from, that network), replaced at each evaluation (every
    /// --select-every steps and at the end) by one that beats the current choice by more than
    /// one standard error of the paired per-episode differences; the choice is written to
    /// residual.safetensors (0: no selection, the last network is written). The val split is
    /// never used. See docs/residual.md.
    #[arg(long, default_value_t = 0)]
    pub holdout: usize,
    /// Instead of --holdout: choose the network, by the same rule, on the dataset's `val`
    /// split and train on every training episode. Only for a development dataset whose `val`
    /// is a selection set and whose `test` is what gets reported (`dev-split --select-val N`,
    /// e.g. on `gen --val <more>` data): a dataset without a `test` split is refused, so that
    /// no one chooses on the episodes they report. See docs/residual.md.
    #[arg(long)]
    pub select_on_val: bool,
    /// With --holdout or --select-on-val: evaluate the rollout MDE of the episodes chosen on
    /// every this many optimiser steps (and at the end).
    #[arg(long, default_value_t = 200)]
    pub select_every: usize,
    /// Ignore an existing checkpoint and start over.
    #[arg(long)]
    pub restart: bool,
    /// Stop (after saving) once this many minutes of training have passed in this session.
    #[arg(long, value_parser = crate::common::parse_minutes)]
    pub max_minutes: Option<f64>,
    /// Ablation: encoder family.
    #[arg(long, value_enum, default_value_t = EncoderArg::Ptv3)]
    pub encoder: EncoderArg,
    /// Channels of the encoder's stages, finest first (default 16,32,64: sized for a 2-core
    /// CPU, docs/residual.md "Encoder"); one more stage per entry. Each must be a multiple of
    /// the 16-channel attention head.
    #[arg(long, value_delimiter = ',')]
    pub enc_channels: Option<Vec<usize>>,
    /// Transformer blocks per encoder stage (default 1 each; as many entries as
    /// --enc-channels).
    #[arg(long, value_delimiter = ',')]
    pub enc_depths: Option<Vec<usize>>,
    /// Channels of the decoder's stages, coarsest first (default 32,32; one entry fewer than
    /// --enc-channels); the last is the per-particle feature width.
    #[arg(long, value_delimiter = ',')]
    pub dec_channels: Option<Vec<usize>>,
    /// Transformer blocks per decoder stage (default 1 each; as many entries as
    /// --dec-channels).
    #[arg(long, value_delimiter = ',')]
    pub dec_depths: Option<Vec<usize>>,
    /// Ablation: a linear head instead of the Fourier-feature decoder.
    #[arg(long)]
    pub no_decoder: bool,
    /// Ablation: no temporal aggregator (Δv = 0.1 r).
    #[arg(long)]
    pub no_temporal: bool,
    /// Ablation: add the temporal offset instead of gating it.
    #[arg(long)]
    pub additive: bool,
    /// Ablation: correct positions instead of velocities.
    #[arg(long)]
    pub position_residual: bool,
    /// Beyond the paper: also feed each particle the nearest closed gripper's offset and
    /// velocity (docs/residual.md, "Gripper inputs").
    #[arg(long)]
    pub gripper_inputs: bool,
    /// Beyond the paper: also feed each particle its height above the ground plane
    /// (docs/residual.md, "Ground inputs").
    #[arg(long)]
    pub ground_inputs: bool,
    /// Beyond the paper: also feed each particle its position in the backbone's rest shape,
    /// a material coordinate (docs/residual.md, "Rest inputs").
    #[arg(long)]
    pub rest_inputs: bool,
    /// Beyond the paper: also correct the particles a closed gripper holds, which moves the
    /// grasp itself (for grasps that slip or grippers that lag their recorded path;
    /// docs/residual-log.md, "The grasp the network may not correct").
    #[arg(long)]
    pub held_residual: bool,
    /// Where training segments start: `guided` (half from a backbone rollout pulled toward
    /// the recorded frames, half as `rollout`), `rollout` (the model's own states along the
    /// evaluation window, refreshed with the hybrid model every --refresh-every steps),
    /// `recorded` (tracked frames, as the reference code) or `guided-recorded` (half
    /// guided, half recorded). See docs/residual.md. Several, comma-separated (e.g.
    /// guided,recorded), need --holdout: one network per start mode and bound, and the held-out
    /// episodes choose (as for several --residual-scale values).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "guided")]
    pub start_from: Vec<StartArg>,
    /// Re-run the hybrid model over the training episodes every this many steps (0: never).
    #[arg(long, default_value_t = 0)]
    pub refresh_every: usize,
    /// Evaluation protocol whose window training segments are drawn from (use the one you
    /// evaluate with).
    #[arg(long, value_enum, default_value_t = ProtocolArg::Paper)]
    pub protocol: ProtocolArg,
    /// Residual bound, m/s per axis and step (0.1 in the paper). Several, comma-separated
    /// (e.g. 0.1,0.5,1,2), need --holdout: one network is trained per bound in
    /// <run>/bound_<b>/ (<run>/<start>_bound_<b>/ with several --start-from) and the run keeps
    /// the first start mode's narrowest bound unless another candidate's trained network is
    /// clearly better on the held-out episodes (docs/residual.md, "Choosing the bound").
    #[arg(long, value_delimiter = ',', default_value = "0.1")]
    pub residual_scale: Vec<f32>,
    /// Loss of each rollout step: `mse` (cm², the paper's) or `distance` (cm, the MDE that
    /// evaluation reports; robust to segments the bounded residual cannot fix). Several,
    /// comma-separated, make one more dimension of the recipe choice (needs `--holdout`).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "mse")]
    pub loss: Vec<LossArg>,
    /// How gradients cross the backbone: `detached` (the paper's: each residual is scored on
    /// its own step's positions only), `free-flight` (a velocity residual is also charged for
    /// the displacement it keeps causing at later steps of the rollout, springs ignored) or
    /// `adjoint` (through the backbone step's own linearisation). See docs/residual.md.
    #[arg(long, value_enum, default_value_t = SimGradientArg::Detached)]
    pub sim_gradient: SimGradientArg,
    /// Keep an exponential moving average of the weights with this decay per optimiser step
    /// (0: off; e.g. 0.995 averages over about 200 steps) and save, select and report the
    /// averaged network instead of the last iterate.
    #[arg(long, default_value_t = 0.0)]
    pub ema_decay: f64,
    /// Score the backbone alone on the training segments every this many optimiser steps (the
    /// yardstick of `train.json`'s `backbone_loss` and the printed "x the backbone's" ratios,
    /// which compare the steps that have it; 0: never, 1: every step). Each scoring costs a
    /// second backbone rollout per segment; nothing learned depends on it.
    #[arg(long, default_value_t = 10)]
    pub yardstick_every: usize,
    /// Decoupled weight decay (AdamW) per unit learning rate; 0: off, the paper's Adam.
    #[arg(long, default_value_t = 0.0)]
    pub weight_decay: f64,
    /// Gaussian noise (metres, per axis) on each training segment's start and history
    /// positions of the free particles, the targets unchanged: teaches the network to pull a
    /// drifted state back (docs/residual.md, "Input noise and weight decay"); 0: off.
    #[arg(long, default_value_t = 0.0)]
    pub input_noise: f32,
    /// Roll out and differentiate the batch's segments in parallel, one per thread of
    /// --threads, their gradients summed in the batch's order: the same weights on any number
    /// of threads, equal to the default way's to rounding (not bit for bit, so runs with and
    /// without it differ in their digits); faster when --threads leaves a thread per segment
    /// (docs/BENCHMARKS.md, "Training").
    #[arg(long)]
    pub parallel_batch: bool,
    /// Start from the weights of this network (a `residual.safetensors` with its
    /// `residual.json` beside it) instead of a fresh initialisation, e.g. to fine-tune a
    /// network trained on 5-step segments on whole windows. Its configuration must match the
    /// model flags given here (bound, encoder, inputs, ablations). With --holdout, step 0 is
    /// this network, so a fine-tuned one is kept only when clearly better than it. Ignored
    /// when resuming from a checkpoint (which holds the weights).
    #[arg(long)]
    pub init_from: Option<PathBuf>,
    /// With several --residual-scale or --start-from values: train this many candidate
    /// recipes at once, each in its own thread with --threads workers (2 with --threads 1 on a
    /// 2-core machine). Each candidate's network is the one it would be on its own, as long as
    /// it finishes its --iterations (a --max-minutes limit counts the candidate's own time, so
    /// a shared machine may stop it earlier).
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// With the recipe choice: when the chosen candidate is a trained network at the widest
    /// bound tried for its loss and start mode (the ladder's edge), train that loss and start
    /// mode at this many wider bounds, each three times the one before, and let the same rule
    /// choose again among all (0: the ladder as given). See docs/residual.md, "Widening the
    /// ladder".
    #[arg(long, default_value_t = 0)]
    pub widen_bounds: usize,
    /// With the recipe choice: the same at the other end of the ladder. When the chosen
    /// candidate (after any widening) is a trained network at the narrowest bound tried for its
    /// loss and start mode, train that loss and start mode at this many narrower bounds, each a
    /// third of the one before, judged after every other candidate by the same rule (0: none).
    #[arg(long, default_value_t = 0)]
    pub narrow_bounds: usize,
    /// Print only the final line.
    #[arg(long)]
    pub quiet: bool,
    /// Set by the recipe choice when candidates train at once: their progress bars share one
    /// display, each labelled with its recipe.
    #[arg(skip)]
    pub progress: Option<(indicatif::MultiProgress, String)>,
}

/// Checkpoint selection on held-out training episodes (`--holdout`) or on a development
/// dataset's val split (`--select-on-val`), in `train.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct Selection {
    /// Dataset indices of the episodes chosen on (never sampled by the optimiser).
    episodes: Vec<usize>,
    /// Their split: `train` (held out of it) or `val` (`--select-on-val`). Runs written before
    /// the option read back as `train`.
    #[serde(default = "train_split")]
    split: String,
    /// Optimiser steps between evaluations.
    every: usize,
    /// Held-out rollout MDE of the backbone alone, cm.
    backbone_mde_cm: f64,
    /// Optimiser steps at which the network was evaluated.
    steps: Vec<usize>,
    /// Held-out rollout MDE at those steps, cm (null: a rollout diverged).
    mde_cm: Vec<Option<f64>>,
    /// Step of the network in residual.safetensors.
    best_step: usize,
    /// Its held-out rollout MDE per episode, cm.
    best_episode_mde_cm: Vec<f64>,
}

fn train_split() -> String {
    "train".to_string()
}

impl Selection {
    /// Held-out MDE of the selected network, cm.
    fn best_mde_cm(&self) -> f64 {
        self.best_episode_mde_cm.iter().sum::<f64>() / self.best_episode_mde_cm.len().max(1) as f64
    }

    /// Records the held-out MDE of `trainer`'s network and saves it as the run's network when
    /// it is the first evaluated or [`residual::clearly_better`] than the one selected so far.
    ///
    /// With `first_is_backbone`, the first network recorded is that network without its
    /// residual ([`ResidualNet::without_residual`]): the choice starts at the backbone itself,
    /// so a run that keeps it predicts exactly as the backbone (an untrained network is only
    /// close to it). A run fine-tuned from another network (`--init-from`) starts at that
    /// network instead.
    /// Returns a line saying what the check found (`None` when this step was already
    /// checked).
    fn record(
        &mut self,
        held: &TrainSet,
        trainer: &Trainer,
        run: &Path,
        first_is_backbone: bool,
    ) -> anyhow::Result<Option<String>> {
        if self.steps.last() == Some(&trainer.step) {
            return Ok(None);
        }
        let quiet = match (self.steps.is_empty() && first_is_backbone, trainer.step) {
            (true, 0) => Some(trainer.with_averaged(|net| net.without_residual())??),
            _ => None,
        };
        let per_episode = match &quiet {
            Some(net) => held.rollout_mde_cm(Some(net))?,
            None => trainer.with_averaged(|net| held.rollout_mde_cm(Some(net)))??,
        };
        let mde = per_episode.iter().sum::<f64>() / per_episode.len().max(1) as f64;
        self.steps.push(trainer.step);
        self.mde_cm.push(mde.is_finite().then_some(mde));
        let diverged = per_episode.iter().filter(|m| !m.is_finite()).count();
        let held_out = per_episode.len();
        let selected =
            self.steps.len() == 1 || clearly_better(&per_episode, &self.best_episode_mde_cm);
        if selected {
            self.best_step = trainer.step;
            self.best_episode_mde_cm = per_episode;
            let path = run.join("residual.safetensors");
            match &quiet {
                Some(net) => net.save(&path)?,
                None => trainer.with_averaged(|net| net.save(&path))??,
            }
        }
        let score = if diverged > 0 {
            format!("{diverged} of {held_out} held-out rollouts diverged")
        } else {
            format!("held-out rollout MDE {mde:.3} cm")
        };
        Ok(Some(format!(
            "step {}: {score} (backbone {:.3} cm); {}",
            trainer.step,
            self.backbone_mde_cm,
            if selected {
                "selected".to_string()
            } else {
                format!("step {} stays selected", self.best_step)
            }
        )))
    }
}

/// What `train` writes to `<run>/train.json`.
#[derive(Serialize)]
struct TrainReport {
    model: &'static str,
    variant: String,
    dataset: String,
    object: String,
    episodes: usize,
    parameters: usize,
    steps_done: usize,
    status: String,
    /// Per optimiser step, in `loss_unit` (the name predates `--loss distance`).
    loss_cm2: Vec<f64>,
    loss_unit: &'static str,
    /// Per optimiser step, the backbone alone on the same segments (same unit; `null` where
    /// no segment could be scored): the network learns where `loss_cm2` falls below it.
    backbone_loss: Vec<f64>,
    grad_norm: Vec<f64>,
    lr: Vec<f64>,
    diverged_rollouts: usize,
    /// Training episodes whose guided trajectory diverged, their guided segments started from
    /// the backbone's own trajectory instead (absent when none did).
    #[serde(skip_serializing_if = "is_zero")]
    guided_fallbacks: usize,
    wall_s: f64,
    session_wall_s: f64,
    threads: usize,
    model_config: ModelConfig,
    train_config: TrainConfig,
    #[serde(skip_serializing_if = "Option::is_none")]
    selection: Option<Selection>,
    /// The network training started from (`--init-from`); absent for a fresh initialisation.
    #[serde(skip_serializing_if = "Option::is_none")]
    init_from: Option<String>,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// Blocks per stage: as given, else one per stage of the channels given, else the default's.
fn depths(
    given: &Option<Vec<usize>>,
    channels: &Option<Vec<usize>>,
    default: Vec<usize>,
) -> Vec<usize> {
    given
        .clone()
        .or_else(|| channels.as_ref().map(|c| vec![1; c.len()]))
        .unwrap_or(default)
}

fn model_config(args: &TrainArgs) -> ModelConfig {
    let sizes = ModelConfig::default();
    ModelConfig {
        enc_channels: args.enc_channels.clone().unwrap_or(sizes.enc_channels),
        enc_depths: depths(&args.enc_depths, &args.enc_channels, sizes.enc_depths),
        dec_channels: args.dec_channels.clone().unwrap_or(sizes.dec_channels),
        dec_depths: depths(&args.dec_depths, &args.dec_channels, sizes.dec_depths),
        encoder: match args.encoder {
            EncoderArg::Ptv3 => EncoderKind::Ptv3,
            EncoderArg::Pointnet => EncoderKind::Pointnet,
        },
        decoder: !args.no_decoder,
        combine: match (args.no_temporal, args.additive) {
            (true, _) => Combine::None,
            (false, true) => Combine::Add,
            (false, false) => Combine::Gate,
        },
        residual: if args.position_residual {
            ResidualKind::Position
        } else {
            ResidualKind::Velocity
        },
        residual_scale: args.residual_scale.first().copied().unwrap_or(0.1),
        gripper_inputs: args.gripper_inputs,
        ground_inputs: args.ground_inputs,
        rest_inputs: args.rest_inputs,
        held_residual: args.held_residual,
        ..ModelConfig::default()
    }
}

/// The network of `path`, checked to have the configuration `want` that the flags ask for.
fn initial_network(path: &Path, want: &ModelConfig) -> anyhow::Result<ResidualNet> {
    // A run directory is the likely slip; name the file it holds.
    let net_in_dir = path.join("residual.safetensors");
    anyhow::ensure!(
        !path.is_dir(),
        "--init-from {} is a directory; give the network file{}",
        path.display(),
        if net_in_dir.is_file() {
            format!(", e.g. {}", net_in_dir.display())
        } else {
            " (a residual.safetensors with its residual.json beside it)".into()
        }
    );
    let net = ResidualNet::load(path)
        .with_context(|| format!("reading the --init-from network {}", path.display()))?;
    let (have, want_v) = (
        serde_json::to_value(net.config())?,
        serde_json::to_value(want)?,
    );
    let mut differ = Vec::new();
    if let (Some(have), Some(want_v)) = (have.as_object(), want_v.as_object()) {
        for (key, value) in want_v {
            match have.get(key) {
                Some(old) if old == value => {}
                old => differ.push(format!(
                    "{key} {} (flags: {value})",
                    old.cloned().unwrap_or(serde_json::Value::Null)
                )),
            }
        }
    }
    anyhow::ensure!(
        differ.is_empty(),
        "--init-from {} has another configuration than the flags ask for: {}; pass the flags it \
         was trained with",
        path.display(),
        differ.join(", ")
    );
    Ok(net)
}

fn read_previous(path: &Path) -> Option<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// `Σ loss / Σ backbone` over the steps `range` where both are finite: below 1 where the
/// network beats the backbone on the segments it is trained on.
fn loss_ratio(loss: &[f64], backbone: &[f64], range: std::ops::Range<usize>) -> f64 {
    let (mut a, mut b) = (0.0, 0.0);
    for (l, k) in loss
        .get(range.clone())
        .unwrap_or_default()
        .iter()
        .zip(backbone.get(range).unwrap_or_default())
    {
        if l.is_finite() && k.is_finite() {
            a += l;
            b += k;
        }
    }
    if b > 0.0 { a / b } else { f64::NAN }
}

fn floats(v: &serde_json::Value, key: &str) -> Vec<f64> {
    v[key]
        .as_array()
        .map(|a| a.iter().map(|x| x.as_f64().unwrap_or(f64::NAN)).collect())
        .unwrap_or_default()
}

/// Trains the residual network and writes the run's files; with several bounds, start modes or
/// losses, one network per combination and the held-out episodes' choice (`crate::train_choice`).
pub fn run(args: &TrainArgs) -> anyhow::Result<()> {
    // Training writes residual.safetensors; in an ensemble's run that file is the ensemble,
    // which the run's ensemble.json only describes, so it would be lost.
    anyhow::ensure!(
        !args.run.join(crate::cmd_ensemble::RECORD).exists(),
        "{} holds an ensemble (`cargo xtask ensemble`), which training would overwrite; \
         train into a new run directory",
        args.run.display()
    );
    // A zero-step run would write the untrained network and report NaN ratios.
    anyhow::ensure!(args.iterations >= 1, "--iterations must be at least 1");
    // The network's flags (sizes, bound) are checked before any data are read.
    model_config(args)
        .validate()
        .context("the network's configuration from the flags")?;
    match (
        args.residual_scale.len(),
        args.start_from.len(),
        args.loss.len(),
    ) {
        (0, _, _) => anyhow::bail!("--residual-scale needs a value"),
        (_, 0, _) => anyhow::bail!("--start-from needs a value"),
        (_, _, 0) => anyhow::bail!("--loss needs a value"),
        (1, 1, 1) if args.widen_bounds == 0 && args.narrow_bounds == 0 => train_one(args),
        _ => crate::train_choice::run(args),
    }
}

/// The `val` split of a development dataset as the set `--select-on-val` chooses on, built as
/// the training episodes are (the same backbone and options). Refuses a dataset without a
/// `test` split: its `val` is what the user reports.
fn selection_set(
    data: &Dataset,
    backbone: &crate::common::BackboneFile,
    protocol: scene::Protocol,
) -> anyhow::Result<TrainSet> {
    anyhow::ensure!(
        !data.split_indices(Split::Test).is_empty(),
        "--select-on-val chooses the network on {}'s val split, but it has no test split to \
         report on: make a development copy first (`cargo xtask dev-split --select-val N`, or \
         --hold-out N) and report its test split",
        data.root.display()
    );
    anyhow::ensure!(
        !data.split_indices(Split::Val).is_empty(),
        "--select-on-val: {} has no val episodes to choose on",
        data.root.display()
    );
    let options = backbone.options_for(data, protocol)?;
    TrainSet::with_backbone_options(
        data,
        Split::Val,
        &backbone.params,
        &backbone.setting().scene_config(data)?,
        protocol,
        options,
    )
    .with_context(|| format!("loading the val episodes of {}", data.root.display()))
}

/// Trains one network, with the bound `args.residual_scale[0]`, the start mode
/// `args.start_from[0]` and the loss `args.loss[0]`.
fn train_one(args: &TrainArgs) -> anyhow::Result<()> {
    let t0 = Instant::now();
    // candle's matmul reads the thread count from RAYON_NUM_THREADS and runs on rayon's global
    // pool; building that pool with `threads` workers bounds both.
    rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads.max(1))
        .build_global()
        .ok();
    let data = Dataset::open(&args.data)?;
    let backbone = read_backbone(&args.run)?;
    backbone.note_other_object(&data);
    let options = backbone.options_for(&data, args.protocol.into())?;
    let mut set = TrainSet::with_backbone_options(
        &data,
        Split::Train,
        &backbone.params,
        &backbone.setting().scene_config(&data)?,
        args.protocol.into(),
        options,
    )
    .with_context(|| format!("loading training episodes of {}", args.data.display()))?;
    let held = match (args.holdout, args.select_on_val) {
        (0, false) => None,
        (n, false) => Some(set.hold_out(n)?),
        (0, true) => Some(selection_set(&data, &backbone, args.protocol.into())?),
        (_, true) => {
            anyhow::bail!("--holdout and --select-on-val both choose the network: give one of them")
        }
    };
    let held_what = if args.select_on_val {
        format!("val episodes of {}", args.data.display())
    } else {
        "held-out training episodes".to_string()
    };
    let model_cfg = model_config(args);
    let train_cfg = TrainConfig {
        iterations: args.iterations,
        rollout_steps: args.rollout_steps,
        batch: args.batch.max(1),
        lr: args.lr,
        lr_min: args.lr_min,
        decay_steps: args.iterations,
        clip: args.clip,
        augment: !args.no_augment,
        start_from: match args.start_from.first().copied().unwrap_or(StartArg::Guided) {
            StartArg::Rollout => StartFrom::Rollout,
            StartArg::Recorded => StartFrom::Recorded,
            StartArg::Guided => StartFrom::Guided,
            StartArg::GuidedRecorded => StartFrom::GuidedRecorded,
        },
        refresh_every: args.refresh_every,
        seed: args.seed,
        loss: match args.loss.first().copied().unwrap_or(LossArg::Mse) {
            LossArg::Mse => TrainLoss::Mse,
            LossArg::Distance => TrainLoss::Distance,
        },
        sim_gradient: match args.sim_gradient {
            SimGradientArg::Detached => SimGradient::Detached,
            SimGradientArg::FreeFlight => SimGradient::FreeFlight,
            SimGradientArg::Adjoint => SimGradient::Adjoint,
        },
        ema_decay: args.ema_decay,
        yardstick_every: args.yardstick_every,
        weight_decay: args.weight_decay,
        input_noise_m: args.input_noise,
        parallel_batch: args.parallel_batch,
    };
    let unit = train_cfg.loss.unit();
    let resuming = args.run.join("train_ckpt.safetensors").exists() && !args.restart;
    let net = match &args.init_from {
        Some(path) if !resuming => initial_network(path, &model_cfg)?,
        _ => ResidualNet::new(&model_cfg, args.seed)?,
    };
    let parameters = net.parameter_count();
    let mut trainer = Trainer::new(net, train_cfg.clone())?;
    let ckpt = args.run.join("train_ckpt.safetensors");
    let report_path = args.run.join("train.json");
    let (mut loss, mut gnorm, mut lrs, mut prior_wall) = (Vec::new(), Vec::new(), Vec::new(), 0.0);
    let mut base_loss = Vec::new();
    let mut selection: Option<Selection> = None;
    let mut init_from = args.init_from.as_ref().map(|p| p.display().to_string());
    if resuming {
        crate::train_resume::check(&ckpt.with_extension("json"), &model_cfg, &train_cfg)?;
        trainer
            .load_checkpoint(&ckpt)
            .with_context(|| format!("resuming from {}", ckpt.display()))?;
        if let Some(prev) = read_previous(&report_path) {
            let keep = trainer.step;
            loss = floats(&prev, "loss_cm2");
            gnorm = floats(&prev, "grad_norm");
            lrs = floats(&prev, "lr");
            base_loss = floats(&prev, "backbone_loss");
            // Runs written before the backbone loss was recorded: unknown for those steps.
            base_loss.resize(loss.len(), f64::NAN);
            base_loss.truncate(keep);
            loss.truncate(keep);
            gnorm.truncate(keep);
            lrs.truncate(keep);
            prior_wall = prev["wall_s"].as_f64().unwrap_or(0.0);
            // The checkpoint's weights descend from the network the run started from.
            if let Some(first) = prev["init_from"].as_str() {
                init_from = Some(first.to_string());
            }
            selection = serde_json::from_value::<Selection>(prev["selection"].clone())
                .ok()
                .filter(|s| {
                    held.as_ref()
                        .is_some_and(|h| h.episode_indices() == s.episodes && s.best_step <= keep)
                })
                .map(|mut s| {
                    let n = s.steps.iter().take_while(|&&t| t <= keep).count();
                    s.steps.truncate(n);
                    s.mde_cm.truncate(n);
                    s
                });
        }
        if !args.quiet {
            above_bars(bars(args), || {
                eprintln!("resuming at step {} from {}", trainer.step, ckpt.display())
            });
        }
    }
    let bar = match (&args.progress, args.quiet) {
        (_, true) => ProgressBar::hidden(),
        (Some((multi, label)), false) => {
            multi.add(ProgressBar::new(args.iterations as u64).with_prefix(label.clone()))
        }
        (None, false) => ProgressBar::new(args.iterations as u64),
    };
    bar.set_style(ProgressStyle::with_template(
        "{prefix}{bar:30} {pos}/{len} {msg} [{elapsed} < {eta}]",
    )?);
    bar.set_position(trainer.step as u64);
    let mut plain_progress =
        crate::common::PlainProgress::new(args.quiet || args.progress.is_some());
    let t_train = Instant::now();
    if let Some(held) = &held {
        let mut sel = match selection.take() {
            Some(s) => s,
            None => Selection {
                episodes: held.episode_indices(),
                split: if args.select_on_val { "val" } else { "train" }.to_string(),
                every: args.select_every.max(1),
                backbone_mde_cm: {
                    let e = held.rollout_mde_cm(None)?;
                    e.iter().sum::<f64>() / e.len().max(1) as f64
                },
                steps: Vec::new(),
                mde_cm: Vec::new(),
                best_step: trainer.step,
                best_episode_mde_cm: Vec::new(),
            },
        };
        sel.every = args.select_every.max(1);
        // The first check (the backbone, or the --init-from network) opens a selection; a
        // resumed one goes on at its next scheduled check, so that a run interrupted after a
        // checkpoint and resumed makes the same checks, and the same choice, as one that ran
        // through (an extra check between two scheduled ones can change which network wins).
        if sel.steps.is_empty()
            && let Some(line) = sel.record(held, &trainer, &args.run, init_from.is_none())?
            && !args.quiet
        {
            say(args, line);
        }
        selection = Some(sel);
    }
    let mut diverged_rollouts = 0;
    // Optimiser steps in a row whose every rollout diverged: such a step has no gradient, so
    // the network stays as it is and the next batch meets the same network.
    let mut stalled_steps = 0;
    let mut status = "done".to_string();
    let save = |trainer: &Trainer,
                loss: &[f64],
                base_loss: &[f64],
                gnorm: &[f64],
                lrs: &[f64],
                status: &str,
                diverged: usize,
                selection: &Option<Selection>|
     -> anyhow::Result<()> {
        trainer.save_checkpoint(&ckpt)?;
        if selection.is_none() {
            trainer.with_averaged(|net| net.save(&args.run.join("residual.safetensors")))??;
        }
        let session = t0.elapsed().as_secs_f64();
        write_json(
            &report_path,
            &TrainReport {
                model: "pgrd",
                variant: trainer.net.config().variant(),
                dataset: args.data.display().to_string(),
                object: data.meta.object.clone(),
                episodes: set.len(),
                parameters,
                steps_done: trainer.step,
                status: status.to_string(),
                loss_cm2: loss.to_vec(),
                loss_unit: unit,
                backbone_loss: base_loss.to_vec(),
                grad_norm: gnorm.to_vec(),
                lr: lrs.to_vec(),
                diverged_rollouts: diverged,
                guided_fallbacks: trainer.guided_fallbacks(),
                wall_s: prior_wall + t_train.elapsed().as_secs_f64(),
                session_wall_s: session,
                threads: args.threads,
                model_config: trainer.net.config().clone(),
                train_config: trainer.cfg.clone(),
                selection: selection.clone(),
                init_from: init_from.clone(),
            },
        )?;
        let checks = selection.as_ref().map(|s| crate::plots::Checks {
            steps: &s.steps,
            mde_cm: &s.mde_cm,
            backbone_mde_cm: s.backbone_mde_cm,
            best_step: s.best_step,
        });
        let svg = args.run.join("train.svg");
        let curves = crate::plots::TrainCurves {
            title: format!("{} ({})", data.meta.object, trainer.net.config().variant()),
            loss,
            backbone_loss: base_loss,
            unit,
            checks,
        };
        crate::plots::or_warn(
            crate::plots::train_svg(&svg, &curves),
            &svg.display().to_string(),
        );
        Ok(())
    };
    while trainer.step < args.iterations {
        match trainer.train_step(&set) {
            Ok(s) => {
                diverged_rollouts += s.diverged;
                stalled_steps = if s.diverged > 0 && s.loss.is_nan() {
                    stalled_steps + 1
                } else {
                    0
                };
                loss.push(s.loss);
                base_loss.push(s.backbone_loss);
                gnorm.push(s.grad_norm);
                lrs.push(s.lr);
                bar.set_message(loss_summary(&loss, &base_loss, unit));
                bar.set_position(trainer.step as u64);
            }
            Err(ResidualError::Diverged { step, what }) => {
                status = format!("diverged at optimiser step {step}: {what}");
                break;
            }
            Err(e) => return Err(e.into()),
        }
        if stalled_steps >= STALLED_STEPS {
            status = format!(
                "diverged: every rollout of optimiser steps {}-{} diverged, so the network \
                 stopped learning (a smaller --residual-scale bounds its corrections)",
                trainer.step + 1 - STALLED_STEPS,
                trainer.step
            );
            break;
        }
        if args.snapshot_every > 0 && trainer.step % args.snapshot_every == 0 {
            let dir = args
                .run
                .join("snapshots")
                .join(format!("step_{:05}", trainer.step));
            std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
            trainer.with_averaged(|net| net.save(&dir.join("residual.safetensors")))??;
        }
        if let (Some(held), Some(sel)) = (&held, &mut selection)
            && trainer.step % sel.every == 0
            && let Some(line) = sel.record(held, &trainer, &args.run, init_from.is_none())?
            && !args.quiet
        {
            say(args, line);
        }
        if trainer.step % args.checkpoint_every.max(1) == 0 {
            // Without a terminal the bar is hidden: a log still shows how training goes.
            if plain_progress
                .as_mut()
                .is_some_and(crate::common::PlainProgress::due)
            {
                say(
                    args,
                    format!(
                        "step {}/{}: {} ({:.0} s)",
                        trainer.step,
                        args.iterations,
                        loss_summary(&loss, &base_loss, unit),
                        prior_wall + t_train.elapsed().as_secs_f64()
                    ),
                );
            }
            save(
                &trainer,
                &loss,
                &base_loss,
                &gnorm,
                &lrs,
                "running",
                diverged_rollouts,
                &selection,
            )?;
        }
        if args
            .max_minutes
            .is_some_and(|m| t_train.elapsed().as_secs_f64() > 60.0 * m)
        {
            status = format!("stopped by --max-minutes at step {}", trainer.step);
            break;
        }
    }
    bar.finish_and_clear();
    if let (Some(held), Some(sel)) = (&held, &mut selection)
        && let Some(line) = sel.record(held, &trainer, &args.run, init_from.is_none())?
        && !args.quiet
    {
        say(args, line);
    }
    save(
        &trainer,
        &loss,
        &base_loss,
        &gnorm,
        &lrs,
        &status,
        diverged_rollouts,
        &selection,
    )?;
    let first = loss
        .iter()
        .take(20)
        .filter(|l| l.is_finite())
        .copied()
        .collect::<Vec<_>>();
    let last = loss
        .iter()
        .rev()
        .take(20)
        .filter(|l| l.is_finite())
        .copied()
        .collect::<Vec<_>>();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let k = loss.len().min(200);
    // With the yardstick off there is no backbone loss to compare with (not a NaN ratio).
    let yardstick = if train_cfg.yardstick_every > 0 {
        format!(
            ", {:.3} -> {:.3} x the backbone's on the same segments (first/last {k} steps, scored every {})",
            loss_ratio(&loss, &base_loss, 0..k),
            loss_ratio(&loss, &base_loss, loss.len() - k..loss.len()),
            train_cfg.yardstick_every,
        )
    } else {
        String::new()
    };
    say(
        args,
        format!(
            "pgrd ({}) on {}: {} steps, {} loss {:.4} -> {:.4} {unit} (mean of first/last 20){yardstick}, {} diverged rollouts, {:.1} s -> {} (curves: train.svg)",
            trainer.net.config().variant(),
            data.meta.object,
            trainer.step,
            train_cfg.loss.name(),
            mean(&first),
            mean(&last),
            diverged_rollouts,
            prior_wall + t_train.elapsed().as_secs_f64(),
            report_path.display()
        ),
    );
    if trainer.guided_fallbacks() > 0 {
        say(
            args,
            format!(
                "note: the guided trajectory of {} of {} training episodes diverged (the backbone \
                 nudged toward the recorded frames by up to {} m/s a step); their guided segments \
                 start from the backbone's own trajectory",
                trainer.guided_fallbacks(),
                set.len(),
                trainer.net.config().residual_scale
            ),
        );
    }
    if let Some(sel) = selection
        .as_ref()
        .filter(|s| s.best_step == 0 && init_from.is_none())
    {
        say(
            args,
            format!(
                "kept the backbone: no network of {} steps beat it clearly on {} {held_what} (backbone {:.3} cm); residual.safetensors adds no residual",
                trainer.step,
                sel.episodes.len(),
                sel.backbone_mde_cm
            ),
        );
    } else if let Some(sel) = &selection {
        say(
            args,
            format!(
                "selected the network of step {} of {}: rollout MDE {:.3} cm on {} {held_what} (backbone {:.3} cm)",
                sel.best_step,
                trainer.step,
                sel.best_mde_cm(),
                sel.episodes.len(),
                sel.backbone_mde_cm
            ),
        );
    }
    anyhow::ensure!(
        !status.starts_with("diverged"),
        "training {status} (the run's train.json records it; residual.safetensors holds the last finite parameters)"
    );
    Ok(())
}

/// The mean training loss of the last 20 optimiser steps and its ratio to the backbone's
/// over the last 100, as the progress bar shows them.
fn loss_summary(loss: &[f64], base_loss: &[f64], unit: &str) -> String {
    let n = loss.len().min(20);
    let recent = loss[loss.len() - n..]
        .iter()
        .filter(|l| l.is_finite())
        .sum::<f64>()
        / n.max(1) as f64;
    let ratio = loss_ratio(loss, base_loss, loss.len().saturating_sub(100)..loss.len());
    format!("loss {recent:.4} {unit}, {ratio:.3} x backbone (last 100)")
}

/// Prints a result line on stdout, without tearing the progress bars of candidates training at
/// once; those lines carry the candidate's recipe, since another candidate's lines come between.
fn say(args: &TrainArgs, line: String) {
    let line = match &args.progress {
        Some((_, label)) => format!("[{}] {line}", label.trim()),
        None => line,
    };
    above_bars(bars(args), || println!("{line}"));
}

/// The display shared by candidates training at once, if this run is one of them.
fn bars(args: &TrainArgs) -> Option<&indicatif::MultiProgress> {
    args.progress.as_ref().map(|(multi, _)| multi)
}

/// Runs `print` with the shared progress bars (if any) cleared, so its line is not torn; it
/// runs also when the bars are hidden (stderr not a terminal), unlike `MultiProgress::println`.
pub(crate) fn above_bars(bars: Option<&indicatif::MultiProgress>, print: impl FnOnce()) {
    match bars {
        Some(multi) => multi.suspend(print),
        None => print(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `train`'s arguments parsed from `argv` (its first entry the command's name).
    fn parse_train(argv: &[&str]) -> TrainArgs {
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            train: TrainArgs,
        }
        <Cli as clap::Parser>::try_parse_from(argv).unwrap().train
    }

    #[test]
    fn a_run_resumed_after_an_interruption_makes_the_checks_of_one_that_ran_through() {
        let dir = std::env::temp_dir().join(format!("pgrd-resume-sel-{}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        let fit = crate::cmd_fit::FitArgs::quick_rope_fixture(dir.join("through"));
        crate::cmd_fit::run(&fit).unwrap();
        std::fs::create_dir_all(dir.join("resumed")).unwrap();
        std::fs::copy(
            dir.join("through/backbone.json"),
            dir.join("resumed/backbone.json"),
        )
        .unwrap();
        let train = |run_dir: &Path, iterations: &str| {
            let argv = [
                "train",
                "--data",
                crate::cmd_fit::FIXTURE_ROPE,
                "--run",
                run_dir.to_str().unwrap(),
                "--iterations",
                iterations,
                "--holdout",
                "1",
                "--select-every",
                "2",
                "--checkpoint-every",
                "1",
                // A flat schedule, so that a 3-step and a 4-step run take the same first steps.
                "--lr-min",
                "0.001",
                "--quiet",
            ];
            run(&parse_train(&argv)).unwrap();
            let text = std::fs::read_to_string(run_dir.join("train.json")).unwrap();
            serde_json::from_str::<serde_json::Value>(&text).unwrap()
        };
        let through = train(&dir.join("through"), "4");
        assert_eq!(through["selection"]["steps"], serde_json::json!([0, 2, 4]));
        // Three steps, then the state a kill right after step 3's checkpoint leaves: the
        // checkpoint at 3, the selection's checks up to step 2 (the end-of-run check at 3 that
        // a finished run makes is taken out again).
        let resumed_dir = dir.join("resumed");
        let mut report = train(&resumed_dir, "3");
        for key in ["steps", "mde_cm"] {
            report["selection"][key].as_array_mut().unwrap().pop();
        }
        std::fs::write(resumed_dir.join("train.json"), report.to_string()).unwrap();
        let resumed = train(&resumed_dir, "4");
        assert_eq!(resumed["selection"]["steps"], through["selection"]["steps"]);
        assert_eq!(
            resumed["selection"]["mde_cm"],
            through["selection"]["mde_cm"]
        );
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn a_training_whose_rollouts_all_diverge_stops_and_says_so() {
        // A bound of 100 km/s per step lets the network's corrections throw particles beyond
        // the divergence limit from its second step on (measured on this fixture): such steps
        // have no gradient, so the run must stop and say why, not report `done` or a NaN loss.
        let dir = std::env::temp_dir().join(format!("pgrd-diverge-{}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        let fit = crate::cmd_fit::FitArgs::quick_rope_fixture(dir.clone());
        crate::cmd_fit::run(&fit).unwrap();
        let argv = [
            "train",
            "--data",
            crate::cmd_fit::FIXTURE_ROPE,
            "--run",
            dir.to_str().unwrap(),
            "--iterations",
            "200",
            "--residual-scale",
            "1e5",
            "--quiet",
        ];
        let err = run(&parse_train(&argv)).unwrap_err().to_string();
        assert!(err.contains("diverged"), "{err}");
        let text = std::fs::read_to_string(dir.join("train.json")).unwrap();
        assert!(!text.contains("NaN"), "train.json holds a NaN");
        let report: serde_json::Value = serde_json::from_str(&text).unwrap();
        let status = report["status"].as_str().unwrap();
        assert!(status.starts_with("diverged"), "{status}");
        let steps = report["steps_done"].as_u64().unwrap() as usize;
        assert!(steps < 200, "ran on for {steps} steps");
        assert!(report["diverged_rollouts"].as_u64().unwrap() as usize >= STALLED_STEPS);
        // The losses of steps without a finite rollout are recorded as null, not as numbers.
        let losses = report["loss_cm2"].as_array().unwrap();
        assert!(losses.iter().rev().take(STALLED_STEPS).all(|l| l.is_null()));
        // Evaluating that network names the divergence too, and writes no scores.
        let eval = crate::cmd_eval::EvalArgs {
            data: crate::cmd_fit::FIXTURE_ROPE.into(),
            run: dir.clone(),
            split: Split::Val,
            protocol: ProtocolArg::Paper,
            json: None,
            plot: None,
            no_emd: true,
            visual: false,
            horizon: None,
            autograd: false,
            save_predictions: None,
        };
        let Err(err) = crate::cmd_eval::run(&eval) else {
            panic!("a network whose every rollout diverges was scored");
        };
        let err = err.to_string();
        assert!(err.contains("diverged"), "{err}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn select_on_val_chooses_on_a_development_copys_val_and_nowhere_else() {
        let dir = std::env::temp_dir().join(format!("pgrd-select-on-val-{}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        let fit = crate::cmd_fit::FitArgs::quick_rope_fixture(dir.join("run"));
        crate::cmd_fit::run(&fit).unwrap();
        let fixture = Dataset::open(Path::new(crate::cmd_fit::FIXTURE_ROPE)).unwrap();
        // The fixture's val episodes are 3 and 4: the last one chooses, the other is test.
        dataset::select_split(&fixture, &dir.join("sel"), 1).unwrap();
        let run_dir = dir.join("run");
        let train = |data: &Path, extra: &[&str]| {
            let mut argv = vec![
                "train",
                "--data",
                data.to_str().unwrap(),
                "--run",
                run_dir.to_str().unwrap(),
                "--iterations",
                "2",
                "--select-every",
                "1",
                "--restart",
                "--quiet",
            ];
            argv.extend_from_slice(extra);
            let args = parse_train(&argv);
            run(&args)
        };
        train(&dir.join("sel"), &["--select-on-val"]).unwrap();
        let text = std::fs::read_to_string(dir.join("run/train.json")).unwrap();
        let report: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(report["selection"]["split"], "val");
        assert_eq!(report["selection"]["episodes"], serde_json::json!([4]));
        // All three training episodes were trained on: none held out.
        assert_eq!(report["episodes"], 3, "{}", report["episodes"]);
        // The picture beside it draws the same selection: its kept step and the backbone.
        let svg = std::fs::read_to_string(run_dir.join("train.svg")).unwrap();
        let kept = report["selection"]["best_step"].as_u64().unwrap();
        assert!(svg.contains(&format!("kept: step {kept},")), "{svg}");
        let backbone = report["selection"]["backbone_mde_cm"].as_f64().unwrap();
        assert!(svg.contains(&format!("backbone alone, {backbone:.3} cm")));
        // The fixture itself has no test split: its val is what a user reports, so no choice.
        let err = train(fixture.root.as_path(), &["--select-on-val"])
            .unwrap_err()
            .to_string();
        assert!(err.contains("dev-split"), "{err}");
        let err = train(&dir.join("sel"), &["--select-on-val", "--holdout", "1"])
            .unwrap_err()
            .to_string();
        assert!(err.contains("give one"), "{err}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn an_ensembles_run_is_not_trained_over() {
        let dir = std::env::temp_dir().join(format!("pgrd-train-ens-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join(crate::cmd_ensemble::RECORD), "{}").unwrap();
        let run_dir = dir.to_str().unwrap();
        let argv = ["train", "--data", "no-such-data", "--run", run_dir];
        let args = parse_train(&argv);
        let err = run(&args).unwrap_err().to_string();
        assert!(err.contains("holds an ensemble"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn size_flags_reach_the_network_and_bad_sizes_are_refused_before_any_data() {
        let parse = |extra: &[&str]| {
            let mut argv = vec!["train", "--data", "no-such-data", "--run", "no-such-run"];
            argv.extend_from_slice(extra);
            parse_train(&argv)
        };
        assert_eq!(model_config(&parse(&[])), ModelConfig::default());
        let wide = model_config(&parse(&[
            "--enc-channels",
            "32,64,128",
            "--dec-channels",
            "64,64",
        ]));
        assert_eq!(wide.enc_channels, [32, 64, 128]);
        assert_eq!(wide.enc_depths, [1, 1, 1]);
        assert_eq!(wide.dec_channels, [64, 64]);
        assert_eq!(wide.feature_dim(), 64);
        wide.validate().unwrap();
        let deep = model_config(&parse(&["--enc-depths", "2,2,2", "--dec-depths", "2,2"]));
        assert_eq!(deep.enc_channels, ModelConfig::default().enc_channels);
        assert_eq!((deep.enc_depths, deep.dec_depths), (vec![2; 3], vec![2; 2]));
        // A fourth stage without its decoder stage, and a width the heads do not divide: both
        // refused by name before the (missing) dataset is opened.
        for bad in [
            &["--enc-channels", "16,32,64,128"][..],
            &["--enc-channels", "16,32,60"][..],
        ] {
            let err = format!("{:#}", run(&parse(bad)).unwrap_err());
            assert!(err.contains("configuration from the flags"), "{err}");
            assert!(err.contains("channel"), "{err}");
            assert!(!err.contains("no-such-data"), "{err}");
        }
        let err = format!("{:#}", run(&parse(&["--iterations", "0"])).unwrap_err());
        assert!(err.contains("--iterations must be at least 1"), "{err}");
    }

    #[test]
    fn init_from_loads_the_same_weights_and_refuses_another_configuration() {
        let dir = std::env::temp_dir().join(format!("pgrd-init-from-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let cfg = ModelConfig::tiny();
        let path = dir.join("residual.safetensors");
        let net = ResidualNet::new(&cfg, 7).unwrap();
        net.save(&path).unwrap();

        let loaded = initial_network(&path, &cfg).unwrap();
        let same = |a: &ResidualNet, b: &ResidualNet| {
            a.named_vars()
                .iter()
                .zip(b.named_vars())
                .all(|((na, va), (nb, vb))| {
                    na == &nb
                        && va
                            .as_tensor()
                            .flatten_all()
                            .unwrap()
                            .to_vec1::<f32>()
                            .unwrap()
                            == vb
                                .as_tensor()
                                .flatten_all()
                                .unwrap()
                                .to_vec1::<f32>()
                                .unwrap()
                })
        };
        assert!(same(&net, &loaded));
        // A fresh network of another seed differs, so the comparison can fail.
        assert!(!same(&net, &ResidualNet::new(&cfg, 8).unwrap()));

        let wider = ModelConfig {
            residual_scale: 1.0,
            ..cfg.clone()
        };
        let err = initial_network(&path, &wider).unwrap_err().to_string();
        assert!(err.contains("residual_scale"), "{err}");
        let missing = initial_network(&dir.join("none.safetensors"), &cfg).unwrap_err();
        assert!(format!("{missing:#}").contains("none"), "{missing:#}");
        std::fs::remove_dir_all(&dir).ok();
    }

    /// Held-out selection starts at the backbone itself: the network it writes at step 0
    /// scores exactly the backbone's held-out errors; a run fine-tuned from a network starts
    /// at that network, which does not.
    #[test]
    fn selection_starts_at_the_backbone_itself() {
        let dir = std::env::temp_dir().join(format!("pgrd-selection-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/rope");
        let data = Dataset::open(&root).unwrap();
        let mut set = TrainSet::new(
            &data,
            Split::Train,
            &springs::SpringParams::reference_rope(),
            &Default::default(),
        )
        .unwrap();
        let held = set.hold_out(1).unwrap();
        let backbone = held.rollout_mde_cm(None).unwrap();
        let net = ResidualNet::new(&ModelConfig::tiny(), 3).unwrap();
        let trainer = Trainer::new(net, TrainConfig::default()).unwrap();
        let path = dir.join("residual.safetensors");
        for first_is_backbone in [true, false] {
            let mut sel = Selection {
                episodes: held.episode_indices(),
                split: train_split(),
                every: 10,
                backbone_mde_cm: 0.0,
                steps: Vec::new(),
                mde_cm: Vec::new(),
                best_step: 0,
                best_episode_mde_cm: Vec::new(),
            };
            sel.record(&held, &trainer, &dir, first_is_backbone)
                .unwrap();
            let written = ResidualNet::load(&path).unwrap();
            let scored = held.rollout_mde_cm(Some(&written)).unwrap();
            assert_eq!(scored, sel.best_episode_mde_cm);
            assert_eq!(
                scored == backbone,
                first_is_backbone,
                "{scored:?} vs {backbone:?}"
            );
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}
