//! `cargo xtask eval`: roll the run's model out on a split and report the paper's metrics.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use dataset::{Dataset, Split};
use metrics::{ChamferConvention, RolloutAggregate};
use rayon::prelude::*;
use scene::{Protocol, StepErrors};
use serde::{Deserialize, Serialize};

use crate::common::{
    NetworkPath, ProtocolArg, load_scenes, predict_tracked, read_backbone, read_residual,
    warn_if_unconnected,
};
use crate::plots::{Curve, plot_curves};
use crate::report::write_json;

/// Arguments of `eval`.
#[derive(clap::Args)]
pub struct EvalArgs {
    /// Dataset directory.
    #[arg(long)]
    pub data: PathBuf,
    /// Run directory holding backbone.json.
    #[arg(long)]
    pub run: PathBuf,
    /// Split to evaluate.
    #[arg(long, default_value = "val")]
    pub split: Split,
    /// Evaluation protocol.
    #[arg(long, value_enum, default_value_t = ProtocolArg::Paper)]
    pub protocol: ProtocolArg,
    /// Write the report as JSON here (default: <run>/eval_<split>.json for the spring-mass
    /// backbone, <run>/eval_pgrd_<split>.json for PGRD, so evaluating both keeps both).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write the error-per-step plot here (default: beside the JSON, .svg).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Skip exact EMD (faster on large clouds).
    #[arg(long)]
    pub no_emd: bool,
    /// Also score action-conditioned video prediction (J, F, LPIPS; `cargo xtask render`)
    /// against the dataset's ground-truth Gaussians (reference-world data only).
    #[arg(long)]
    pub visual: bool,
    /// Score K-step predictions started from every recorded frame of each episode's window
    /// (state and history read from the recording), the way a planner uses the model,
    /// instead of one rollout over the window; the per-step curve is over the K steps and
    /// each episode's score the mean over its starts. Written to `eval_h<K>_<split>.json`
    /// (`eval_pgrd_h<K>_<split>.json`) by default.
    #[arg(long, value_name = "K")]
    pub horizon: Option<usize>,
    /// Evaluate the residual network through the autograd operations training runs instead of
    /// the forward-only kernels (two to four times slower; the same up to float rounding):
    /// reproduces to the digit the numbers documented before session 82, which were made so.
    #[arg(long)]
    pub autograd: bool,
    /// Also write each episode's predicted trajectory beside the recorded one into this
    /// directory: `ep_<episode>.safetensors` (predicted, recorded and start positions, the
    /// tracker's visibility and the grippers' path, m) and `predictions.json`, which lists the
    /// episodes and says what each tensor holds (docs/pipelines.md, "Saved predictions").
    #[arg(long, value_name = "DIR")]
    pub save_predictions: Option<PathBuf>,
}

/// A metric's summary in cm.
#[derive(Serialize)]
pub struct Summary {
    /// Mean over steps of the per-step mean over episodes.
    pub mean: f64,
    /// Mean over steps of the per-step standard deviation over episodes (the tables' ±).
    pub std: f64,
    /// What exactly was measured.
    pub convention: &'static str,
}

/// One episode's errors, cm, each the mean over the rollout's steps (so the mean of these over
/// episodes is the report's summary when every episode has the same steps). `cargo xtask
/// compare` pairs two reports' episodes by these.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeScore {
    /// Index of the episode in the dataset.
    pub episode: usize,
    /// Mean Euclidean distance of same-index points.
    pub mde_cm: f64,
    /// Two-sided Chamfer (sum of both directions' means).
    pub chamfer_cm: f64,
    /// Exact EMD; absent with `--no-emd`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub emd_cm: Option<f64>,
}

