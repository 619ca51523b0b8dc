//! `cargo xtask plan`: MPPI with a run's model, executed in closed loop in the reference world.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use glam::Vec3;
use plan::render::{Frame, render, view_bounds};
use plan::{DEFAULT_GAINS, OnlinePgrd};
use plan::{
    ForwardModel, LoopSettings, ModelState, Mppi, Pgrd, SpringMass, System, Task, TaskConfig,
    TaskKind, Trajectory, WorldOracle, run_closed_loop,
};
use serde::Serialize;

use crate::common::{BackboneFile, read_backbone, read_residual};
use crate::plots::{Curve, plot_curves};
use crate::report::write_json;

/// `--model`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ModelArg {
    /// The fitted spring-mass backbone alone.
    SpringMass,
    /// Backbone plus the run's residual network.
    Pgrd,
    /// Backbone plus the run's residual network scaled by a gain (0, 0.5 or 1) chosen after
    /// every executed step by how well each gain predicted the steps executed so far
    /// (`plan::OnlinePgrd`; windows of the planning horizon).
    PgrdOnline,
    /// Backbone plus each network of the run's ensemble on its own trajectory: every candidate
    /// is scored by its mean cost over the members plus `--member-risk` times their standard
    /// deviation (PETS-style trajectory sampling), so a path only some members think good is
    /// not chosen; executed steps and path errors use the ensemble as one model.
    PgrdMembers,
    /// The reference world itself, a perfect model: checks whether the planner can solve the
    /// task at all (not a model a user could have).
    World,
}

/// `--resolution` of the world's rope.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum ResolutionArg {
    /// Coarse (the fixtures' resolution).
    Coarse,
    /// Full.
    Full,
}

/// Arguments of `plan`.
#[derive(clap::Args)]
pub struct PlanArgs {
    /// Task: rope-lift, rope-lower, rope-rotate, rope-curve or reroute.
    #[arg(long)]
    pub task: String,
    /// Run directory: backbone.json (fitted parameters) and, for pgrd, residual.safetensors.
    #[arg(long)]
    pub run: PathBuf,
    /// Models to plan with (comma-separated; default: spring-mass, plus pgrd when the run has a
    /// residual network).
    #[arg(long, value_enum, value_delimiter = ',')]
    pub model: Vec<ModelArg>,
    /// Trials per model (rerouting draws a new start and target per trial; the simple tasks
    /// repeat theirs with another planner seed).
    #[arg(long, default_value_t = 10)]
    pub trials: usize,
    /// Write the report here.
    #[arg(long)]
    pub json: PathBuf,
    /// Chamfer-curve plot (default: the JSON path with `.svg`).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// GIF of the first trial (default: the JSON path with `_<model>.gif`, one per model).
    #[arg(long)]
    pub gif: Option<PathBuf>,
    /// Planner seed of trial 0 (trial k uses seed + k).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Index of the first trial: runs trials first-trial … first-trial + trials − 1, each with
    /// its own start and target (rerouting) and seed, so `--first-trial 3 --trials 1` repeats
    /// exactly the fourth trial of a `--trials 10` run and trials can be split across
    /// processes or machines.
    #[arg(long, default_value_t = 0)]
    pub first_trial: usize,
    /// Tracked rope points = model particles (default: the particle count of the run's
    /// dataset, else 150).
    #[arg(long)]
    pub tracked: Option<usize>,
    /// The world rope's resolution.
    #[arg(long, value_enum, default_value_t = ResolutionArg::Coarse)]
    pub resolution: ResolutionArg,
    /// Override the task's step limit (>= 1).
    #[arg(long, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub max_steps: Option<usize>,
    /// Run every trial to the step limit, also after it succeeded (default: stop at success);
    /// success is then judged on the final state.
    #[arg(long)]
    pub full_length: bool,
    /// Earlier reports of the same task whose models' curves join the plot (e.g. a slow model
    /// run separately).
    #[arg(long)]
    pub compare: Vec<PathBuf>,
    /// Add every trial's executed path (the world's observed points and the gripper, one frame
    /// per step) as a training episode of the dataset in this directory: appended when it
    /// holds one (e.g. a copy of the run's dataset), else created with the run's dataset's
    /// metadata. On-policy data: the motions the planner chooses, for training a model on
    /// them. Not for rerouting (the dataset format has no obstacles).
    #[arg(long)]
    pub record: Option<PathBuf>,
    /// `pgrd-members`: weight of the members' disagreement (standard deviation of their
    /// costs) in a candidate's cost; 0 scores by their mean cost alone. Any other value
    /// without `--model pgrd-members` is an error (no other model has members).
    #[arg(long, default_value_t = 0.0)]
    pub member_risk: f64,
    /// Override the task's MPPI temperature (the weights' `exp(−(c − c_min) / λ)`, m of
    /// Chamfer distance; default 0.01).
    #[arg(long)]
    pub temperature: Option<f64>,
    /// Override the task's candidate sequences per MPPI iteration (the paper's: 8 on the simple
    /// tasks, 15 on rerouting).
    #[arg(long)]
    pub samples: Option<usize>,
    /// Override the task's planning horizon, steps of 0.1 s (10; rerouting 15).
    #[arg(long)]
    pub horizon: Option<usize>,
    /// Override the task's MPPI iterations per replanning step (3; rerouting 6).
    #[arg(long)]
    pub iterations: Option<usize>,
    /// Override the task's action noise (covariance of the normalised action per axis, 0.1).
    #[arg(long)]
    pub noise: Option<f32>,
}

