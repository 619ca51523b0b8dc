//! `cargo xtask diagnose-bench`: the diagnosis scored on reference-world data whose effect was
//! withheld from the model. Per object:
//!
//! 1. data without any effect; the backbone fitted on it (threshold and springs per particle
//!    are kept for every case of the object);
//! 2. the object's *base model*: diagnose the no-effect data; while the verdict is an effect
//!    (at most `--max-base` times), add it to the model and diagnose again. The base effects are
//!    the model-class corrections of the object (e.g. bending springs for a sheet);
//! 3. `none`: a replicate of the no-effect data (next seed), diagnosed against the base model;
//! 4. per effect: the effect alone, its strength scaled up the ladder `--scales` until the base
//!    model refitted on it (the diagnosis' control refit) has a training MDE above the same
//!    refit's on the no-effect data by `--target-raise` × the latter (chosen before and
//!    independently of the diagnosis), or, if no rung does, at the rung where the effect moves
//!    the object most; then diagnosed against the base model.
//!
//! Every control refit starts from the same base model with the same seed and budget, and the
//! effect data share the no-effect data's seed (same placements and gripper motions), so the
//! effect-attributable gap is a paired difference.
//!
//! Method: `docs/gap.md`; measured results: `docs/gap-log.md`. Here: the steps above; what
//! `--json` holds in `records.rs`; the confusion matrix and the shares right in `summary.rs`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use dataset::{Dataset, Split};
use fit::{BackboneFamily, FitConfig};
use gap::{BaseEffect, Candidate, DiagnoseConfig, Diagnosis};
use scene::{Protocol, Scene};
use springs::SpringParams;
use world::{EffectKind, Effects, ObjectKind};

mod page;
mod records;
mod summary;
#[cfg(test)]
mod tests;

use super::write_report;
use crate::cmd_fit::BoundsArg;
use crate::common::{BackboneFile, SubstepArg, backbone_path, read_residual, scenes};
use crate::report::write_json;
use records::PartialBench;
pub use records::{BaseStep, BenchCase, BenchSummary, ObjectModel, Rung, SkippedCase};

/// Which cases run on which object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CasePlan {
    /// Every case on every object.
    All,
    /// Each effect only on objects whose motions excite it ([`relevant_cases`]).
    Relevant,
    /// Each effect only on objects the world visibly moves with it: where its displacement
    /// ([`world::effect_displacement_m`], measured before any fit) at the ladder's top scale
    /// is at least `--min-displacement-cm`.
    Visible,
}

/// The effects (world names, the out-of-library ones included) each object's recorded motions
/// expose it to,
/// fixed from the world's default effects and motions (docs/world.md) before any bench run
/// used it: friction needs an object that slides on the table (not the hanging paper, flag or
/// duster), grasp slip a grasped one (not the pushed teddy), drag a light object with a large
/// area, heterogeneity and mass distribution an object with parts, plasticity one that is bent
/// and released. Every effect has at least three objects. The fan (session 57) is on every
/// object's list: its jet crosses the workspace where each object moves.
pub fn relevant_cases(object: ObjectKind) -> &'static [&'static str] {
    match object {
        ObjectKind::Rope => &[
            "bending",
            "friction",
            "plasticity",
            "actuation-delay",
            "grasp-slip",
            "magnet",
            "rotating-frame",
            "fan",
        ],
        ObjectKind::Paper => &[
            "drag",
            "bending",
            "plasticity",
            "actuation-delay",
            "grasp-slip",
            "magnet",
            "rotating-frame",
            "fan",
        ],
        ObjectKind::Flag => &[
            "drag",
            "nonlinear-elasticity",
            "actuation-delay",
            "rotating-frame",
            "fan",
        ],
        ObjectKind::Sloth => &[
            "stiffness-heterogeneity",
            "nonlinear-elasticity",
            "friction",
            "plasticity",
            "grasp-slip",
            "mass-distribution",
            "magnet",
            "rotating-frame",
            "fan",
        ],
        ObjectKind::Duster => &[
            "drag",
            "stiffness-heterogeneity",
            "bending",
            "mass-distribution",
            "rotating-frame",
            "fan",
        ],
        ObjectKind::Teddy => &[
            "stiffness-heterogeneity",
            "nonlinear-elasticity",
            "friction",
            "mass-distribution",
            "rotating-frame",
            "fan",
        ],
    }
}