/// The report `eval` writes.
#[derive(Debug, Serialize)]
pub struct EvalReport {
    /// Model name ("spring-mass", "spring-mass+<effect>..." for a backbone with effects, or
    /// "pgrd" when `<run>/residual.safetensors` exists).
    pub model: String,
    /// Ablation variant of the residual network ("full" for the paper's); absent for the backbone.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub variant: Option<String>,
    /// The backbone (with its effects, if any): `spring-mass` or `spring-mass+drag+...`.
    pub backbone: String,
    /// Dataset directory.
    pub dataset: String,
    /// Object name from the dataset.
    pub object: String,
    /// Split evaluated.
    pub split: String,
    /// Protocol.
    pub protocol: String,
    /// Episodes evaluated.
    pub episodes: usize,
    /// Steps per rollout (with `--horizon`, K).
    pub steps: usize,
    /// With `--horizon K`: K. Each episode's score is then the mean over its K-step
    /// predictions started from every frame of the window that leaves K frames after it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub horizon: Option<usize>,
    /// Summaries (cm; `deform_l1_m` in m).
    pub metrics: serde_json::Value,
    /// Per-step means over episodes, cm.
    pub per_step_cm: serde_json::Value,
    /// Per episode, in dataset order (diverged episodes are left out).
    pub per_episode: Vec<EpisodeScore>,
    /// Rollouts that diverged (scored as missing; the command fails if any does).
    pub diverged: usize,
    /// How the residual network was evaluated (`forward-only`, or `autograd` with
    /// `--autograd`); absent for the backbone.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub network_path: Option<&'static str>,
    /// Wall time of the rollouts, s.
    pub rollout_wall_s: f64,
    /// Wall time of the whole command, s.
    pub wall_s: f64,
}

/// The paper's aggregate of per-episode curves, cm; a step an episode has no score at (the
/// tracker saw nothing there) is left to the other episodes, and a step none has is NaN
/// (`null` in the JSON).
fn summary(
    curves: &[Vec<Option<f64>>],
    convention: &'static str,
) -> anyhow::Result<(Summary, Vec<f64>)> {
    let agg = RolloutAggregate::from_per_episode_curves_with_gaps(curves)?.scaled(100.0);
    Ok((
        Summary {
            mean: agg.mean,
            std: agg.std,
            convention,
        },
        agg.per_step_mean,
    ))
}

/// File name (without extension) of an evaluation's default outputs: the backbone's keep the
/// historical `eval_<split>`, PGRD's get the model name so one run directory holds both.
fn stem(model_name: &str, split: Split, horizon: Option<usize>) -> String {
    let h = horizon.map(|k| format!("h{k}_")).unwrap_or_default();
    if model_name == "pgrd" {
        format!("eval_pgrd_{h}{split}")
    } else {
        format!("eval_{h}{split}")
    }
}