/// One trial in the report.
#[derive(Serialize)]
struct TrialReport {
    trial: usize,
    seed: u64,
    success: bool,
    steps: usize,
    final_chamfer_cm: f64,
    chamfer_curve_cm: Vec<f64>,
    stopped: Option<String>,
    failed_rollouts: usize,
    replan_wall_s_mean: f64,
    replan_wall_s_max: f64,
    /// Mean wall time per step the model took to learn from the executed step (`pgrd-online`;
    /// about 0 for the others), s.
    observe_wall_s_mean: f64,
    /// Per learned model: its prediction error along this trial's executed path (see
    /// [`path_error_cm`]), cm; null where the path was too short or a prediction failed.
    path_error_cm: std::collections::BTreeMap<&'static str, Option<f64>>,
    /// `pgrd-online` only: the residual gain it planned with after each executed step.
    #[serde(skip_serializing_if = "Option::is_none")]
    residual_gains: Option<Vec<f32>>,
    /// `pgrd-members` only: per replanning step, the standard deviation over the members of
    /// the costs of the candidate the planner scored best in its last iteration, cm of
    /// Chamfer distance (`plan::ReplanStats::best_member_sd`).
    #[serde(skip_serializing_if = "Option::is_none")]
    member_cost_sd_cm: Option<Vec<f64>>,
}

/// One model's results.
#[derive(Serialize)]
struct ModelReport {
    model: ModelArg,
    successes: usize,
    trials: Vec<TrialReport>,
    /// Mean over trials of the Chamfer distance after each executed step; a trial that ended
    /// early (done) holds its last value.
    mean_curve_cm: Vec<f64>,
    final_chamfer_cm_mean: f64,
    /// Per learned model, the mean of the trials' `path_error_cm` (trials without one left
    /// out), cm.
    path_error_cm_mean: std::collections::BTreeMap<&'static str, f64>,
    wall_s: f64,
}