/// Arguments of `diagnose-bench`. They are written into `--json` as `settings`, so a bench
/// report says how it was made (seed, dataset size, ladder, link sweeps, rule, …).
#[derive(clap::Args, serde::Serialize)]
pub struct DiagnoseBenchArgs {
    /// Write the objects, cases and summary as JSON here (rewritten after every case with the
    /// objects and cases so far, under the summary's keys; the summary at the end).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Objects to generate (comma-separated).
    #[arg(long, default_value = "rope,paper,sloth")]
    pub objects: String,
    /// Cases: comma-separated world effect names (the out-of-library `magnet`,
    /// `rotating-frame` and `fan` included) and `none` (default: all).
    #[arg(long)]
    pub cases: Option<String>,
    /// Which of those cases run on which object: every case on every object, or on each
    /// object only the effects it is physically exposed to ([`relevant_cases`]) plus `none`.
    #[arg(long, value_enum, default_value_t = CasePlan::All)]
    pub plan: CasePlan,
    /// Training episodes per generated dataset.
    #[arg(long, default_value_t = 16)]
    pub episodes: usize,
    /// Held-out episodes per generated dataset.
    #[arg(long, default_value_t = 8)]
    pub val: usize,
    /// Episodes cut from one continuous recording. The default 1 makes every episode its own
    /// recording (its own placement and motion): episodes cut from one recording share 20
    /// frames with their neighbours, so with 10 per recording the 8 held-out episodes were
    /// one recording and the bootstrap over them treated correlated episodes as independent.
    #[arg(long, default_value_t = 1)]
    pub episodes_per_recording: usize,
    /// Tracked particles.
    #[arg(long, default_value_t = 60)]
    pub tracked: usize,
    /// Generations of the backbone fit on each object's no-effect data.
    #[arg(long, default_value_t = 16)]
    pub fit_generations: usize,
    /// Generations of each diagnosis refit.
    #[arg(long, default_value_t = 8)]
    pub generations: usize,
    /// Training episodes sampled per generation.
    #[arg(long, default_value_t = 6)]
    pub samples: usize,
    /// Seed of the data and of every fit (the `none` replicate uses seed + 1).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Seed of the cases' diagnoses alone (their refits' draws and bootstraps; default:
    /// `--seed`). The data, the backbone fit and the base search keep `--seed`, so a bench that
    /// differs only here diagnoses the same data against the same base models: it measures
    /// how much of a verdict is the refits' luck.
    #[arg(long)]
    pub case_seed: Option<u64>,
    /// Final selection of every fit and refit: the optimiser's mean and the best candidates
    /// of this many of the best generations are scored on all training episodes and the best
    /// is kept (0: the best candidate by its own generation's sampled episodes).
    #[arg(long, default_value_t = 3)]
    pub rescore: usize,
    /// Most training episodes the rescoring scores (a seeded subset when there are more;
    /// 0: all).
    #[arg(long, default_value_t = 64)]
    pub rescore_scenes: usize,
    /// The substep rule of every diagnosis (`diagnose --substep`); the backbones are fitted
    /// with `fit`'s default, `auto`, either way.
    #[arg(long, value_enum, default_value_t = SubstepArg::Auto)]
    pub substep: SubstepArg,
    /// Race the candidates' refits in every case's diagnosis (`diagnose --race`; 0: off); the
    /// base search's diagnoses are not raced.
    #[arg(long, default_value_t = 0)]
    pub race: usize,
    /// The probe's refit runs this many times `--generations` in every diagnosis, the base
    /// search's included (`diagnose --probe-factor`; default: `diagnose`'s).
    #[arg(long, default_value_t = DiagnoseConfig::default().probe_factor)]
    pub probe_factor: usize,
    /// CMA-ES candidates per generation of the probe's refit in every diagnosis, the base
    /// search's included (`diagnose --probe-population`; 0: as every refit's).
    #[arg(long, default_value_t = DiagnoseConfig::default().probe_population)]
    pub probe_population: usize,
    /// Training episodes sampled per generation by every case's diagnosis refits (default:
    /// `--samples`); the backbone fit and the base search keep `--samples`, so that benches
    /// that differ only here diagnose their cases against the same base models. Measures what
    /// the time budget's fewer-samples rung costs in verdicts.
    #[arg(long)]
    pub case_samples: Option<usize>,
    /// Most base effects per object (0: diagnose against the bare backbone).
    #[arg(long, default_value_t = 2)]
    pub max_base: usize,
    /// Search bounds of each object's backbone fit (the diagnosis refits around the result),
    /// the threshold's range widened where the tracked points are sparse (as `fit`'s).
    #[arg(long, value_enum, default_value_t = BoundsArg::Reference)]
    pub bounds: BoundsArg,
    /// Keep `--bounds`' threshold range as it is (as `fit --fixed-threshold-range`; the
    /// benches before 2026-12-07).
    #[arg(long)]
    pub fixed_threshold_range: bool,
    /// Strength ladder: multiples of the world's default strength tried in order
    /// (comma-separated; `1` keeps the defaults).
    #[arg(long, default_value = "1,4,16,64")]
    pub scales: String,
    /// Least raise of the base model's training MDE an effect must cause, as a fraction of
    /// its no-effect training MDE.
    #[arg(long, default_value_t = 0.5)]
    pub target_raise: f64,
    /// `--plan visible`: least world-level displacement, cm, an effect must cause at the
    /// ladder's top scale to be tried on an object.
    #[arg(long, default_value_t = 1.0)]
    pub min_displacement_cm: f64,
    /// Gripper motions of every generated dataset (`everyday` or `probing`; see `gen`).
    #[arg(long, default_value_t = world::MotionStyle::Everyday)]
    pub motion: world::MotionStyle,
    /// Gauss–Seidel sweeps over the links per substep in every generated dataset and
    /// displacement measurement (`gen --link-sweeps`; 1, the default, is the world every bench
    /// so far ran on).
    #[arg(long, default_value_t = 1)]
    pub link_sweeps: usize,
    /// Minutes of residual-network training per case listed in `--network-cases` (0: none).
    /// The network learns on top of the object's base model on the case's training episodes
    /// (`cargo xtask train` defaults, both threads) and joins the diagnosis
    /// (`gap::add_learnable`): a `none` verdict becomes `unknown` when it beats the control
    /// significantly.
    #[arg(long, default_value_t = 0.0)]
    pub network_minutes: f64,
    /// Cases that get a network when `--network-minutes` > 0 (comma-separated, as `--cases`;
    /// default: `none` and the out-of-library effects among the bench's cases).
    #[arg(long)]
    pub network_cases: Option<String>,
    /// The verdict rule's least significant shrinkage in every diagnosis, base searches
    /// included (as `diagnose --min-shrinkage`).
    #[arg(long, default_value_t = gap::VerdictRule::default().min_shrinkage)]
    pub min_shrinkage: f64,
    /// The verdict rule's least signature cosine for the tie-break in every diagnosis (as
    /// `diagnose --tie-break-min-cosine`; 0 before session 97).
    #[arg(long, default_value_t = gap::VerdictRule::default().tie_break_min_cosine)]
    pub tie_break_min_cosine: f64,
    /// Every diagnosis scores only the optimiser's points in each refit's final rescoring (as
    /// `diagnose --drop-start`; the bench's rule before session 95).
    #[arg(long)]
    pub drop_start: bool,
    /// The cases' diagnoses (second rounds included) hold the object's base effects at the
    /// values its base search fitted, refitting only the backbone's stiffness, damping and
    /// friction and each candidate (as `diagnose --hold-base`); the base searches refit them
    /// as by default.
    #[arg(long)]
    pub hold_base: bool,
    /// The cases' diagnoses hold the base effects in the probe's refit only (as `diagnose
    /// --probe-hold-base`).
    #[arg(long)]
    pub probe_hold_base: bool,
    /// Where generated datasets and reports go.
    #[arg(long, default_value = "target/diagnose-bench")]
    pub work: PathBuf,
    /// Answer as the first two rounds of `cargo xtask chain` would: when a case's diagnosis
    /// names an effect, diagnose again with that effect added at its refitted values (as
    /// `diagnose --write-run` writes it; same settings and seed), and answer `unknown` when
    /// that second round does, otherwise the first round's effect. Its report goes to
    /// `report-round2` (`docs/gap-log.md`, "A second round after an effect verdict").
    #[arg(long)]
    pub second_round: bool,
}

