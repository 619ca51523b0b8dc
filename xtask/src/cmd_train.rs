//! `cargo xtask train`: train PGRD's residual network on top of the run's fitted backbone.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use dataset::{Dataset, Split};
use indicatif::{ProgressBar, ProgressStyle};
use residual::{
    Combine, EncoderKind, ModelConfig, ResidualError, ResidualKind, ResidualNet, StartFrom,
    TrainConfig, TrainSet, Trainer,
};
use scene::SceneConfig;
use serde::Serialize;

use crate::common::{ProtocolArg, read_backbone};
use crate::report::write_json;

/// `--encoder`.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum EncoderArg {
    /// Serialized point transformer (PTv3-style), the paper's.
    Ptv3,
    /// PointNet++-style set abstraction (ablation).
    Pointnet,
}

/// `--start-from`.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum StartArg {
    /// The model's own rollout states (what evaluation meets).
    Rollout,
    /// The recorded frames (the reference code's sampling).
    Recorded,
    /// Half from a guided backbone rollout near the truth, half from the model's own.
    Guided,
}

/// Arguments of `train`.
#[derive(clap::Args)]
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
    /// Rollouts per optimiser step.
    #[arg(long, default_value_t = 2)]
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
    /// Gradient-norm clip (loss in cm²).
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
    /// Ignore an existing checkpoint and start over.
    #[arg(long)]
    pub restart: bool,
    /// Stop (after saving) once this many minutes of training have passed in this session.
    #[arg(long)]
    pub max_minutes: Option<f64>,
    /// Ablation: encoder family.
    #[arg(long, value_enum, default_value_t = EncoderArg::Ptv3)]
    pub encoder: EncoderArg,
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
    /// Where training segments start: `guided` (half from a backbone rollout pulled toward
    /// the recorded frames, half as `rollout`), `rollout` (the model's own states along the
    /// evaluation window, refreshed with the hybrid model every --refresh-every steps) or
    /// `recorded` (tracked frames, as the reference code). See docs/residual.md.
    #[arg(long, value_enum, default_value_t = StartArg::Guided)]
    pub start_from: StartArg,
    /// Re-run the hybrid model over the training episodes every this many steps (0: never).
    #[arg(long, default_value_t = 0)]
    pub refresh_every: usize,
    /// Evaluation protocol whose window training segments are drawn from (use the one you
    /// evaluate with).
    #[arg(long, value_enum, default_value_t = ProtocolArg::Paper)]
    pub protocol: ProtocolArg,
    /// Residual bound, m/s per axis (0.1 in the paper).
    #[arg(long, default_value_t = 0.1)]
    pub residual_scale: f32,
    /// Print only the final line.
    #[arg(long)]
    pub quiet: bool,
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
    loss_cm2: Vec<f64>,
    grad_norm: Vec<f64>,
    lr: Vec<f64>,
    diverged_rollouts: usize,
    wall_s: f64,
    session_wall_s: f64,
    threads: usize,
    model_config: ModelConfig,
    train_config: TrainConfig,
}

fn model_config(args: &TrainArgs) -> ModelConfig {
    ModelConfig {
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
        residual_scale: args.residual_scale,
        ..ModelConfig::default()
    }
}

fn read_previous(path: &Path) -> Option<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

fn floats(v: &serde_json::Value, key: &str) -> Vec<f64> {
    v[key]
        .as_array()
        .map(|a| a.iter().map(|x| x.as_f64().unwrap_or(f64::NAN)).collect())
        .unwrap_or_default()
}