/// Runs `plan`.
pub fn run(args: &PlanArgs) -> anyhow::Result<()> {
    let kind: TaskKind = args.task.parse()?;
    anyhow::ensure!(args.trials >= 1, "--trials must be at least 1");
    anyhow::ensure!(
        args.first_trial.checked_add(args.trials).is_some(),
        "--first-trial {} plus --trials {} is past the last trial index",
        args.first_trial,
        args.trials
    );
    anyhow::ensure!(
        args.record.is_none() || kind != TaskKind::Reroute,
        "--record cannot record rerouting: the dataset format has no obstacles, so a model \
         trained on its paths would never see the slot"
    );
    let net = read_residual(&args.run)?.map(std::sync::Arc::new);
    let models = if args.model.is_empty() {
        let mut m = vec![ModelArg::SpringMass];
        if net.is_some() {
            m.push(ModelArg::Pgrd);
        }
        m
    } else {
        args.model.clone()
    };
    if let Some(m) = models.iter().find(|m| {
        matches!(
            m,
            ModelArg::Pgrd | ModelArg::PgrdOnline | ModelArg::PgrdMembers
        )
    }) && net.is_none()
    {
        anyhow::bail!(
            "--model {} needs {} (run `cargo xtask train` first)",
            model_name(*m),
            args.run.join("residual.safetensors").display()
        );
    }
    if models.contains(&ModelArg::PgrdMembers)
        && let Some(net) = &net
    {
        anyhow::ensure!(
            net.ensemble_size() >= 2,
            "--model pgrd-members needs an ensemble of networks in {} (`cargo xtask ensemble`); \
             it holds one network, which is --model pgrd",
            args.run.display()
        );
    }
    // Only member trajectories have a spread to weigh; on any other model the weight would be
    // silently ignored, and the user would think the plan risk-averse.
    anyhow::ensure!(
        args.member_risk == 0.0 || models.contains(&ModelArg::PgrdMembers),
        "--member-risk weighs the members' disagreement, which only --model pgrd-members \
         scores; the models asked for ({}) have one prediction per candidate",
        models
            .iter()
            .map(|m| model_name(*m))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let mut mppi_cfg = kind.mppi();
    mppi_cfg.member_risk = args.member_risk;
    if let Some(t) = args.temperature {
        mppi_cfg.temperature = t;
    }
    mppi_cfg.samples = args.samples.unwrap_or(mppi_cfg.samples);
    mppi_cfg.horizon = args.horizon.unwrap_or(mppi_cfg.horizon);
    mppi_cfg.iterations = args.iterations.unwrap_or(mppi_cfg.iterations);
    mppi_cfg.noise = args.noise.unwrap_or(mppi_cfg.noise);
    mppi_cfg.validate()?;
    let backbone = read_backbone(&args.run)?;
    // The field is per tracked particle of the training data; a task's rope has its own.
    anyhow::ensure!(
        backbone.refined.is_none(),
        "{} holds a refined stiffness field (`cargo xtask refine`), which is placed on the \
         training data's tracked particles; planning builds its rope from the task",
        args.run.display()
    );
    let tracked = match args.tracked {
        Some(n) => n,
        None => dataset_particles(&backbone.dataset).unwrap_or(150),
    };
    let mut cfg = TaskConfig {
        tracked,
        resolution: match args.resolution {
            ResolutionArg::Coarse => world::Resolution::Coarse,
            ResolutionArg::Full => world::Resolution::Full,
        },
        ..TaskConfig::new()
    };
    let trial_seeds = trial_seeds(args.first_trial, args.trials, args.seed);
    let tasks = build_tasks(kind, &mut cfg, &trial_seeds, !args.full_length)?;
    let mut reports = Vec::new();
    for &m in &models {
        let t0 = Instant::now();
        let mut trials = Vec::new();
        let mut trajectories = Vec::new();
        for (&(t, seed), task) in trial_seeds.iter().zip(&tasks) {
            let (mut report, traj) = if m == ModelArg::World {
                let oracle = WorldOracle::new(task.start.clone());
                run_trial(
                    &oracle,
                    &mut oracle.system(),
                    task,
                    mppi_cfg,
                    seed,
                    args.max_steps,
                )?
            } else if let (ModelArg::PgrdOnline, Some(net)) = (m, &net) {
                let bb = task_backbone(task, &backbone)?;
                let model = OnlinePgrd::new(bb, net, &DEFAULT_GAINS, kind.mppi().horizon)?;
                let mut world = task.start.clone();
                let (mut report, traj) =
                    run_trial(&model, &mut world, task, mppi_cfg, seed, args.max_steps)?;
                report.residual_gains = Some(model.chosen_gains());
                (report, traj)
            } else {
                let bb = task_backbone(task, &backbone)?;
                let model: Box<dyn ForwardModel> = match (m, &net) {
                    (ModelArg::Pgrd, Some(net)) => Box::new(Pgrd::new(bb, net.clone())),
                    (ModelArg::PgrdMembers, Some(net)) => {
                        Box::new(Pgrd::with_member_trajectories(bb, net.clone())?)
                    }
                    _ => Box::new(SpringMass::new(bb)),
                };
                let mut world = task.start.clone();
                let (mut report, traj) = run_trial(
                    model.as_ref(),
                    &mut world,
                    task,
                    mppi_cfg,
                    seed,
                    args.max_steps,
                )?;
                if m == ModelArg::PgrdMembers {
                    let sd = traj.replans.iter().map(|r| r.best_member_sd * 100.0);
                    report.member_cost_sd_cm = Some(sd.collect());
                }
                (report, traj)
            };
            report.trial = t;
            for (name, scorer) in scorers(task, &backbone, net.as_ref())? {
                report.path_error_cm.insert(
                    name,
                    path_error_cm(scorer.as_ref(), &traj, kind.mppi().horizon),
                );
            }
            let gains = report.residual_gains.as_ref().map_or(String::new(), |g| {
                let at = |x: f32| g.iter().filter(|&&v| v == x).count();
                format!(
                    "; residual gain 0 / 0.5 / 1 in {} / {} / {} steps",
                    at(0.0),
                    at(0.5),
                    at(1.0)
                )
            });
            // A trial the planner had to stop says why on the console too, not only in the JSON.
            let stopped = report
                .stopped
                .as_ref()
                .map_or(String::new(), |why| format!("; stopped: {why}"));
            let replan = if report.steps > 0 {
                format!(", {:.2} s per replan", report.replan_wall_s_mean)
            } else {
                String::new()
            };
            eprintln!(
                "{kind} {} trial {t}: {} in {} steps, final Chamfer {:.2} cm{replan}{gains}{stopped}",
                model_name(m),
                if report.success { "success" } else { "failure" },
                report.steps,
                report.final_chamfer_cm,
            );
            trials.push(report);
            trajectories.push(traj);
        }
        let steps = trials
            .iter()
            .map(|t| t.chamfer_curve_cm.len())
            .max()
            .unwrap_or(0);
        let mean_curve_cm = (0..steps)
            .map(|k| {
                trials
                    .iter()
                    .map(|t| t.chamfer_curve_cm[k.min(t.chamfer_curve_cm.len() - 1)])
                    .sum::<f64>()
                    / trials.len() as f64
            })
            .collect();
        let gif = match &args.gif {
            Some(p) if models.len() == 1 => p.clone(),
            Some(p) => with_suffix(p, &format!("_{}", model_name(m)), "gif"),
            None => with_suffix(&args.json, &format!("_{}", model_name(m)), "gif"),
        };
        if let (Some(task), Some(traj)) = (tasks.first(), trajectories.first()) {
            write_gif(&gif, task, traj)?;
        }
        if let Some(dir) = &args.record {
            let added = record_paths(dir, &backbone.dataset, &tasks, &trajectories)?;
            eprintln!(
                "{kind} {}: {added} paths added to {} (train split)",
                model_name(m),
                dir.display()
            );
        }
        let mut path_error_cm_mean = std::collections::BTreeMap::new();
        for name in trials
            .iter()
            .flat_map(|t| t.path_error_cm.keys().copied())
            .collect::<std::collections::BTreeSet<_>>()
        {
            let v: Vec<f64> = trials
                .iter()
                .filter_map(|t| t.path_error_cm.get(name).copied().flatten())
                .collect();
            if !v.is_empty() {
                path_error_cm_mean.insert(name, v.iter().sum::<f64>() / v.len() as f64);
            }
        }
        reports.push(ModelReport {
            model: m,
            path_error_cm_mean,
            successes: trials.iter().filter(|t| t.success).count(),
            final_chamfer_cm_mean: trials.iter().map(|t| t.final_chamfer_cm).sum::<f64>()
                / trials.len().max(1) as f64,
            mean_curve_cm,
            trials,
            wall_s: t0.elapsed().as_secs_f64(),
        });
    }
    let plot = args
        .plot
        .clone()
        .unwrap_or_else(|| args.json.with_extension("svg"));
    let mut labelled: Vec<(String, Vec<f64>)> = reports
        .iter()
        .map(|r| {
            let label = format!(
                "{} ({}/{} succeeded)",
                model_name(r.model),
                r.successes,
                r.trials.len()
            );
            (label, r.mean_curve_cm.clone())
        })
        .collect();
    for path in &args.compare {
        labelled.extend(compared_curves(path, kind)?);
    }
    let curves: Vec<Curve<'_>> = labelled
        .iter()
        .map(|(label, y)| Curve {
            label: label.clone(),
            y,
        })
        .collect();
    plot_curves(
        &plot,
        &format!(
            "{kind}: Chamfer distance to the target, mean of {} trials",
            args.trials
        ),
        "planning step",
        "Chamfer distance (cm)",
        0.0,
        &curves,
    )?;
    let task0 = &tasks[0];
    let mppi = mppi_cfg;
    write_json(
        &args.json,
        &serde_json::json!({
            "task": kind.name(),
            "run": args.run.display().to_string(),
            "params": backbone.params,
            "tracked": tracked,
            "trials": args.trials,
            "first_trial": args.first_trial,
            "max_steps": args.max_steps.unwrap_or(task0.max_steps),
            "stop_at_success": task0.stop_at_success,
            "mppi": mppi,
            "model_steps_per_replan": mppi.model_steps_per_replan(),
            "success_test": match kind {
                TaskKind::Reroute => "every observed rope point beyond the slot's far face and the gripper below the slot's top at the end, the rope and the gripper having crossed the wall within its length (through the gap)".to_string(),
                _ => format!("Chamfer distance to the target below {} cm", task0.success_chamfer_m * 100.0),
            },
            "slot": task0.slot,
            "workspace": task0.workspace,
            "chamfer": "two-sided sum of means (PGND convention), cm",
            "models": reports,
        }),
    )?;
    for r in &reports {
        let errors: Vec<String> = r
            .path_error_cm_mean
            .iter()
            .map(|(name, e)| format!("{name} {e:.2} cm"))
            .collect();
        println!(
            "{kind} {}: {}/{} succeeded, final Chamfer {:.2} cm (mean); prediction error along its paths: {}",
            model_name(r.model),
            r.successes,
            r.trials.len(),
            r.final_chamfer_cm_mean,
            errors.join(", ")
        );
    }
    Ok(())
}

fn model_name(m: ModelArg) -> &'static str {
    match m {
        ModelArg::SpringMass => "spring-mass",
        ModelArg::Pgrd => "pgrd",
        ModelArg::PgrdOnline => "pgrd-online",
        ModelArg::PgrdMembers => "pgrd-members",
        ModelArg::World => "world",
    }
}