fn generate(
    object: ObjectKind,
    effects: Effects,
    seed: u64,
    args: &DiagnoseBenchArgs,
    dir: &Path,
) -> anyhow::Result<Dataset> {
    let mut cfg = world::GenConfig::fixture(object);
    cfg.train_episodes = args.episodes;
    cfg.val_episodes = args.val;
    cfg.episodes_per_recording = args.episodes_per_recording;
    cfg.tracked = args.tracked;
    cfg.seed = seed;
    cfg.effects = effects;
    cfg.motion = args.motion;
    cfg.link_sweeps = args.link_sweeps;
    // The diagnosis never renders: skip the ground-truth Gaussians.
    cfg.gaussian_particles = 0;
    let data = world::generate(&cfg)?;
    Ok(data.write(dir)?)
}

/// [`world::effect_displacement_m`] of `effects` on `object` with the bench's seed, tracked
/// particles and motions, over `--val` recordings, cm.
fn displacement_cm(
    object: ObjectKind,
    effects: Effects,
    args: &DiagnoseBenchArgs,
) -> anyhow::Result<f64> {
    let mut cfg = world::GenConfig::fixture(object);
    cfg.train_episodes = 0;
    cfg.val_episodes = args.val.max(1);
    cfg.episodes_per_recording = 1;
    cfg.tracked = args.tracked;
    cfg.seed = args.seed;
    cfg.effects = effects;
    cfg.motion = args.motion;
    cfg.link_sweeps = args.link_sweeps;
    Ok(100.0 * world::effect_displacement_m(&cfg)?)
}