/// Trains the residual network and writes the run's files.
pub fn run(args: &TrainArgs) -> anyhow::Result<()> {
    let t0 = Instant::now();
    // candle's matmul reads the thread count from RAYON_NUM_THREADS and runs on rayon's global
    // pool; building that pool with `threads` workers bounds both.
    rayon::ThreadPoolBuilder::new()
        .num_threads(args.threads.max(1))
        .build_global()
        .ok();
    let data = Dataset::open(&args.data)?;
    let backbone = read_backbone(&args.run)?;
    let set = TrainSet::with_protocol(
        &data,
        Split::Train,
        &backbone.params,
        &SceneConfig::default(),
        args.protocol.into(),
    )
    .with_context(|| format!("loading training episodes of {}", args.data.display()))?;
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
        start_from: match args.start_from {
            StartArg::Rollout => StartFrom::Rollout,
            StartArg::Recorded => StartFrom::Recorded,
            StartArg::Guided => StartFrom::Guided,
        },
        refresh_every: args.refresh_every,
        seed: args.seed,
    };
    let net = ResidualNet::new(&model_cfg, args.seed)?;
    let parameters = net.parameter_count();
    let mut trainer = Trainer::new(net, train_cfg.clone())?;
    let ckpt = args.run.join("train_ckpt.safetensors");
    let report_path = args.run.join("train.json");
    let (mut loss, mut gnorm, mut lrs, mut prior_wall) = (Vec::new(), Vec::new(), Vec::new(), 0.0);
    if ckpt.exists() && !args.restart {
        trainer
            .load_checkpoint(&ckpt)
            .with_context(|| format!("resuming from {}", ckpt.display()))?;
        if let Some(prev) = read_previous(&report_path) {
            let keep = trainer.step;
            loss = floats(&prev, "loss_cm2");
            gnorm = floats(&prev, "grad_norm");
            lrs = floats(&prev, "lr");
            loss.truncate(keep);
            gnorm.truncate(keep);
            lrs.truncate(keep);
            prior_wall = prev["wall_s"].as_f64().unwrap_or(0.0);
        }
        if !args.quiet {
            eprintln!("resuming at step {} from {}", trainer.step, ckpt.display());
        }
    }
    let bar = if args.quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(args.iterations as u64)
    };
    bar.set_style(ProgressStyle::with_template(
        "{bar:30} {pos}/{len} {msg} [{elapsed} < {eta}]",
    )?);
    bar.set_position(trainer.step as u64);
    let t_train = Instant::now();
    let mut diverged_rollouts = 0;
    let mut status = "done".to_string();
    let save = |trainer: &Trainer,
                loss: &[f64],
                gnorm: &[f64],
                lrs: &[f64],
                status: &str,
                diverged: usize|
     -> anyhow::Result<()> {
        trainer.save_checkpoint(&ckpt)?;
        trainer.net.save(&args.run.join("residual.safetensors"))?;
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
                grad_norm: gnorm.to_vec(),
                lr: lrs.to_vec(),
                diverged_rollouts: diverged,
                wall_s: prior_wall + t_train.elapsed().as_secs_f64(),
                session_wall_s: session,
                threads: args.threads,
                model_config: trainer.net.config().clone(),
                train_config: trainer.cfg.clone(),
            },
        )
    };
    while trainer.step < args.iterations {
        match trainer.train_step(&set) {
            Ok(s) => {
                diverged_rollouts += s.diverged;
                loss.push(s.loss);
                gnorm.push(s.grad_norm);
                lrs.push(s.lr);
                let n = loss.len().min(20);
                let recent = loss[loss.len() - n..]
                    .iter()
                    .filter(|l| l.is_finite())
                    .sum::<f64>()
                    / n as f64;
                bar.set_message(format!("loss {recent:.4} cm²"));
                bar.set_position(trainer.step as u64);
            }
            Err(ResidualError::Diverged { step, what }) => {
                status = format!("diverged at optimiser step {step}: {what}");
                break;
            }
            Err(e) => return Err(e.into()),
        }
        if trainer.step % args.checkpoint_every.max(1) == 0 {
            save(&trainer, &loss, &gnorm, &lrs, "running", diverged_rollouts)?;
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
    save(&trainer, &loss, &gnorm, &lrs, &status, diverged_rollouts)?;
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
    println!(
        "pgrd ({}) on {}: {} steps, loss {:.4} -> {:.4} cm² (mean of first/last 20), {} diverged rollouts, {:.1} s -> {}",
        trainer.net.config().variant(),
        data.meta.object,
        trainer.step,
        mean(&first),
        mean(&last),
        diverged_rollouts,
        prior_wall + t_train.elapsed().as_secs_f64(),
        report_path.display()
    );
    anyhow::ensure!(
        !status.starts_with("diverged"),
        "training {status} (the run's train.json records it; residual.safetensors holds the last finite parameters)"
    );
    Ok(())
}