/// Runs one closed-loop trial and summarises it.
fn run_trial(
    model: &dyn ForwardModel,
    world: &mut dyn System,
    task: &Task,
    mut cfg: plan::MppiConfig,
    seed: u64,
    max_steps: Option<usize>,
) -> anyhow::Result<(TrialReport, Trajectory)> {
    cfg.seed = seed;
    let mut mppi = Mppi::new(cfg, 1)?;
    let objective = task.objective()?;
    let settings = LoopSettings {
        max_steps: max_steps.unwrap_or(task.max_steps),
        dt: 0.1,
    };
    let done =
        |x: &[Vec3], g: &[Vec3]| task.stop_at_success && task.success(x, g[0]).unwrap_or(false);
    let traj = run_closed_loop(model, world, &mut mppi, &objective, settings, &done)?;
    let walls: Vec<f64> = traj.replans.iter().map(|r| r.wall_s).collect();
    let report = TrialReport {
        trial: 0,
        seed,
        success: task.trial_success(&traj)?,
        steps: traj.replans.len(),
        final_chamfer_cm: traj.chamfer_m.last().copied().unwrap_or(f64::NAN) * 100.0,
        chamfer_curve_cm: traj.chamfer_m.iter().map(|c| c * 100.0).collect(),
        stopped: traj.stopped.clone(),
        failed_rollouts: traj.replans.iter().map(|r| r.failed).sum(),
        replan_wall_s_mean: walls.iter().sum::<f64>() / walls.len().max(1) as f64,
        replan_wall_s_max: walls.iter().copied().fold(0.0, f64::max),
        observe_wall_s_mean: traj.replans.iter().map(|r| r.observe_wall_s).sum::<f64>()
            / walls.len().max(1) as f64,
        path_error_cm: Default::default(),
        residual_gains: None,
        member_cost_sd_cm: None,
    };
    Ok((report, traj))
}