fn split(data: &Dataset, substep: SubstepArg) -> anyhow::Result<(Vec<Scene>, Vec<Scene>)> {
    Ok((
        scenes(data, Split::Train, Protocol::Paper, substep)?,
        scenes(data, Split::Val, Protocol::Paper, substep)?,
    ))
}

fn fit_backbone(
    train: &[Scene],
    args: &DiagnoseBenchArgs,
) -> anyhow::Result<(SpringParams, fit::FitOutcome, FitConfig)> {
    let family = BackboneFamily::new(crate::cmd_fit::search_bounds(
        args.bounds,
        args.fixed_threshold_range,
        train,
        false,
    ))?;
    let cfg = FitConfig {
        population: 8,
        generations: args.fit_generations,
        samples: args.samples,
        sigma0: 0.2,
        seed: args.seed,
        rescore: args.rescore,
        rescore_scenes: args.rescore_scenes,
        rescore_start: false,
    };
    let out = fit::fit(train, &family, &cfg, None, &mut |_| {})?;
    Ok((BackboneFamily::params(&out.best), out, cfg))
}

/// One diagnosis with the bench's settings: a case's (`case`) with `--race` and
/// `--case-samples`, the base search's without either, so that benches of one seed that differ
/// only in those diagnose their cases against the same base models.
fn diagnose(
    train: &[Scene],
    val: &[Scene],
    start: &SpringParams,
    base: &[BaseEffect],
    args: &DiagnoseBenchArgs,
    case: bool,
) -> anyhow::Result<Diagnosis> {
    let cfg = case_config(base, args, case);
    Ok(gap::diagnose(train, val, start, &cfg, &mut |_| {})?)
}

/// The settings of [`diagnose`].
fn case_config(base: &[BaseEffect], args: &DiagnoseBenchArgs, case: bool) -> DiagnoseConfig {
    let (race, samples, seed) = if case {
        (
            args.race,
            args.case_samples.unwrap_or(args.samples),
            args.case_seed.unwrap_or(args.seed),
        )
    } else {
        (0, args.samples, args.seed)
    };
    DiagnoseConfig {
        race,
        generations: args.generations,
        probe_factor: args.probe_factor,
        probe_population: args.probe_population,
        samples,
        seed,
        rescore: args.rescore,
        rescore_scenes: args.rescore_scenes,
        keep_start: !args.drop_start,
        base: base.to_vec(),
        hold_base: case && args.hold_base,
        probe_hold_base: case && args.probe_hold_base,
        rule: gap::VerdictRule {
            min_shrinkage: args.min_shrinkage,
            tie_break_min_cosine: args.tie_break_min_cosine,
            ..gap::VerdictRule::default()
        },
        ..DiagnoseConfig::default()
    }
}

/// The control refit alone (the diagnosis without candidates) and its training MDE, cm.
fn control_only(
    train: &[Scene],
    val: &[Scene],
    start: &SpringParams,
    base: &[BaseEffect],
    args: &DiagnoseBenchArgs,
) -> anyhow::Result<(Diagnosis, f64)> {
    let cfg = DiagnoseConfig {
        generations: args.generations,
        samples: args.samples,
        seed: args.seed,
        rescore: args.rescore,
        rescore_scenes: args.rescore_scenes,
        keep_start: !args.drop_start,
        base: base.to_vec(),
        candidates: Vec::new(),
        probe: false,
        ..DiagnoseConfig::default()
    };
    let d = gap::diagnose(train, val, start, &cfg, &mut |_| {})?;
    let (model, effects) = d.refitted_model(start, None)?;
    let frame = gap::material_frame(train)?;
    let mde = gap::evaluate(&frame, train, &model, &effects)?.mde_cm;
    Ok((d, mde))
}

fn labels(base: &[BaseEffect]) -> Vec<String> {
    base.iter().map(BaseEffect::label).collect()
}