/// Evaluates the run's model and writes the JSON report and the plot.
pub fn run(args: &EvalArgs) -> anyhow::Result<EvalReport> {
    let t0 = Instant::now();
    anyhow::ensure!(
        !(args.visual && args.horizon.is_some()),
        "--visual scores the video of one rollout over the window; --horizon scores many short \
         predictions, which make no video"
    );
    anyhow::ensure!(
        !(args.save_predictions.is_some() && args.horizon.is_some()),
        "--save-predictions writes one rollout over each episode's window; --horizon makes many \
         short predictions per episode, which it does not save"
    );
    let data = Dataset::open(&args.data)?;
    let backbone = read_backbone(&args.run)?;
    backbone.note_other_object(&data);
    let protocol: Protocol = args.protocol.into();
    let scene_config = backbone.setting().scene_config(&data)?;
    let scenes = load_scenes(&data, args.split, protocol, &scene_config)?;
    if let Some(k) = args.horizon {
        let shortest = scenes
            .iter()
            .map(|(_, s)| s.window.steps)
            .min()
            .unwrap_or(0);
        anyhow::ensure!(
            (1..=shortest).contains(&k),
            "--horizon {k}: must be between 1 and the shortest window's {shortest} steps"
        );
    }
    // Many short predictions per episode: exact EMD on each would cost more than the rest.
    let with_emd = !args.no_emd && args.horizon.is_none();
    let net = read_residual(&args.run)?;
    let model_name = if net.is_some() {
        "pgrd".to_string()
    } else {
        backbone.label()
    };
    let options = backbone.options_for(&data, protocol)?;
    if let Some((_, scene)) = scenes.first() {
        warn_if_unconnected(scene, &backbone.params, options())?;
    }
    // With --horizon every start reads its own history (eval_horizon).
    let histories = match &net {
        Some(_) if args.horizon.is_none() => scenes
            .iter()
            .map(|(i, scene)| {
                Ok(Some(residual::History::from_episode(
                    scene,
                    &data.load_episode(*i)?,
                    data.meta.fps,
                )?))
            })
            .collect::<anyhow::Result<Vec<_>>>()?,
        _ => vec![None; scenes.len()],
    };
    let path = if args.autograd {
        NetworkPath::Autograd
    } else {
        NetworkPath::ForwardOnly
    };
    let t_roll = Instant::now();
    let results: Vec<anyhow::Result<Scored<'_>>> = scenes
        .par_iter()
        .zip(&histories)
        .map(|((i, scene), history)| {
            if let Some(k) = args.horizon {
                let predictor = crate::eval_horizon::Predictor {
                    params: &backbone.params,
                    options: &options,
                    net: net.as_ref(),
                    path,
                };
                let (errors, l1) = crate::eval_horizon::horizon_errors(
                    &data,
                    &data.load_episode(*i)?,
                    scene,
                    &scene_config,
                    k,
                    &predictor,
                )
                .with_context(|| format!("episode {i}"))?;
                return Ok((errors, l1, (*i, scene, Vec::new())));
            }
            let pred = predict_tracked(
                scene,
                &backbone.params,
                &options,
                net.as_ref(),
                history.as_ref(),
                path,
            )
            .with_context(|| format!("episode {i}"))?;
            let errors = scene::score_steps(scene, &pred, with_emd)?;
            let l1 = scene::deform_l1(scene, &pred)?;
            // The predictions are kept only for the video metrics and for saving.
            let kept = if args.visual || args.save_predictions.is_some() {
                pred
            } else {
                Vec::new()
            };
            Ok((errors, l1, (*i, scene, kept)))
        })
        .collect();
    let rollout_wall_s = t_roll.elapsed().as_secs_f64();
    let mut per_episode = Vec::new();
    let mut diverged = 0;
    // Episodes left out of the scores, for the saved predictions' index.
    let (mut diverged_episodes, mut unseen_episodes) = (Vec::new(), Vec::new());
    for (r, (i, _)) in results.into_iter().zip(&scenes) {
        match r {
            Ok(v) if v.0.iter().all(Option::is_none) => {
                unseen_episodes.push(*i);
                eprintln!(
                    "warning: episode {i}: the tracker saw no tracked point in any predicted \
                     frame; not scored"
                )
            }
            Ok(v) => per_episode.push(v),
            Err(e) => {
                diverged += 1;
                diverged_episodes.push(*i);
                eprintln!("warning: {e:#}");
            }
        }
    }
    let json = args.json.clone().unwrap_or_else(|| {
        args.run.join(format!(
            "{}.json",
            stem(&model_name, args.split, args.horizon)
        ))
    });
    let plot = args.plot.clone().unwrap_or_else(|| {
        args.run.join(format!(
            "{}.svg",
            stem(&model_name, args.split, args.horizon)
        ))
    });
    let spec = ReportSpec {
        model: model_name,
        variant: net.as_ref().map(|n| n.config().variant()),
        backbone: backbone.label(),
        data: &data,
        dataset: args.data.display().to_string(),
        split: args.split,
        protocol,
        horizon: args.horizon,
        with_emd,
        visual: args.visual,
        json,
        plot,
        network_path: net.as_ref().map(|_| path.label()),
        rollout_wall_s,
        started: t0,
    };
    let about = crate::eval_save::About {
        model: &spec.model,
        dataset: &spec.dataset,
        split: spec.split,
        protocol: protocol.name(),
        step_s: data.meta.step_dt(),
        diverged: &diverged_episodes,
        unseen: &unseen_episodes,
    };
    // With nothing scored the report is an error; the index still says which episodes
    // diverged.
    if let (Some(dir), true) = (&args.save_predictions, per_episode.is_empty()) {
        crate::eval_save::write(dir, &about, &[])?;
    }
    let report = write_report(&spec, &per_episode, diverged)?;
    let saved_predictions = match &args.save_predictions {
        Some(dir) => {
            let saved: Vec<crate::eval_save::Saved<'_>> = per_episode
                .iter()
                .zip(&report.per_episode)
                .map(
                    |((_, _, (i, scene, pred)), score)| crate::eval_save::Saved {
                        episode: *i,
                        scene,
                        predicted: pred,
                        mde_cm: score.mde_cm,
                    },
                )
                .collect();
            Some(crate::eval_save::write(dir, &about, &saved)?)
        }
        None => None,
    };
    if let Some(index) = saved_predictions {
        println!(
            "saved the predicted and recorded trajectories of {} episodes -> {}",
            report.episodes,
            index.display()
        );
    }
    anyhow::ensure!(
        diverged == 0,
        "{diverged} rollouts diverged (see warnings above)"
    );
    Ok(report)
}