/// The learned models a trial's executed path is scored with: spring-mass, and PGRD when the
/// run has a network.
fn scorers(
    task: &Task,
    backbone: &BackboneFile,
    net: Option<&std::sync::Arc<residual::ResidualNet>>,
) -> anyhow::Result<Vec<(&'static str, Box<dyn ForwardModel>)>> {
    let mut out: Vec<(&'static str, Box<dyn ForwardModel>)> = vec![(
        "spring-mass",
        Box::new(SpringMass::new(task_backbone(task, backbone)?)),
    )];
    if let Some(net) = net {
        out.push((
            "pgrd",
            Box::new(Pgrd::new(task_backbone(task, backbone)?, net.clone())),
        ));
    }
    Ok(out)
}

/// The run's backbone for `task`, with the library effects its `backbone.json` carries (from
/// `diagnose --write-run`), under the run's substep rule (its damping was fitted for that
/// integrator). Effects placed along the object (stiffness heterogeneity, mass distribution)
/// take their material coordinate from the task's start shape.
fn task_backbone(task: &Task, backbone: &BackboneFile) -> anyhow::Result<springs::Backbone> {
    let options = if backbone.effects.is_empty() {
        springs::BackboneOptions::default()
    } else {
        let frame = gap::MaterialFrame::of_shape(&task.start.observe())?;
        gap::backbone_options(&backbone.effects, &frame)
    };
    Ok(task.backbone_under(backbone.params, backbone.substep.substep(), options)?)
}

/// How well `model` predicts what the world did along an executed path: from every executed
/// step k that has `horizon` more, the model starts from the observations up to k (as the
/// planner does) and is driven along the executed gripper positions; the mean distance
/// between predicted and observed points over the `horizon` steps, averaged over the starts,
/// cm. This is the error of the predictions the planner relied on, on the motions it chose.
fn path_error_cm(model: &dyn ForwardModel, traj: &Trajectory, horizon: usize) -> Option<f64> {
    let n = traj.observed.len();
    if horizon == 0 || n <= horizon {
        return None;
    }
    let mut sum = 0.0;
    let mut count = 0usize;
    for k in 0..n - horizon {
        let state = ModelState::from_frames(&traj.observed[k.saturating_sub(3)..=k], 0.1).ok()?;
        let path = traj.grippers[k..=k + horizon].to_vec();
        let actions = springs::Actions::new(path, vec![vec![true]; horizon + 1]).ok()?;
        let predicted = model.rollout(&state, &actions).ok()?;
        for (p, o) in predicted.iter().zip(&traj.observed[k + 1..=k + horizon]) {
            sum += p
                .iter()
                .zip(o)
                .map(|(a, b)| f64::from(a.distance(*b)))
                .sum::<f64>()
                / p.len().max(1) as f64;
            count += 1;
        }
    }
    (count > 0).then(|| 100.0 * sum / count as f64)
}