fn verdict_shrinkage(d: &Diagnosis) -> Option<f64> {
    d.ranking
        .iter()
        .find(|r| r.effect == d.verdict)
        .map(|r| r.shrinkage)
}

/// Steps 1–2: the backbone on the no-effect data and the object's base model.
fn base_model(
    object: ObjectKind,
    args: &DiagnoseBenchArgs,
) -> anyhow::Result<(ObjectModel, Vec<BaseEffect>, BackboneFile)> {
    let t0 = Instant::now();
    let dir = args.work.join(format!("{object}-none"));
    let data = generate(object, Effects::none(), args.seed, args, &dir)?;
    let (train, val) = split(&data, args.substep)?;
    let (backbone, outcome, fit_cfg) = if args.substep == SubstepArg::Auto {
        fit_backbone(&train, args)?
    } else {
        fit_backbone(&split(&data, SubstepArg::Auto)?.0, args)?
    };
    let (mut start, mut base) = (backbone, Vec::new());
    let mut steps = Vec::new();
    let last = loop {
        let t = Instant::now();
        let d = diagnose(&train, &val, &start, &base, args, false)?;
        write_report(
            &dir.join(format!("report-base{}", steps.len())),
            &d,
            &format!("{object}, no effect, base [{}]", labels(&base).join(", ")),
        )?;
        let step = BaseStep {
            base: labels(&base),
            verdict: d.verdict.clone(),
            shrinkage: verdict_shrinkage(&d),
            control_mde_cm: d.control.heldout_mde_cm,
            wall_s: t.elapsed().as_secs_f64(),
        };
        println!(
            "{object:<6} base search: base [{}] -> control {:.3} cm, verdict {}{} ({:.0} s)",
            step.base.join(", "),
            step.control_mde_cm,
            step.verdict,
            step.shrinkage
                .map_or(String::new(), |s| format!(" ({:+.1}%)", 100.0 * s)),
            step.wall_s
        );
        steps.push(step);
        match Candidate::parse(&d.verdict) {
            Ok(c) if base.len() < args.max_base => {
                // The user's next step: the verdict's effect joins the model, at its refitted
                // values, and the diagnosis runs again.
                (start, base) = d.refitted_model(&start, Some(c))?;
            }
            _ => break d,
        }
    };
    let (model, base) = last.refitted_model(&start, None)?;
    // The reference: the same control refit every case gets, from the base model.
    let (reference, train_mde) = control_only(&train, &val, &model, &base, args)?;
    let m = ObjectModel {
        object: object.to_string(),
        backbone,
        steps,
        model,
        base: labels(&base),
        mde_without_effect_cm: reference.control.heldout_mde_cm,
        train_mde_without_effect_cm: train_mde,
        wall_s: t0.elapsed().as_secs_f64(),
    };
    println!(
        "{object:<6} base model: backbone + [{}], no-effect held-out MDE {:.3} cm (train {:.3}) ({:.0} s)",
        m.base.join(", "),
        m.mde_without_effect_cm,
        m.train_mde_without_effect_cm,
        m.wall_s
    );
    // A base model whose free particles have no spring makes every case of the object a test of
    // a falling object, not of its effect: say so where the bench's reader looks.
    if let Some(scene) = train.first() {
        crate::common::warn_if_unconnected(scene, &model, Default::default())?;
    }
    // The base model as a run's backbone file, for the networks of `--network-minutes`, and
    // as a run directory beside the data (`<object>-base`), so that any case can be diagnosed
    // again with other settings: `diagnose --data <work>/<case> --run <work>/<object>-base`.
    let file = BackboneFile {
        model: "spring-mass".into(),
        dataset: dir.display().to_string(),
        protocol: Protocol::Paper.name().into(),
        params: m.model,
        fit: outcome,
        config: fit_cfg,
        wall_s: m.wall_s,
        session_wall_s: m.wall_s,
        effects: base.clone(),
        refined: None,
        substep: args.substep,
        material_springs: false,
        controller_springs: None,
        controller_starts: Vec::new(),
    };
    let run = args.work.join(format!("{object}-base"));
    std::fs::create_dir_all(&run)?;
    write_json(&backbone_path(&run), &file)?;
    Ok((m, base, file))
}