/// One scored episode: its per-step errors, DEFORM's L1 score, and its index, scene and
/// prediction (the prediction kept only where it is needed after scoring).
pub(crate) type Scored<'a> = (
    Vec<Option<StepErrors>>,
    f64,
    (usize, &'a scene::Scene, Vec<Vec<glam::Vec3>>),
);

/// What a report describes and where it goes (`eval`'s, and `score`'s for predictions made
/// elsewhere).
pub(crate) struct ReportSpec<'a> {
    /// The model's name in the report.
    pub model: String,
    /// The residual network's ablation variant, if any.
    pub variant: Option<String>,
    /// The backbone's label.
    pub backbone: String,
    /// The dataset.
    pub data: &'a Dataset,
    /// Its directory as given on the command line.
    pub dataset: String,
    /// The split scored.
    pub split: Split,
    /// The protocol of the windows.
    pub protocol: Protocol,
    /// `--horizon K`, if the episodes were scored by K-step predictions.
    pub horizon: Option<usize>,
    /// Whether the episodes' errors include exact EMD.
    pub with_emd: bool,
    /// Also score the video metrics (the predictions must be kept).
    pub visual: bool,
    /// Where the JSON report goes.
    pub json: PathBuf,
    /// Where the error-per-step plot goes.
    pub plot: PathBuf,
    /// How a residual network was evaluated, if there is one.
    pub network_path: Option<&'static str>,
    /// Wall time of the rollouts, s.
    pub rollout_wall_s: f64,
    /// When the command started (for the report's wall time).
    pub started: Instant,
}