/// The labelled mean curves of another `plan` report of the same task.
fn compared_curves(path: &Path, kind: TaskKind) -> anyhow::Result<Vec<(String, Vec<f64>)>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    anyhow::ensure!(
        v["task"] == kind.name(),
        "{} is a report of task {}, not {kind}",
        path.display(),
        v["task"]
    );
    let models = v["models"]
        .as_array()
        .with_context(|| format!("{}: no models", path.display()))?;
    models
        .iter()
        .map(|m| {
            let curve: Vec<f64> = serde_json::from_value(m["mean_curve_cm"].clone())
                .with_context(|| format!("{}: mean_curve_cm", path.display()))?;
            let trials = m["trials"].as_array().map_or(0, Vec::len);
            let label = format!(
                "{} ({}/{trials} succeeded)",
                m["model"].as_str().unwrap_or("?"),
                m["successes"]
            );
            Ok((label, curve))
        })
        .collect()
}

/// Appends each trial's executed path to the dataset at `dir` (created from the metadata of
/// `run_dataset`, the dataset the run was fitted on, when `dir` holds none) as a training
/// episode; returns how many were added. Every trial's rope must match the dataset's step
/// length and particle count, or the data would not be one model's.
fn record_paths(
    dir: &Path,
    run_dataset: &str,
    tasks: &[Task],
    trajectories: &[Trajectory],
) -> anyhow::Result<usize> {
    use dataset::{Dataset, DatasetMeta, DatasetWriter, Episode, Manipulation, Split};
    let mut writer = if dir.join("dataset.json").exists() {
        DatasetWriter::append(dir)?
    } else {
        let meta = match Dataset::open(run_dataset) {
            Ok(d) => d.meta,
            Err(_) => DatasetMeta::new("rope", 10.0, Manipulation::Grasp),
        };
        DatasetWriter::create(dir, meta)?
    };
    let meta = writer.meta();
    anyhow::ensure!(
        meta.manipulation == Manipulation::Grasp && (meta.fps - 10.0).abs() < 1e-3,
        "{}: recorded paths are grasped at 10 frames per second; this dataset is {:?} at {} fps",
        dir.display(),
        meta.manipulation,
        meta.fps
    );
    let particles = match meta.episodes.first() {
        Some(_) => Some(Dataset::open(dir)?.load_episode(0)?.particles()),
        None => None,
    };
    let mut added = 0;
    for (task, traj) in tasks.iter().zip(trajectories) {
        let n = task.start.held().len();
        anyhow::ensure!(
            particles.is_none_or(|p| p == n),
            "{}: its episodes have {} particles, the task's rope {n} (--tracked)",
            dir.display(),
            particles.unwrap_or(0)
        );
        let frames = traj.observed.len();
        let positions: Vec<Vec3> = traj.observed.iter().flatten().copied().collect();
        let grippers: Vec<Vec3> = traj.grippers.iter().flatten().copied().collect();
        let g = grippers.len() / frames.max(1);
        let episode = Episode::new(frames, n, g, positions, grippers)?
            .with_held(task.start.held().to_vec())?
            .with_closed(vec![1; frames * g])?;
        writer.add_episode(&episode, Split::Train)?;
        added += 1;
    }
    writer.finish()?;
    let short = trajectories
        .iter()
        .filter(|t| scene::Protocol::Paper.window(t.observed.len()).is_err())
        .count();
    if short > 0 {
        eprintln!(
            "note: {short} of these paths have fewer frames than the paper protocol's scenes need \
             (40), so `train` and `fit` refuse them; record with --full-length --max-steps 39"
        );
    }
    Ok(added)
}

/// Particles per frame of the run's dataset, when it can be opened.
fn dataset_particles(dir: &str) -> Option<usize> {
    let data = dataset::Dataset::open(dir).ok()?;
    Some(data.load_episode(0).ok()?.particles())
}

/// `path` with `suffix` appended to its stem and extension `ext`.
fn with_suffix(path: &Path, suffix: &str, ext: &str) -> PathBuf {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!("{stem}{suffix}.{ext}"))
}