/// Trains a residual network on top of `file`'s model on `data` for `minutes` (run directory
/// `run`) and adds it to the diagnosis `d`.
fn add_network(
    d: &mut Diagnosis,
    data: &Dataset,
    file: &BackboneFile,
    run: &Path,
    minutes: f64,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(run)?;
    write_json(&backbone_path(run), file)?;
    let argv = [
        "--data".to_string(),
        data.root.display().to_string(),
        "--run".into(),
        run.display().to_string(),
        "--max-minutes".into(),
        minutes.to_string(),
        "--threads".into(),
        "2".into(),
        "--restart".into(),
        "--quiet".into(),
    ];
    let train: crate::cmd_train::TrainArgs = crate::common::parse_command("train", &argv)?;
    crate::cmd_train::run(&train)?;
    let net = read_residual(run)?
        .ok_or_else(|| anyhow::anyhow!("training wrote no network to {}", run.display()))?;
    let options = file.options_for(data, Protocol::Paper)?;
    let (network, alone) = super::network_errors(data, Protocol::Paper, file, &options, &net)?;
    gap::add_learnable(d, &network, &alone)?;
    Ok(())
}

/// Step 4's calibration: generates the effect at each scale of the ladder until the control
/// refit's training MDE rises by the target; returns the chosen dataset and the ladder.
fn calibrate(
    object: ObjectKind,
    kind: EffectKind,
    model: &ObjectModel,
    base: &[BaseEffect],
    scales: &[f32],
    args: &DiagnoseBenchArgs,
) -> anyhow::Result<(Dataset, f32, Vec<Rung>, bool)> {
    let target = args.target_raise * model.train_mde_without_effect_cm;
    let mut ladder: Vec<(Rung, PathBuf)> = Vec::new();
    for &s in scales {
        let dir = args.work.join(format!("{object}-{kind}-x{s}"));
        let data = generate(
            object,
            Effects::only_scaled(object, kind, s),
            args.seed,
            args,
            &dir,
        )?;
        let (train, val) = split(&data, args.substep)?;
        let (_, mde) = control_only(&train, &val, &model.model, base, args)?;
        let rung = Rung {
            scale: s,
            raise_cm: mde - model.train_mde_without_effect_cm,
            displacement_cm: displacement_cm(object, Effects::only_scaled(object, kind, s), args)?,
        };
        let reached = rung.raise_cm >= target;
        ladder.push((rung, dir));
        if reached {
            break;
        }
    }
    let rungs: Vec<Rung> = ladder.iter().map(|(r, _)| r.clone()).collect();
    let (pick, reached) =
        pick_rung(&rungs, target).ok_or_else(|| anyhow::anyhow!("--scales is empty"))?;
    let data = Dataset::open(&ladder[pick].1)?;
    Ok((data, rungs[pick].scale, rungs, reached))
}

/// The rung a case runs at, and whether it reached the target raise: the last rung climbed
/// when it did; otherwise the rung where the effect moves the object most. (The rung with the
/// largest raise, the rule until session 18, was often x1, where the effect moves the object
/// by less than a centimetre: the refit absorbs weak and strong versions alike, so the raise
/// says little there.) `None` for an empty ladder.
fn pick_rung(ladder: &[Rung], target_cm: f64) -> Option<(usize, bool)> {
    let last = ladder.len().checked_sub(1)?;
    if ladder[last].raise_cm >= target_cm {
        return Some((last, true));
    }
    let most_visible = (0..ladder.len()).max_by(|a, b| {
        ladder[*a]
            .displacement_cm
            .total_cmp(&ladder[*b].displacement_cm)
    })?;
    Some((most_visible, false))
}

/// The cases that get a residual network: `--network-cases`, or by default `none` and the
/// out-of-library effects among `cases`. A named case the bench does not run is an error
/// (only checked when networks are on).
fn network_cases(args: &DiagnoseBenchArgs, cases: &[String]) -> anyhow::Result<Vec<String>> {
    let chosen: Vec<String> = match &args.network_cases {
        Some(list) => list.split(',').map(|c| c.trim().to_string()).collect(),
        None => cases
            .iter()
            .filter(|c| *c == "none" || c.parse::<EffectKind>().is_ok_and(|k| !k.in_library()))
            .cloned()
            .collect(),
    };
    if args.network_minutes > 0.0
        && let Some(c) = chosen.iter().find(|c| !cases.contains(c))
    {
        anyhow::bail!(
            "--network-cases: `{c}` is not one of the bench's cases ({})",
            cases.join(",")
        );
    }
    Ok(chosen)
}