/// Summarises scored episodes the paper's way, writes the JSON report and the plot, and prints
/// the summary line; an error when nothing could be scored (the JSON then says why).
pub(crate) fn write_report(
    spec: &ReportSpec<'_>,
    per_episode: &[Scored<'_>],
    diverged: usize,
) -> anyhow::Result<EvalReport> {
    let (model_name, data, protocol, with_emd) =
        (spec.model.as_str(), spec.data, spec.protocol, spec.with_emd);
    anyhow::ensure!(
        !per_episode.is_empty() || diverged > 0,
        "{model_name}: the tracker saw no tracked point in any predicted frame of any episode: \
         nothing to score"
    );
    if per_episode.is_empty() {
        let json = spec.json.clone();
        write_json(
            &json,
            &serde_json::json!({
                "model": model_name,
                "variant": spec.variant.clone(),
                "dataset": spec.dataset.to_string(),
                "object": data.meta.object,
                "split": spec.split.to_string(),
                "protocol": protocol.name(),
                "episodes": 0,
                "diverged": diverged,
                "status": "every rollout diverged",
            }),
        )?;
        anyhow::bail!(
            "{model_name}: every one of {diverged} rollouts diverged (no scores; see {})",
            json.display()
        );
    }
    let curve = |f: fn(&StepErrors) -> f64| -> Vec<Vec<Option<f64>>> {
        per_episode
            .iter()
            .map(|(e, _, _)| e.iter().map(|s| s.as_ref().map(f)).collect())
            .collect()
    };
    let (mde, mde_steps) = summary(
        &curve(|e| e.mde),
        "mean Euclidean distance of same-index points",
    )?;
    let (ch, ch_steps) = summary(
        &curve(StepErrors::chamfer_two_sided),
        ChamferConvention::TwoSidedSum.label(),
    )?;
    let (ch1, ch1_steps) = summary(
        &curve(|e| e.chamfer_pred_to_gt),
        ChamferConvention::PredToGt.label(),
    )?;
    let mut metrics = serde_json::json!({
        "mde_cm": mde,
        "chamfer_cm": ch,
        "chamfer_pred_to_gt_cm": ch1,
    });
    let mut per_step = serde_json::json!({
        "mde_cm": mde_steps,
        "chamfer_cm": ch_steps,
        "chamfer_pred_to_gt_cm": ch1_steps,
    });
    let mut curves = vec![
        Curve {
            label: "MDE".into(),
            y: &mde_steps,
        },
        Curve {
            label: "Chamfer (two-sided sum)".into(),
            y: &ch_steps,
        },
    ];
    let emd_steps;
    if with_emd {
        let (emd, steps) = summary(
            &curve(|e| e.emd),
            "exact EMD, mean matched Euclidean distance",
        )?;
        metrics["emd_cm"] = serde_json::to_value(emd)?;
        per_step["emd_cm"] = serde_json::to_value(&steps)?;
        emd_steps = steps;
        curves.push(Curve {
            label: "EMD".into(),
            y: &emd_steps,
        });
    }
    if matches!(protocol, Protocol::Deform) {
        let l1 = per_episode.iter().map(|(_, l, _)| l).sum::<f64>() / per_episode.len() as f64;
        metrics["deform_l1_m"] = serde_json::json!({
            "mean": l1,
            "convention": "DEFORM: mean |coordinate error| over all markers (driven included), summed over steps / frames"
        });
    }
    if spec.visual {
        let predictions: Vec<_> = per_episode.iter().map(|(_, _, p)| p.clone()).collect();
        metrics["visual"] = crate::cmd_render::visual_metrics(
            data,
            &predictions,
            &crate::cmd_render::VideoOptions::default(),
        )?;
    }
    let split = spec.split.to_string();
    let plot = spec.plot.clone();
    plot_curves(
        &plot,
        &format!(
            "{} ({} episodes, {split}): {model_name}",
            data.meta.object,
            per_episode.len()
        ),
        "rollout step",
        "error (cm)",
        1.0,
        &curves,
    )?;
    // Every episode kept here has a scored step.
    let mean_cm = |e: &[Option<StepErrors>], f: fn(&StepErrors) -> f64| {
        let (sum, n) = scene::sum_over_steps(e, f);
        100.0 * sum / n as f64
    };
    let episode_scores = per_episode
        .iter()
        .map(|(e, _, (i, _, _))| EpisodeScore {
            episode: *i,
            mde_cm: mean_cm(e, |s| s.mde),
            chamfer_cm: mean_cm(e, StepErrors::chamfer_two_sided),
            emd_cm: with_emd.then(|| mean_cm(e, |s| s.emd)),
        })
        .collect::<Vec<EpisodeScore>>();
    let report = EvalReport {
        model: model_name.to_string(),
        variant: spec.variant.clone(),
        backbone: spec.backbone.clone(),
        dataset: spec.dataset.to_string(),
        object: data.meta.object.clone(),
        split: split.clone(),
        protocol: protocol.name().into(),
        episodes: per_episode.len(),
        steps: mde_steps.len(),
        horizon: spec.horizon,
        metrics,
        per_step_cm: per_step,
        per_episode: episode_scores,
        diverged,
        network_path: spec.network_path,
        rollout_wall_s: spec.rollout_wall_s,
        wall_s: spec.started.elapsed().as_secs_f64(),
    };
    let json = spec.json.clone();
    write_json(&json, &report)?;
    let m = &report.metrics;
    let emd_text = m
        .get("emd_cm")
        .map(|e| {
            format!(
                ", EMD {:.3} ± {:.3} cm",
                e["mean"].as_f64().unwrap_or(f64::NAN),
                e["std"].as_f64().unwrap_or(f64::NAN)
            )
        })
        .unwrap_or_default();
    let visual_text = m
        .get("visual")
        .map(|v| {
            let x = |k: &str| v[k]["mean"].as_f64().unwrap_or(f64::NAN);
            format!(
                ", J {:.3}, F {:.3}, LPIPS {:.4}",
                x("j"),
                x("f"),
                x("lpips")
            )
        })
        .unwrap_or_default();
    println!(
        "{} {} on {} ({} {split} episodes, {} steps): MDE {:.3} ± {:.3} cm, Chamfer {:.3} ± {:.3} cm [two-sided sum]{emd_text}{}{visual_text}  ({:.1} s) -> {}",
        report.model,
        report.protocol,
        report.object,
        report.episodes,
        report.steps,
        mde.mean,
        mde.std,
        ch.mean,
        ch.std,
        m.get("deform_l1_m")
            .map(|l| format!(
                ", deform_l1 {:.4} m",
                l["mean"].as_f64().unwrap_or(f64::NAN)
            ))
            .unwrap_or_default(),
        report.wall_s,
        json.display(),
    );
    Ok(report)
}