/// (trial index, planner seed) of each trial a run plans: trial k plans with `seed + k`
/// (wrapping, so any seed is valid).
fn trial_seeds(first_trial: usize, trials: usize, seed: u64) -> Vec<(usize, u64)> {
    (first_trial..first_trial.saturating_add(trials))
        .map(|k| (k, seed.wrapping_add(k as u64)))
        .collect()
}

/// The task of each trial: rerouting draws trial k's start and target from k; the simple tasks
/// use one start and target for every trial (as in the paper).
fn build_tasks(
    kind: TaskKind,
    cfg: &mut TaskConfig,
    trial_seeds: &[(usize, u64)],
    stop_at_success: bool,
) -> anyhow::Result<Vec<Task>> {
    trial_seeds
        .iter()
        .map(|&(t, _)| {
            cfg.trial = if kind == TaskKind::Reroute {
                t as u64
            } else {
                0
            };
            let mut task =
                Task::build(kind, cfg).with_context(|| format!("building {kind} trial {t}"))?;
            task.stop_at_success = stop_at_success;
            Ok(task)
        })
        .collect()
}

/// Writes an animated GIF of a trajectory (top, side and front views; the target in blue).
fn write_gif(path: &Path, task: &Task, traj: &Trajectory) -> anyhow::Result<()> {
    let obstacles = task.obstacles()?;
    let frames: Vec<Frame<'_>> = traj
        .observed
        .iter()
        .zip(&traj.grippers)
        .map(|(x, g)| Frame {
            points: x,
            target: &task.target,
            grippers: g,
            obstacles: &obstacles,
        })
        .collect();
    let bounds = view_bounds(&frames);
    let mut bytes = Vec::new();
    {
        let first = render(&frames[0], bounds);
        let (w, h) = (u16::try_from(first.width)?, u16::try_from(first.height)?);
        let mut enc = gif::Encoder::new(&mut bytes, w, h, &[])?;
        enc.set_repeat(gif::Repeat::Infinite)?;
        for (i, f) in frames.iter().enumerate() {
            let img = render(f, bounds);
            let mut frame = gif::Frame::from_rgb_speed(w, h, &img.rgb, 10);
            // 0.1 s per step, the last frame held for a second.
            frame.delay = if i + 1 == frames.len() { 100 } else { 10 };
            enc.write_frame(&frame)?;
        }
    }
    dataset::write_atomic(path, &bytes).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan_args(task: &str, record: PathBuf) -> PlanArgs {
        PlanArgs {
            task: task.into(),
            run: std::env::temp_dir().join("pgrd-plan-no-such-run"),
            model: vec![ModelArg::SpringMass],
            trials: 1,
            json: std::env::temp_dir().join("pgrd-plan-unused.json"),
            plot: None,
            gif: None,
            seed: 0,
            first_trial: 0,
            tracked: None,
            resolution: ResolutionArg::Coarse,
            max_steps: None,
            full_length: false,
            compare: Vec::new(),
            record: Some(record),
            member_risk: 0.0,
            temperature: None,
            samples: None,
            horizon: None,
            iterations: None,
            noise: None,
        }
    }

    /// A path of `steps` gripper moves on the lift task's rope, as a closed loop records it.
    fn lifted_path(task: &Task, steps: usize) -> Trajectory {
        let mut world = task.start.clone();
        let mut traj = Trajectory {
            observed: vec![world.observe()],
            grippers: vec![vec![world.gripper()]],
            chamfer_m: Vec::new(),
            replans: Vec::new(),
            done: false,
            stopped: None,
        };
        for _ in 0..steps {
            let to = world.gripper() + Vec3::new(0.0, 0.0, 0.02);
            world.step(to).unwrap();
            traj.observed.push(world.observe());
            traj.grippers.push(vec![world.gripper()]);
        }
        traj
    }

    #[test]
    fn a_trial_run_on_its_own_is_the_same_trial_as_in_a_longer_run() {
        let run = trial_seeds(0, 4, 7);
        let alone = trial_seeds(3, 1, 7);
        assert_eq!(alone, vec![(3, 10)]);
        assert_eq!(alone[..], run[3..]);
        let mut cfg = TaskConfig {
            tracked: 30,
            ..TaskConfig::new()
        };
        let long = build_tasks(TaskKind::Reroute, &mut cfg, &run, true).unwrap();
        let single = build_tasks(TaskKind::Reroute, &mut cfg, &alone, true).unwrap();
        assert_eq!(single[0].target, long[3].target);
        assert_eq!(single[0].start.observe(), long[3].start.observe());
        // Rerouting's trials differ from one another, so the trial's index chose its geometry,
        // not its place in the run.
        assert_ne!(single[0].target, long[0].target);
        assert!(single[0].stop_at_success);
    }

    #[test]
    fn recorded_paths_become_training_episodes_of_a_new_or_existing_dataset() {
        let dir = std::env::temp_dir().join(format!("pgrd-plan-record-{}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        let cfg = TaskConfig {
            tracked: 30,
            ..TaskConfig::new()
        };
        let task = Task::build(TaskKind::RopeLift, &cfg).unwrap();
        let paths = [lifted_path(&task, 2), lifted_path(&task, 3)];
        let tasks = [task.clone(), task.clone()];
        // Created from the run's dataset's metadata (the fixture's gripper radius) ...
        let fixture = crate::cmd_fit::FIXTURE_ROPE;
        assert_eq!(record_paths(&dir, fixture, &tasks, &paths).unwrap(), 2);
        // ... then appended to.
        assert_eq!(
            record_paths(&dir, fixture, &tasks[..1], &paths[..1]).unwrap(),
            1
        );
        let data = dataset::Dataset::open(&dir).unwrap();
        let fixture_meta = dataset::Dataset::open(fixture).unwrap().meta;
        assert_eq!(data.meta.gripper_radius, fixture_meta.gripper_radius);
        assert_eq!(data.split_indices(dataset::Split::Train), vec![0, 1, 2]);
        let ep = data.load_episode(1).unwrap();
        assert_eq!((ep.frames(), ep.particles(), ep.grippers()), (4, 30, 1));
        assert_eq!(data.held(&ep), task.start.held());
        assert!(data.held(&ep).contains(&0));
        let last = &paths[1].observed[3];
        assert_eq!(ep.positions()[3 * 30..].to_vec(), *last);
        // A rope of another size does not join these episodes.
        let other = Task::build(
            TaskKind::RopeLift,
            &TaskConfig {
                tracked: 20,
                ..TaskConfig::new()
            },
        )
        .unwrap();
        let err = record_paths(
            &dir,
            fixture,
            std::slice::from_ref(&other),
            &[lifted_path(&other, 1)],
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("30 particles") && err.contains("20"), "{err}");
        assert_eq!(dataset::Dataset::open(&dir).unwrap().meta.episodes.len(), 3);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn member_trajectories_need_an_ensemble_and_a_valid_risk_and_temperature() {
        let run = std::env::temp_dir().join(format!("pgrd-plan-members-{}", std::process::id()));
        std::fs::create_dir_all(&run).unwrap();
        residual::ResidualNet::new(&residual::ModelConfig::tiny(), 1)
            .unwrap()
            .save(&run.join("residual.safetensors"))
            .unwrap();
        let mut args = plan_args("rope-lift", run.join("unused"));
        args.record = None;
        args.run = run.clone();
        args.model = vec![ModelArg::PgrdMembers];
        let err = run_plan_error(&args);
        assert!(err.contains("needs an ensemble"), "{err}");
        // Past that check with two networks, a negative risk is refused before any work.
        let cfg = residual::ModelConfig::tiny();
        residual::ResidualNet::ensemble(vec![
            residual::ResidualNet::new(&cfg, 1).unwrap(),
            residual::ResidualNet::new(&cfg, 2).unwrap(),
        ])
        .unwrap()
        .save(&run.join("residual.safetensors"))
        .unwrap();
        args.member_risk = -1.0;
        let err = run_plan_error(&args);
        assert!(err.contains("member_risk"), "{err}");
        // A risk weight asked of models that have no members is refused, not ignored.
        args.model = vec![ModelArg::SpringMass, ModelArg::Pgrd];
        args.member_risk = 1.0;
        let err = run_plan_error(&args);
        assert!(err.contains("only --model pgrd-members"), "{err}");
        args.model = vec![ModelArg::PgrdMembers];
        args.member_risk = 0.0;
        args.temperature = Some(0.0);
        let err = run_plan_error(&args);
        assert!(err.contains("temperature"), "{err}");
        // The paper's settings can be overridden, and a meaningless one is refused.
        args.temperature = None;
        args.horizon = Some(0);
        let err = run_plan_error(&args);
        assert!(err.contains("horizon"), "{err}");
        args.horizon = None;
        args.noise = Some(f32::NAN);
        let err = run_plan_error(&args);
        assert!(err.contains("noise"), "{err}");
        std::fs::remove_dir_all(&run).unwrap();
    }

    fn run_plan_error(args: &PlanArgs) -> String {
        format!("{:#}", run(args).unwrap_err())
    }

    #[test]
    fn rerouting_is_not_recorded() {
        let args = plan_args("reroute", std::env::temp_dir().join("pgrd-plan-never"));
        let err = run(&args).unwrap_err().to_string();
        assert!(err.contains("no obstacles"), "{err}");
        assert!(!std::env::temp_dir().join("pgrd-plan-never").exists());
    }
}