/// Runs the bench (see the module documentation); `--json` is rewritten after every case.
pub fn run_bench(args: &DiagnoseBenchArgs) -> anyhow::Result<BenchSummary> {
    let t0 = Instant::now();
    let cases: Vec<String> = match &args.cases {
        Some(c) => c.split(',').map(|s| s.trim().to_string()).collect(),
        None => std::iter::once("none".to_string())
            .chain(EffectKind::ALL.iter().map(|k| k.name().to_string()))
            .collect(),
    };
    let scales: Vec<f32> = args
        .scales
        .split(',')
        .map(|s| s.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .map_err(|e| anyhow::anyhow!("--scales: {e}"))?;
    anyhow::ensure!(
        !scales.is_empty() && scales.iter().all(|s| s.is_finite() && *s > 0.0),
        "--scales needs positive numbers"
    );
    anyhow::ensure!(
        args.episodes_per_recording >= 1,
        "--episodes-per-recording must be at least 1"
    );
    anyhow::ensure!(
        args.network_minutes.is_finite() && args.network_minutes >= 0.0,
        "--network-minutes must be a number >= 0 (got {})",
        args.network_minutes
    );
    let network_cases = network_cases(args, &cases)?;
    let settings = records::settings(args)?;
    let mut objects = Vec::new();
    let mut out: Vec<BenchCase> = Vec::new();
    let mut skipped: Vec<SkippedCase> = Vec::new();
    let save = |objects: &Vec<ObjectModel>, out: &Vec<BenchCase>| -> anyhow::Result<()> {
        if let Some(path) = &args.json {
            // Partial results survive an interrupted bench, under the summary's own keys.
            write_json(
                path,
                &PartialBench {
                    settings: &settings,
                    objects,
                    cases: out,
                },
            )?;
        }
        Ok(())
    };
    for name in args.objects.split(',') {
        let object: ObjectKind = name.trim().parse()?;
        let (model, base, file) = base_model(object, args)?;
        let e0 = model.mde_without_effect_cm;
        objects.push(model.clone());
        save(&objects, &out)?;
        for truth in &cases {
            if args.plan == CasePlan::Relevant
                && truth != "none"
                && !relevant_cases(object).contains(&truth.as_str())
            {
                continue;
            }
            if args.plan == CasePlan::Visible && truth != "none" {
                let kind: EffectKind = truth.parse()?;
                let top = *scales.last().unwrap_or(&1.0);
                let d = displacement_cm(object, Effects::only_scaled(object, kind, top), args)?;
                if d < args.min_displacement_cm {
                    skipped.push(SkippedCase {
                        object: object.to_string(),
                        truth: truth.clone(),
                        scale: top,
                        displacement_cm: d,
                    });
                    println!(
                        "{object:<6} {truth:<24} skipped: moves the object {d:.2} cm at x{top} \
                         (below --min-displacement-cm {})",
                        args.min_displacement_cm
                    );
                    continue;
                }
            }
            let t = Instant::now();
            let (data, dir, scale, ladder, reached) = if truth == "none" {
                // A replicate (next seed): the base model was chosen on the seed's own data.
                let dir = args.work.join(format!("{object}-none-replicate"));
                let data = generate(object, Effects::none(), args.seed + 1, args, &dir)?;
                (data, dir, 1.0, Vec::new(), true)
            } else {
                let kind: EffectKind = truth.parse()?;
                let (data, scale, ladder, reached) =
                    calibrate(object, kind, &model, &base, &scales, args)?;
                let dir = data.root.clone();
                (data, dir, scale, ladder, reached)
            };
            let (train, val) = split(&data, args.substep)?;
            let estimated = gap::effort(
                &train,
                &val,
                &model.model,
                &case_config(&base, args, true),
                args.substep.substep(),
            )?
            .estimated_s();
            let td = Instant::now();
            let mut d = diagnose(&train, &val, &model.model, &base, args, true)?;
            let mut network_wall = 0.0;
            if args.network_minutes > 0.0 && network_cases.contains(truth) {
                let tn = Instant::now();
                add_network(
                    &mut d,
                    &data,
                    &file,
                    &dir.join("pgrd"),
                    args.network_minutes,
                )?;
                if let Some(l) = &d.learnable {
                    println!(
                        "{object:<6} {truth:<24} {} ({:.0} s)",
                        super::learnable_line(l),
                        tn.elapsed().as_secs_f64()
                    );
                }
                network_wall = tn.elapsed().as_secs_f64();
            }
            write_report(
                &dir.join("report"),
                &d,
                &format!("{object}, {truth} ×{scale}"),
            )?;
            let mut rounds = None;
            let mut answer = d.verdict.clone();
            if args.second_round
                && let Ok(effect) = Candidate::parse(&d.verdict)
            {
                let (start, with) = d.refitted_model(&model.model, Some(effect))?;
                let d2 = diagnose(&train, &val, &start, &with, args, true)?;
                write_report(
                    &dir.join("report-round2"),
                    &d2,
                    &format!("{object}, {truth} ×{scale}, second round"),
                )?;
                if d2.verdict == "unknown" {
                    answer = d2.verdict.clone();
                }
                rounds = Some([d.verdict.clone(), d2.verdict]);
            }
            let wall = td.elapsed().as_secs_f64() - network_wall;
            let in_base = base.iter().any(|b| b.effect.name() == truth);
            let out_of_library = truth.parse::<EffectKind>().is_ok_and(|k| !k.in_library());
            let (class, expected) = match truth.as_str() {
                "none" => ("none", "none".to_string()),
                _ if out_of_library => ("out-of-library", "unknown".to_string()),
                _ if in_base => ("in-base", "none".to_string()),
                t => ("in-library", t.to_string()),
            };
            let before = d.control.heldout_mde_cm;
            let gap = before - e0;
            let truth_entry = if out_of_library {
                d.probe.as_ref()
            } else {
                d.ranking.iter().find(|r| &r.effect == truth)
            };
            let after = truth_entry.map(|r| r.heldout_mde_after_cm);
            // The first round's effect's, unless the second round turned the answer.
            let answer_shrinkage = verdict_shrinkage(&d).filter(|_| answer == d.verdict);
            let case = BenchCase {
                object: object.to_string(),
                truth: truth.clone(),
                class: class.to_string(),
                expected,
                verdict: answer,
                rounds,
                scale,
                ladder,
                target_reached: reached,
                verdict_shrinkage: answer_shrinkage,
                mde_before_cm: before,
                mde_without_effect_cm: e0,
                attributable_gap_cm: gap,
                mde_after_cm: after,
                shrinkage: truth_entry.map(|r| r.shrinkage),
                ci95: truth_entry.map(|r| r.ci95),
                recovered: after.filter(|_| gap > 0.0).map(|a| (before - a) / gap),
                true_effect_raced_out: truth_entry.is_some_and(|r| r.raced_out),
                diagnose_wall_s: wall,
                diagnose_estimated_s: estimated,
                network: d.learnable.clone(),
                tie_break: d.tie_break.clone(),
                caution: d.carry_over_caution().is_some(),
            };
            // The rung the case uses (the last one climbed, or the one that moves the object most).
            let rung = case.ladder.iter().find(|r| r.scale == case.scale);
            let raise = rung.map_or(String::new(), |r| {
                format!(
                    " raise {:+.2} cm (moves it {:.2} cm)",
                    r.raise_cm, r.displacement_cm
                )
            });
            println!(
                "{:<6} {:<24} x{:<3}{}{} verdict {:<24} (expected {}) control {:.3} cm, gap {:+.3} cm, true effect {} ({:.0} s + {:.0} s data)",
                case.object,
                case.truth,
                case.scale,
                raise,
                if case.target_reached {
                    ""
                } else {
                    " (target not reached)"
                },
                case.verdict,
                case.expected,
                before,
                gap,
                match (after, case.shrinkage) {
                    (Some(a), Some(s)) => format!(
                        "{a:.3} cm ({:+.1}%, recovered {}{})",
                        100.0 * s,
                        case.recovered
                            .map_or("-".into(), |r| format!("{:.0}%", 100.0 * r)),
                        if case.true_effect_raced_out {
                            ", raced out"
                        } else {
                            ""
                        }
                    ),
                    _ => "-".into(),
                },
                wall,
                t.elapsed().as_secs_f64() - wall - network_wall
            );
            if let Some([first, second]) = &case.rounds {
                println!(
                    "       first round {first}, second round (with {first}) {second}: answers {}",
                    case.verdict
                );
            }
            if let Some(tb) = &case.tie_break {
                println!(
                    "       tied on held-out error: {} (largest shrinkage {}, signature chose {})",
                    tb.tied.join(", "),
                    tb.by_shrinkage,
                    tb.chosen
                );
            }
            out.push(case);
            save(&objects, &out)?;
        }
    }
    let summary = summary::summarise(
        args,
        settings,
        &cases,
        objects,
        out,
        skipped,
        t0.elapsed().as_secs_f64(),
    );
    if let Some(path) = &args.json {
        write_json(path, &summary)?;
        let page = path.with_extension("html");
        crate::plots::or_warn(
            serde_json::to_value(&summary)
                .map_err(anyhow::Error::from)
                .and_then(|v| page::write(&page, &v)),
            &page.display().to_string(),
        );
    }
    Ok(summary)
}
