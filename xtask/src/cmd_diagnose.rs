//! `cargo xtask diagnose` (where / which / how far for one dataset and fitted run) and
//! `cargo xtask diagnose-bench` (the diagnosis scored on reference-world data whose effect was
//! withheld from the model; `cmd_diagnose_bench/`). Method: `docs/gap.md`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use dataset::{Dataset, Split};
use gap::{BaseEffect, Candidate, DiagnoseConfig, Diagnosis};
use scene::{Protocol, Scene};

use crate::common::{
    BackboneFile, NetworkPath, ProtocolArg, SceneSetting, SubstepArg, backbone_path, load_scenes,
    predict_tracked, read_backbone, read_residual, scenes,
};
use crate::report::write_json;

#[path = "cmd_diagnose_bench/mod.rs"]
mod bench;
pub use bench::{DiagnoseBenchArgs, run_bench};

/// Arguments of `diagnose`.
#[derive(clap::Args, Clone, Debug)]
pub struct DiagnoseArgs {
    /// Dataset directory (train split for refits, val split held out).
    #[arg(long)]
    pub data: PathBuf,
    /// Run directory holding backbone.json (from `cargo xtask fit`).
    #[arg(long)]
    pub run: PathBuf,
    /// Report directory (created): report.json and report.html.
    #[arg(long, required_unless_present = "estimate")]
    pub out: Option<PathBuf>,
    /// CMA-ES candidates per generation of each refit.
    #[arg(long, default_value_t = 8)]
    pub population: usize,
    /// Generations of each refit. Default 10, unless `--budget-min` takes the bench's refit
    /// size (8 generations of 6 episodes, rescored on 16).
    #[arg(long)]
    pub generations: Option<usize>,
    /// Training episodes sampled per generation. Default 8 (see `--generations`).
    #[arg(long)]
    pub samples: Option<usize>,
    /// Seed of the refits and the bootstrap.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Bootstrap resamples over held-out episodes.
    #[arg(long, default_value_t = 2000)]
    pub resamples: usize,
    /// Final selection of every refit: the optimiser's mean and the best candidates
    /// of this many of the best generations are scored on all training episodes and the best
    /// is kept (0: the best candidate by its own generation's sampled episodes).
    #[arg(long, default_value_t = 3)]
    pub rescore: usize,
    /// Most training episodes the rescoring scores: a subset of this many, drawn with the
    /// seed, when there are more (0: all; with 100 training episodes the default 64 saves
    /// about 13 % of each refit's rollouts, `docs/gap.md`). Default 64 (see `--generations`).
    #[arg(long)]
    pub rescore_scenes: Option<usize>,
    /// Race the library candidates' refits (0: off): every candidate gets half the
    /// generations, and only the best N by training loss get the rest and the rescoring; the
    /// control and the probe always get the whole budget. Faster, at some risk to the verdict
    /// (`docs/gap-log.md`, "Racing the refits"). Default: off, unless `--budget-min` chooses it.
    #[arg(long)]
    pub race: Option<usize>,
    /// The probe's refit runs this many times `--generations` (1: as every other refit). The
    /// probe searches eleven parameters; a longer refit finds strong fields a short one
    /// misses (`docs/gap-log.md`, "A longer refit for the probe").
    #[arg(long)]
    pub probe_factor: Option<usize>,
    /// CMA-ES candidates per generation of the probe's refit (0: `--population`, as every
    /// other refit). Default: `gap::DiagnoseConfig`'s.
    #[arg(long)]
    pub probe_population: Option<usize>,
    /// Time budget, minutes on the reference 2-core host of `gap::SECONDS_PER_WORK` (0:
    /// none). When the diagnosis's estimated time (`gap::effort`: simulator work counted
    /// before the run, no clock, so the choice is the same on every run) times
    /// `gap::ESTIMATE_MARGIN` (the largest measured overrun) is above it, the refits race
    /// (`--race 3`), then also shrink to the bench's size, then also take the spectral
    /// substep, then also sample 4 episodes a generation instead of 6 (the refit sizes unless
    /// `--generations`, `--samples` or `--rescore-scenes` is given; the race and the substep
    /// unless `--race` or `--substep` is given); the command says so and `report.json`
    /// records it (`budget`). `docs/gap.md`, "Time budget".
    #[arg(long, default_value_t = 10.0, value_parser = crate::common::parse_minutes)]
    pub budget_min: f64,
    /// Print the estimated time of the diagnosis as given and with the speed options the
    /// budget can choose, and stop.
    #[arg(long)]
    pub estimate: bool,
    /// Window of each episode.
    #[arg(long, value_enum, default_value_t = ProtocolArg::Paper)]
    pub protocol: ProtocolArg,
    /// Comma-separated candidate effects (default: the nine library effects). Names starting
    /// with `+` are added to the nine instead, e.g. `+gravity-scale`, `+bending-damping`,
    /// `+twist` or `+stiffness-lag` (extra candidates, offered on request only;
    /// `bending-damping` and `twist` on `chain` datasets; `docs/gap.md`).
    #[arg(long)]
    pub candidates: Option<String>,
    /// Effects already in the model, refitted with the backbone in the control and in every
    /// candidate refit, and not candidates themselves: comma-separated `name` (starts at the
    /// effect's usual strength) or `name=v1[:v2]` (e.g. `bending=0.12`, as printed after a
    /// diagnosis). Default: the effects in the run's backbone.json, if any.
    #[arg(long = "with")]
    pub with: Option<String>,
    /// Skip the generic external-field probe (the verdict can then not be `unknown`).
    #[arg(long)]
    pub no_probe: bool,
    /// Name the significant candidate with the largest shrinkage even when others are tied
    /// with it on held-out error (by default the signature breaks such ties).
    #[arg(long)]
    pub no_tie_break: bool,
    /// Score only the optimiser's points in each refit's final rescoring, not the refit's
    /// start too (the rule before session 95: a control refit could then end worse than the
    /// model as given; `docs/gap.md`, Method 1).
    #[arg(long)]
    pub drop_start: bool,
    /// Hold the base effects (`--with`, or the run's) at their values in the control and every
    /// candidate refit: only the backbone's stiffness, damping and friction and the candidate
    /// are refitted (`gap::DiagnoseConfig::hold_base`; by default the base effects are
    /// refitted with them).
    #[arg(long)]
    pub hold_base: bool,
    /// Hold the base effects at their values in the probe's refit only
    /// (`gap::DiagnoseConfig::probe_hold_base`).
    #[arg(long)]
    pub probe_hold_base: bool,
    /// Least held-out shrinkage (fraction) a candidate, and the effect inside it, must reach
    /// besides an interval above 0 to count as significant (`gap::VerdictRule`).
    #[arg(long, default_value_t = gap::VerdictRule::default().min_shrinkage)]
    pub min_shrinkage: f64,
    /// Least signature cosine with which a tied candidate overrules the one with the largest
    /// shrinkage (`gap::VerdictRule::tie_break_min_cosine`; 0: any larger cosine, the rule
    /// before session 97).
    #[arg(long, default_value_t = gap::VerdictRule::default().tie_break_min_cosine)]
    pub tie_break_min_cosine: f64,
    /// Ignore `<run>/residual.safetensors` (by default a trained network there is scored on
    /// the held-out episodes: how much of the gap is learnable, and `unknown` when it beats
    /// every library model).
    #[arg(long)]
    pub no_network: bool,
    /// Also write this run directory with the model the diagnosis refitted: when the verdict
    /// is an effect, the model that has it, i.e. `backbone.json` with the refitted backbone
    /// parameters and the base effects plus the verdict's, at their refitted values (for
    /// `eval`, `train`, `render` and another `diagnose`, which then starts from those effects
    /// as its base). With the verdict `none`
    /// or `unknown` it holds the better on the held-out episodes of the control refit (the
    /// run's own effects refitted, none added) and the model as given (both held-out MDEs are
    /// printed). A refined
    /// stiffness field of the run (`refine`) is kept as it is: the diagnosis holds it fixed.
    #[arg(long)]
    pub write_run: Option<PathBuf>,
    /// With the verdict `unknown`, `--write-run` adds the effect the library's refits name on
    /// their own (`gap::Diagnosis::library_verdict`: a significant candidate the probe outdid)
    /// instead of writing the model without one; with none significant it writes as for
    /// `unknown`. For users who add every effect that holds out before modelling the rest
    /// (`cargo xtask chain`).
    #[arg(long)]
    pub add_past_unknown: bool,
    /// When the effect `--write-run` adds was tied with other significant candidates (held-out
    /// error could not separate them; `tie_break` in the report), also write the model with the
    /// tied candidate of largest shrinkage it did not add, the runner-up, to this run directory
    /// (refitted values from this diagnosis, as `--write-run` writes them). Nothing is written
    /// without such a tie. `cargo xtask chain --branch-ties` follows it as a second branch.
    #[arg(long)]
    pub write_runner_up: Option<PathBuf>,
    /// How the simulator chooses its substep in every rollout of the diagnosis (the backbone
    /// as given included): every contender is refitted and compared under it. Default: the
    /// run's own, unless `--budget-min` chooses `spectral`. `--write-run` records it in a
    /// refitted model it writes (a model carried on as given keeps its own).
    #[arg(long, value_enum)]
    pub substep: Option<SubstepArg>,
    /// Print only the verdict line.
    #[arg(long)]
    pub quiet: bool,
}

/// `a,b` names the candidates; `+a,+b` adds them to the nine library effects.
fn parse_candidates(list: &str) -> anyhow::Result<Vec<Candidate>> {
    let names: Vec<&str> = list.split(',').map(str::trim).collect();
    let adding = names.iter().filter(|n| n.starts_with('+')).count();
    if adding != 0 && adding != names.len() {
        anyhow::bail!("--candidates: either name every candidate or add with '+' to all, not both");
    }
    let mut out = if adding > 0 {
        Candidate::LIBRARY.to_vec()
    } else {
        Vec::new()
    };
    for name in names {
        let c = Candidate::parse(name.trim_start_matches('+'))?;
        if !out.contains(&c) {
            out.push(c);
        }
    }
    Ok(out)
}

fn config_from(args: &DiagnoseArgs, run_effects: &[BaseEffect]) -> anyhow::Result<DiagnoseConfig> {
    let candidates = match &args.candidates {
        Some(list) => parse_candidates(list)?,
        None => Candidate::LIBRARY.to_vec(),
    };
    Ok(DiagnoseConfig {
        population: args.population,
        generations: args.generations.unwrap_or(DEFAULT_REFITS.generations),
        samples: args.samples.unwrap_or(DEFAULT_REFITS.samples),
        seed: args.seed,
        resamples: args.resamples,
        rescore: args.rescore,
        rescore_scenes: args.rescore_scenes.unwrap_or(DEFAULT_REFITS.rescore_scenes),
        race: args.race.unwrap_or(0),
        probe_factor: args
            .probe_factor
            .unwrap_or(DiagnoseConfig::default().probe_factor),
        probe_population: args
            .probe_population
            .unwrap_or(DiagnoseConfig::default().probe_population),
        candidates,
        base: match &args.with {
            Some(list) => BaseEffect::parse_list(list)?,
            None => run_effects.to_vec(),
        },
        probe: !args.no_probe,
        keep_start: !args.drop_start,
        hold_base: args.hold_base,
        probe_hold_base: args.probe_hold_base,
        rule: gap::VerdictRule {
            signature_tie_break: !args.no_tie_break,
            min_shrinkage: args.min_shrinkage,
            tie_break_min_cosine: args.tie_break_min_cosine,
            ..gap::VerdictRule::default()
        },
        ..DiagnoseConfig::default()
    })
}

/// Arguments of `report-page`.
#[derive(clap::Args)]
pub struct ReportPageArgs {
    /// Report directories, each holding `report.json` (written by `diagnose`).
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    /// Page title (default: the one of the `report.html` there, else the directory's name).
    #[arg(long)]
    pub title: Option<String>,
}

/// `report-page`: writes `<dir>/report.html` again from `<dir>/report.json` with this
/// version's page for every directory given, e.g. for reports written before the page learnt
/// something. Stops at the first directory that fails, naming it.
pub fn report_page(args: &ReportPageArgs) -> anyhow::Result<()> {
    for dir in &args.dirs {
        one_report_page(dir, args.title.as_deref())
            .with_context(|| format!("report-page {}", dir.display()))?;
    }
    Ok(())
}

fn one_report_page(dir: &Path, title: Option<&str>) -> anyhow::Result<()> {
    let json = dir.join("report.json");
    let text =
        std::fs::read_to_string(&json).with_context(|| format!("reading {}", json.display()))?;
    let d: Diagnosis = serde_json::from_str(&text)
        .with_context(|| format!("{} is not a diagnosis report", json.display()))?;
    let page = dir.join("report.html");
    let title = match title {
        Some(t) => t.to_string(),
        None => page_title(&page).unwrap_or_else(|| {
            dir.file_name()
                .map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into())
        }),
    };
    dataset::write_atomic(&page, gap::render_html(&d, &title).as_bytes())
        .with_context(|| format!("writing {}", page.display()))?;
    println!("{} ({}) -> {}", d.verdict, title, page.display());
    Ok(())
}

/// The title of a page `gap::render_html` wrote, unescaped; `None` for any other file.
fn page_title(page: &Path) -> Option<String> {
    const OPEN: &str = "<title>pgrd diagnosis: ";
    let s = std::fs::read_to_string(page).ok()?;
    let start = s.find(OPEN)? + OPEN.len();
    let end = start + s[start..].find("</title>")?;
    Some(
        s[start..end]
            .replace("&lt;", "<")
            .replace("&gt;", ">")
            .replace("&amp;", "&"),
    )
}

/// Writes `<out>/report.json` and `<out>/report.html`.
pub fn write_report(out: &Path, diagnosis: &Diagnosis, title: &str) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    write_json(&out.join("report.json"), diagnosis)?;
    let html = gap::render_html(diagnosis, title);
    dataset::write_atomic(&out.join("report.html"), html.as_bytes())
        .with_context(|| format!("writing {}", out.join("report.html").display()))
}

/// One line on a diagnosis's network comparison ([`gap::Learnable`]).
pub(crate) fn learnable_line(l: &gap::Learnable) -> String {
    format!(
        "residual network: held-out MDE {:.3} cm (its backbone {:.3} cm); against {}: {:+.1}% [{:+.1}, {:+.1}]{}",
        l.network_mde_cm,
        l.backbone_mde_cm,
        l.model,
        100.0 * l.vs_model.shrinkage,
        100.0 * l.vs_model.ci95[0],
        100.0 * l.vs_model.ci95[1],
        if l.changed_verdict {
            " -> verdict unknown"
        } else {
            ""
        }
    )
}

/// Per held-out episode, the MDE (cm, mean over steps) of the backbone with the network and of
/// the backbone alone. An episode whose hybrid rollout fails gets the backbone's error (with a
/// warning), so a failure cannot make the network look better.
pub(crate) fn network_errors(
    data: &Dataset,
    protocol: Protocol,
    backbone: &BackboneFile,
    options: &residual::BackboneOptionsFn,
    net: &residual::ResidualNet,
) -> anyhow::Result<(Vec<f64>, Vec<f64>)> {
    use rayon::prelude::*;
    // The network was trained on the run's backbone, under the run's integrator.
    let params = &backbone.params;
    let val = load_scenes(
        data,
        Split::Val,
        protocol,
        &backbone.setting().scene_config(data)?,
    )?;
    let mde = |scene: &Scene, pred: &[Vec<glam::Vec3>]| -> anyhow::Result<f64> {
        let e = scene::score_steps(scene, pred, false)?;
        // An episode the tracker saw nothing of scores 0 for both models.
        let (sum, n) = scene::sum_over_steps(&e, |x| x.mde);
        Ok(100.0 * sum / n.max(1) as f64)
    };
    let rows: Vec<anyhow::Result<(f64, f64)>> = val
        .par_iter()
        .map(|(i, scene)| {
            let alone = mde(scene, &predict_tracked(scene, params, options, None, None, NetworkPath::ForwardOnly)?)?;
            let history = residual::History::from_episode(scene, &data.load_episode(*i)?, data.meta.fps)?;
            let with = match predict_tracked(scene, params, options, Some(net), Some(&history), NetworkPath::ForwardOnly) {
                Ok(p) => mde(scene, &p)?,
                Err(e) => {
                    eprintln!("warning: episode {i}: the hybrid rollout failed ({e:#}); scored as its backbone");
                    alone
                }
            };
            Ok((with, alone))
        })
        .collect();
    let rows = rows.into_iter().collect::<anyhow::Result<Vec<_>>>()?;
    Ok(rows.into_iter().unzip())
}

/// `--write-run` must not replace the diagnosed run's own backbone, nor put a backbone under a
/// network trained on another one; checked before the diagnosis runs.
pub(crate) fn check_write_run(dir: &Path, run: &Path) -> anyhow::Result<()> {
    anyhow::ensure!(
        !crate::common::same_directory(dir, run),
        "--write-run {} is the diagnosed run itself; name a new directory",
        dir.display()
    );
    let net = dir.join("residual.safetensors");
    anyhow::ensure!(
        !net.exists(),
        "--write-run {}: it holds a residual network trained on another backbone ({}); name a new directory",
        dir.display(),
        net.display()
    );
    Ok(())
}

/// The race a budget chooses (the bench's measured setting, `docs/gap.md`).
const BUDGET_RACE: usize = 3;

/// The size of every refit of a diagnosis: generations, training episodes sampled per
/// generation, and most training episodes of the final rescoring.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Refits {
    generations: usize,
    samples: usize,
    rescore_scenes: usize,
}

/// A user's diagnosis when nothing is given.
const DEFAULT_REFITS: Refits = Refits {
    generations: 10,
    samples: 8,
    rescore_scenes: 64,
};

/// `diagnose-bench`'s default refit size: 8 generations of 6 episodes, rescored on all of its
/// 16 training episodes. Its measured benches sampled and rescored so (6 episodes a
/// generation, 12–16 rescored) but mostly ran 16 generations, and fewer generations cost
/// verdicts there (`docs/gap-log.md`, "A larger refit budget"), hence the race before it.
const BENCH_REFITS: Refits = Refits {
    generations: 8,
    samples: 6,
    rescore_scenes: 16,
};

/// The budget's last resort, taken only when no other level fits: the bench's refit size
/// with 4 training episodes sampled per generation instead of 6 (a noisier generation for 28 %
/// fewer refit rollouts on a default-size dataset; its cost in bench verdicts: `docs/gap-log.md`,
/// "A margin and fewer samples in the budget").
const FEWER_SAMPLES: Refits = Refits {
    samples: 4,
    ..BENCH_REFITS
};

impl Refits {
    fn of(config: &DiagnoseConfig) -> Refits {
        Refits {
            generations: config.generations,
            samples: config.samples,
            rescore_scenes: config.rescore_scenes,
        }
    }

    fn apply(self, config: &DiagnoseConfig) -> DiagnoseConfig {
        DiagnoseConfig {
            generations: self.generations,
            samples: self.samples,
            rescore_scenes: self.rescore_scenes,
            ..config.clone()
        }
    }
}

/// One set of speed options a diagnosis can run with, and its estimated effort.
struct Level {
    refits: Refits,
    race: usize,
    substep: SubstepArg,
    probe_factor: usize,
    effort: gap::Effort,
}

impl Level {
    /// The flags that turn `given` (the first level) into this one.
    fn options(&self, given: &Level) -> String {
        let mut out = Vec::new();
        if self.refits != given.refits {
            out.push(format!(
                "--generations {} --samples {} --rescore-scenes {}",
                self.refits.generations, self.refits.samples, self.refits.rescore_scenes
            ));
        }
        if self.race != given.race {
            out.push(format!("--race {}", self.race));
        }
        if self.probe_factor != given.probe_factor {
            out.push(format!("--probe-factor {}", self.probe_factor));
        }
        if self.substep != given.substep {
            out.push(format!("--substep {}", self.substep.name()));
        }
        out.join(" ")
    }
}

/// The options as given first, then each level adding one more of what the user left open, in
/// the order of their measured cost in verdicts (`docs/gap.md`, "Time budget"): the race
/// (when neither `--race` nor `--substep` was given; it changed 2 of 106 bench verdicts), the
/// probe at the other refits' length (when `--probe-factor` was not given and the default's
/// is above 1; it costs `unknown` verdicts, `docs/gap-log.md`, "A longer refit for the probe"), the
/// bench's default refit size (when none of `--generations`, `--samples`, `--rescore-scenes`
/// was given; fewer generations cost bench verdicts), the spectral substep (with the race,
/// when the run's rule is `auto`; it cost verdicts on two of three bench seeds), then, when the
/// refit size was left open too, 4 episodes sampled per generation instead of 6
/// ([`FEWER_SAMPLES`]). Usually each is faster than the one before.
fn effort_levels(
    args: &DiagnoseArgs,
    run_substep: SubstepArg,
    train: &[Scene],
    val: &[Scene],
    params: &springs::SpringParams,
    config: &DiagnoseConfig,
) -> anyhow::Result<Vec<Level>> {
    let (mut refits, mut race, mut substep, mut probe) = (
        Refits::of(config),
        config.race,
        args.substep.unwrap_or(run_substep),
        config.probe_factor,
    );
    let mut options = vec![(refits, race, substep, probe)];
    let speed_open = args.race.is_none() && args.substep.is_none();
    let refits_open =
        args.generations.is_none() && args.samples.is_none() && args.rescore_scenes.is_none();
    if speed_open {
        race = BUDGET_RACE;
        options.push((refits, race, substep, probe));
    }
    if args.probe_factor.is_none() && config.probe && probe > 1 {
        probe = 1;
        options.push((refits, race, substep, probe));
    }
    if refits_open && refits != BENCH_REFITS {
        refits = BENCH_REFITS;
        options.push((refits, race, substep, probe));
    }
    if speed_open && run_substep == SubstepArg::Auto {
        substep = SubstepArg::Spectral;
        options.push((refits, race, substep, probe));
    }
    if refits_open && refits.samples > FEWER_SAMPLES.samples {
        refits = FEWER_SAMPLES;
        options.push((refits, race, substep, probe));
    }
    options
        .into_iter()
        .map(|(refits, race, substep, probe_factor)| {
            let cfg = DiagnoseConfig {
                race,
                probe_factor,
                ..refits.apply(config)
            };
            Ok(Level {
                refits,
                race,
                substep,
                probe_factor,
                effort: gap::effort(train, val, params, &cfg, substep.substep())?,
            })
        })
        .collect()
}

/// The first level whose estimate times `margin` ([`gap::ESTIMATE_MARGIN`] in use) is within
/// `budget_min` (when none is, the cheapest, the first of equals: on small settings a race can
/// cost more than it saves, and the spectral substep nothing where both rules sit at the
/// accuracy cap), with the record of the choice; `None` without a budget or a choice to make.
fn choose_level(
    budget_min: f64,
    margin: f64,
    levels: &[Level],
) -> Option<(usize, gap::BudgetChoice)> {
    // NaN counts as no budget.
    if budget_min.is_nan() || budget_min <= 0.0 || levels.len() < 2 {
        return None;
    }
    let budget_s = 60.0 * budget_min;
    let cost = |k: usize| levels[k].effort.estimated_s();
    let k = (0..levels.len())
        .find(|&k| cost(k) * margin <= budget_s)
        .unwrap_or_else(|| (1..levels.len()).fold(0, |b, k| if cost(k) < cost(b) { k } else { b }));
    Some((
        k,
        gap::BudgetChoice {
            budget_s,
            margin,
            full_estimated_s: levels[0].effort.estimated_s(),
            estimated_s: levels[k].effort.estimated_s(),
            options: levels[k].options(&levels[0]),
        },
    ))
}

/// What `diagnose` and `diagnose --estimate` start from: the dataset, the run, both splits
/// under the rule asked for (else the run's own), the settings and the levels of effort.
struct Setup {
    data: Dataset,
    backbone: BackboneFile,
    protocol: Protocol,
    substep: SubstepArg,
    train: Vec<Scene>,
    val: Vec<Scene>,
    config: DiagnoseConfig,
    levels: Vec<Level>,
}

fn setup(args: &DiagnoseArgs) -> anyhow::Result<Setup> {
    let data = Dataset::open(&args.data)?;
    let backbone = read_backbone(&args.run)?;
    backbone.note_other_object(&data);
    let protocol: Protocol = args.protocol.into();
    let substep = args.substep.unwrap_or(backbone.substep);
    let setting = |substep| SceneSetting {
        substep,
        ..backbone.setting()
    };
    let train = scenes(&data, Split::Train, protocol, setting(substep))?;
    let val = scenes(&data, Split::Val, protocol, setting(substep))?;
    let mut config = config_from(args, &backbone.effects)?;
    let along_chain = [Candidate::BendingDamping, Candidate::Twist];
    if let Some(c) = along_chain.iter().find(|c| config.candidates.contains(c))
        && data.meta.structure != dataset::Structure::Chain
    {
        anyhow::bail!(
            "--candidates: {} acts along a cable's order and needs a `chain` dataset (e.g. \
             `xtask import deform`); {} is not one",
            c.name(),
            args.data.display()
        );
    }
    if config.candidates.contains(&Candidate::StiffnessLag) && gap::grasp_lag(&train).is_none() {
        anyhow::bail!(
            "--candidates: stiffness-lag needs a grasp lag, and every tracked point of {}'s \
             training episodes keeps the same distance from where the grippers' motion would \
             carry it",
            args.data.display()
        );
    }
    // A refined stiffness field stays at its values in every model; the refits move the
    // global stiffness it multiplies.
    config.field = backbone.refined.as_ref().map(|r| r.log_factor.clone());
    let levels = effort_levels(
        args,
        backbone.substep,
        &train,
        &val,
        &backbone.params,
        &config,
    )?;
    Ok(Setup {
        data,
        backbone,
        protocol,
        substep,
        train,
        val,
        config,
        levels,
    })
}

/// `diagnose --estimate`: the estimated time of each level, nothing run.
pub fn estimate(args: &DiagnoseArgs) -> anyhow::Result<()> {
    let Setup {
        data,
        train,
        val,
        levels,
        ..
    } = setup(args)?;
    let chosen = choose_level(args.budget_min, gap::ESTIMATE_MARGIN, &levels).map(|(k, _)| k);
    println!(
        "estimated diagnosis time of {} on the reference 2-core host ({} training, {} held-out episodes; a budget counts each estimate x{:.2}, the largest overrun measured):",
        data.meta.object,
        train.len(),
        val.len(),
        gap::ESTIMATE_MARGIN
    );
    for (k, l) in levels.iter().enumerate() {
        let options = l.options(&levels[0]);
        println!(
            "  {:>6.0} s  {}: {} refit, {} held-out and {} signature rollouts, {:.0} substeps per step, {:.0} springs, {:.0} particles{}",
            l.effort.estimated_s(),
            if options.is_empty() {
                "as given"
            } else {
                &options
            },
            l.effort.refit_rollouts,
            l.effort.heldout_rollouts,
            l.effort.signature_rollouts,
            l.effort.substeps,
            l.effort.springs,
            l.effort.particles,
            if chosen == Some(k) {
                format!(" <- chosen by the {} min budget", args.budget_min)
            } else {
                String::new()
            }
        );
    }
    Ok(())
}

/// Runs `diagnose`.
pub fn run(args: &DiagnoseArgs) -> anyhow::Result<Diagnosis> {
    let out = args
        .out
        .as_deref()
        .context("--out names the report directory")?;
    let t0 = Instant::now();
    if let Some(dir) = &args.write_run {
        check_write_run(dir, &args.run)?;
    }
    if let Some(dir) = &args.write_runner_up {
        check_write_run(dir, &args.run)?;
        anyhow::ensure!(
            args.write_run.as_ref() != Some(dir),
            "--write-runner-up names the --write-run directory; name another"
        );
    }
    let Setup {
        data,
        backbone,
        protocol,
        mut substep,
        mut train,
        mut val,
        mut config,
        levels,
    } = setup(args)?;
    let quiet = args.quiet;
    let budget = choose_level(args.budget_min, gap::ESTIMATE_MARGIN, &levels);
    if let Some((k, choice)) = &budget {
        let chosen = &levels[*k];
        if !quiet {
            println!(
                "  budget {:.0} s, each estimate counted x{:.2} (the largest measured overrun): estimated {:.0} s as given{}",
                choice.budget_s,
                choice.margin,
                choice.full_estimated_s,
                if choice.options.is_empty() {
                    String::new()
                } else {
                    format!(
                        ", {:.0} s with {} (chosen; --budget-min 0 for the whole diagnosis)",
                        choice.estimated_s, choice.options
                    )
                }
            );
            if choice.estimated_s * choice.margin > choice.budget_s {
                println!(
                    "  note: no option fits the budget; fewer --generations or --samples, or \
                     fewer --candidates, would shorten it further"
                );
            }
        }
        config = DiagnoseConfig {
            race: chosen.race,
            probe_factor: chosen.probe_factor,
            ..chosen.refits.apply(&config)
        };
        if chosen.substep != substep {
            substep = chosen.substep;
            let setting = SceneSetting {
                substep,
                ..backbone.setting()
            };
            train = scenes(&data, Split::Train, protocol, setting)?;
            val = scenes(&data, Split::Val, protocol, setting)?;
        }
    }
    if !quiet {
        println!("  substep rule: {}", substep.name());
    }
    let d = gap::diagnose(&train, &val, &backbone.params, &config, &mut |line| {
        if !quiet {
            println!("  {line}");
        }
    })?;
    let mut d = d;
    d.budget = budget.map(|(_, choice)| choice);
    if !args.no_network
        && let Some(net) = read_residual(&args.run)?
    {
        let options = backbone.options_for(&data, protocol)?;
        let (network, backbone_alone) = network_errors(&data, protocol, &backbone, &options, &net)?;
        gap::add_learnable(&mut d, &network, &backbone_alone)?;
        if let Some(l) = &d.learnable {
            println!("  {}", learnable_line(l));
        }
    }
    let title = format!("{} ({})", data.meta.object, args.data.display());
    write_report(out, &d, &title)?;
    let how = d.how_far.as_ref().map_or(String::new(), |h| {
        // With `none` / `unknown` this is the best library candidate, which the verdict did
        // not take: say so, or the line reads as if the effect were added.
        let what = if h.effect == d.verdict {
            "adding"
        } else {
            "best candidate, not the verdict,"
        };
        format!(
            "; {what} {}: held-out MDE {:.3} -> {:.3} cm ({:.1}% shrinkage)",
            h.effect,
            h.before.mde_cm,
            h.after.mde_cm,
            100.0 * h.shrinkage_mde
        )
    });
    println!(
        "diagnosis of {}: verdict {}{} ({:.1} s) -> {}",
        data.meta.object,
        d.verdict,
        how,
        t0.elapsed().as_secs_f64(),
        out.join("report.html").display()
    );
    if let Some(c) = d.carry_over_caution() {
        println!("caution: {c}");
    }
    // The user's next step: diagnose again with the verdict's effect in the model. With the
    // verdict `none` / `unknown` there is no effect to add, but the control refit (the same
    // model refitted on the train split) may still beat the model as given: `--write-run`
    // writes the better of the two on the held-out episodes, with both scores.
    let added = effect_to_add(&d, args.add_past_unknown)?;
    if args.add_past_unknown && d.verdict == "unknown" {
        println!(
            "verdict unknown; the library's refits alone: {}",
            added.map_or("none".to_string(), |c| format!(
                "{} (added, --add-past-unknown)",
                c.name()
            ))
        );
    }
    if added.is_some() {
        let (_, effects) = d.refitted_model(&backbone.params, added)?;
        let list: Vec<String> = effects.iter().map(BaseEffect::label).collect();
        println!(
            "to diagnose the model with it: --with {} (values refitted here)",
            list.join(",")
        );
    }
    if let Some(dir) = &args.write_run {
        let file = write_model(dir, &backbone, &d, added, protocol, substep)?;
        if added.is_some() {
            println!(
                "wrote {} ({}, refitted here)",
                backbone_path(dir).display(),
                file.label()
            );
        } else {
            println!(
                "verdict {}: no effect to add; wrote the {} to {} ({}; held-out MDE: control refit {:.3} cm, as given {:.3} cm)",
                d.verdict,
                if !control_is_better(&d) {
                    "model as given"
                } else {
                    "control refit"
                },
                backbone_path(dir).display(),
                file.label(),
                d.control.heldout_mde_cm,
                d.backbone_as_given.mde_cm
            );
        }
        if file.substep != backbone.substep {
            println!(
                "note: the run is written with the {} substep rule (the run diagnosed used {}): \
                 its parameters were refitted under it",
                substep.name(),
                backbone.substep.name()
            );
        }
    }
    if let Some(dir) = &args.write_runner_up
        && let Some(other) = added.and_then(|a| runner_up(&d, a))
    {
        let file = write_model(dir, &backbone, &d, Some(other), protocol, substep)?;
        println!(
            "runner-up: {} was tied with {}; wrote {} ({}, refitted here)",
            other.name(),
            added.map_or("", |a| a.name()),
            backbone_path(dir).display(),
            file.label()
        );
    }
    Ok(d)
}

/// Writes `<dir>/backbone.json`: the diagnosed model with `added` at the values this
/// diagnosis refitted, or with no effect to add the better on the held-out episodes of the
/// control refit and the model as given. Returns what it wrote.
fn write_model(
    dir: &Path,
    backbone: &BackboneFile,
    d: &Diagnosis,
    added: Option<Candidate>,
    protocol: Protocol,
    substep: SubstepArg,
) -> anyhow::Result<BackboneFile> {
    let mut file = backbone.clone();
    // No effect to add and the control refit no better on the held-out episodes than the
    // model as given (session 59: two refined cables): carry the model on as given.
    let as_given = added.is_none() && !control_is_better(d);
    if !as_given {
        let (params, effects) = d.refitted_model(&backbone.params, added)?;
        file.params = params;
        file.effects = effects;
        // The refits' damping suits the rule they ran under, so the run keeps it; a model
        // carried on as given keeps its own.
        file.substep = substep;
    }
    file.protocol = protocol.name().to_string();
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    write_json(&backbone_path(dir), &file)?;
    Ok(file)
}

/// The candidate tied with `added` (significant, not separable from it on the held-out
/// episodes: the report's `tie_break`) that has the largest shrinkage among the others, if
/// `added` was one of a tie.
pub(crate) fn runner_up(d: &Diagnosis, added: Candidate) -> Option<Candidate> {
    let tie = d.tie_break.as_ref()?;
    if !tie.tied.iter().any(|t| t == added.name()) {
        return None;
    }
    // The ranking runs from the largest shrinkage down.
    d.ranking
        .iter()
        .filter(|r| r.effect != added.name() && tie.tied.contains(&r.effect))
        .find_map(|r| Candidate::parse(&r.effect).ok())
}

/// The effect `--write-run` adds to the model: the verdict's, or with `add_past_unknown` the
/// library's own verdict behind an `unknown` ([`Diagnosis::library_verdict`]); `None` when the
/// verdict adds none.
pub(crate) fn effect_to_add(
    d: &Diagnosis,
    add_past_unknown: bool,
) -> anyhow::Result<Option<Candidate>> {
    if let Ok(c) = Candidate::parse(&d.verdict) {
        return Ok(Some(c));
    }
    if add_past_unknown && d.verdict == "unknown" {
        return Ok(Candidate::parse(&d.library_verdict()?).ok());
    }
    Ok(None)
}

/// Whether the control refit (the model's own effects refitted on the train split, none
/// added) predicts the held-out episodes better than the model as given: what `--write-run`
/// carries on with when the verdict adds no effect.
pub(crate) fn control_is_better(d: &gap::Diagnosis) -> bool {
    d.control.heldout_mde_cm < d.backbone_as_given.mde_cm
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn candidates_are_named_or_added_to_the_library() {
        let named = parse_candidates("drag, bending").unwrap();
        assert_eq!(named, vec![Candidate::Drag, Candidate::Bending]);
        let added = parse_candidates("+gravity-scale").unwrap();
        assert_eq!(added.len(), Candidate::LIBRARY.len() + 1);
        assert_eq!(added.last(), Some(&Candidate::GravityScale));
        let both = parse_candidates("+gravity-scale, +bending-damping").unwrap();
        assert_eq!(
            both[Candidate::LIBRARY.len()..],
            [Candidate::GravityScale, Candidate::BendingDamping]
        );
        // Adding one already there changes nothing.
        assert_eq!(
            parse_candidates("+drag").unwrap(),
            Candidate::LIBRARY.to_vec()
        );
        assert!(parse_candidates("drag,+bending").is_err());
        assert!(parse_candidates("+gravity").is_err());
    }

    /// A level whose estimate is `seconds`.
    fn level(race: usize, substep: SubstepArg, seconds: f64) -> Level {
        Level {
            refits: DEFAULT_REFITS,
            race,
            substep,
            probe_factor: 1,
            effort: gap::Effort {
                refit_rollouts: 1000,
                heldout_rollouts: 0,
                signature_rollouts: 0,
                work_per_rollout: seconds / (1000.0 * gap::SECONDS_PER_WORK),
                substeps: 1.0,
                springs: 1.0,
                particles: 1.0,
            },
        }
    }

    #[test]
    fn the_budget_takes_the_first_level_within_it_and_the_cheapest_when_none_is() {
        let levels = [
            level(0, SubstepArg::Auto, 320.0),
            level(3, SubstepArg::Auto, 160.0),
            level(3, SubstepArg::Spectral, 80.0),
        ];
        let pick = |minutes: f64| choose_level(minutes, 1.0, &levels).map(|(k, c)| (k, c.options));
        assert_eq!(pick(10.0), Some((0, String::new())));
        assert_eq!(pick(3.0), Some((1, "--race 3".to_string())));
        assert_eq!(
            pick(2.0),
            Some((2, "--race 3 --substep spectral".to_string()))
        );
        assert_eq!(
            pick(0.5),
            Some((2, "--race 3 --substep spectral".to_string()))
        );
        // Over budget everywhere, a level dearer than an earlier one is not taken, and of
        // equals the first (fewer options) is.
        let odd = [
            level(0, SubstepArg::Auto, 320.0),
            level(3, SubstepArg::Auto, 640.0),
            level(3, SubstepArg::Spectral, 320.0),
        ];
        assert_eq!(choose_level(1.0, 1.0, &odd).map(|(k, _)| k), Some(0));
        let flat = [
            level(0, SubstepArg::Auto, 320.0),
            level(3, SubstepArg::Auto, 160.0),
            level(3, SubstepArg::Spectral, 160.0),
        ];
        assert_eq!(choose_level(1.0, 1.0, &flat).map(|(k, _)| k), Some(1));
        let (_, c) = choose_level(2.0, 1.0, &levels).unwrap();
        assert!((c.full_estimated_s - 320.0).abs() < 1e-6 && (c.estimated_s - 80.0).abs() < 1e-6);
        // No budget, or nothing to choose between (options given): no choice.
        assert!(choose_level(0.0, 1.0, &levels).is_none());
        assert!(choose_level(f64::NAN, 1.0, &levels).is_none());
        assert!(choose_level(1.0, 1.0, &levels[..1]).is_none());
        // With a margin each estimate counts that many times against the budget: 320 s
        // fits 6 minutes bare, not with 1.32, and the record says what was counted.
        assert_eq!(pick(6.0), Some((0, String::new())));
        let (k, c) = choose_level(6.0, 1.32, &levels).unwrap();
        assert_eq!((k, c.margin), (1, 1.32));
        assert!((c.estimated_s - 160.0).abs() < 1e-6);
        // A smaller refit size is named by all three of its flags.
        let smaller = Level {
            refits: BENCH_REFITS,
            ..level(3, SubstepArg::Spectral, 40.0)
        };
        assert_eq!(
            smaller.options(&levels[0]),
            "--generations 8 --samples 6 --rescore-scenes 16 --race 3 --substep spectral"
        );
        let short_probe = Level {
            probe_factor: 1,
            ..level(3, SubstepArg::Auto, 120.0)
        };
        let long_probe = Level {
            probe_factor: 4,
            ..level(0, SubstepArg::Auto, 400.0)
        };
        assert_eq!(
            short_probe.options(&long_probe),
            "--race 3 --probe-factor 1"
        );
    }

    #[derive(clap::Parser)]
    struct Diag {
        #[command(flatten)]
        args: DiagnoseArgs,
    }

    #[test]
    fn a_tight_budget_races_the_refits_and_the_report_says_so() {
        let dir = std::env::temp_dir().join(format!("pgrd-budget-{}", std::process::id()));
        let data = crate::cmd_fit::FIXTURE_ROPE;
        let fit = crate::cmd_fit::FitArgs::quick_rope_fixture(dir.join("run"));
        crate::cmd_fit::run(&fit).unwrap();
        // The ladder a budget climbs: the bench's refit size, and last its fewer samples, only
        // when the user left all three of their flags open, the race and the spectral substep
        // only when both of theirs are, the probe's usual length when its factor is open.
        let ladder = |extra: &[&str]| -> Vec<(String, f64)> {
            let run = dir.join("run");
            let run = run.to_str().unwrap();
            let mut argv = vec!["diagnose", "--estimate", "--data", data, "--run", run];
            argv.extend(extra);
            let args = <Diag as clap::Parser>::try_parse_from(argv).unwrap().args;
            let levels = setup(&args).unwrap().levels;
            levels
                .iter()
                .map(|l| (l.options(&levels[0]), l.effort.estimated_s()))
                .collect()
        };
        let open = ladder(&[]);
        let names: Vec<&str> = open.iter().map(|(o, _)| o.as_str()).collect();
        assert_eq!(
            names,
            [
                "",
                "--race 3",
                "--race 3 --probe-factor 1",
                "--generations 8 --samples 6 --rescore-scenes 16 --race 3 --probe-factor 1",
                "--generations 8 --samples 6 --rescore-scenes 16 --race 3 --probe-factor 1 --substep spectral",
                "--generations 8 --samples 4 --rescore-scenes 16 --race 3 --probe-factor 1 --substep spectral",
            ]
        );
        assert!(open[2].1 < open[1].1 && open[3].1 < open[2].1, "{open:?}");
        // The fixture's three training episodes are fewer than either sample size, so the
        // last rung saves nothing here (the choice then keeps the earlier level of equals).
        assert!(open[5].1 <= open[4].1, "{open:?}");
        let sized = ladder(&["--samples", "8"]);
        let names: Vec<&str> = sized.iter().map(|(o, _)| o.as_str()).collect();
        assert_eq!(
            names,
            [
                "",
                "--race 3",
                "--race 3 --probe-factor 1",
                "--race 3 --probe-factor 1 --substep spectral"
            ]
        );
        let raced = ladder(&["--race", "2", "--probe-factor", "4"]);
        let names: Vec<&str> = raced.iter().map(|(o, _)| o.as_str()).collect();
        assert_eq!(
            names,
            [
                "",
                "--generations 8 --samples 6 --rescore-scenes 16",
                "--generations 8 --samples 4 --rescore-scenes 16",
            ]
        );
        assert_eq!(ladder(&["--race", "2", "--generations", "10"]).len(), 2);
        assert_eq!(
            ladder(&["--race", "2", "--generations", "10", "--probe-factor", "4"]).len(),
            1
        );
        let diagnose = |out: &str, extra: &[&str]| -> Diagnosis {
            let out = dir.join(out);
            let mut argv: Vec<String> = [
                "diagnose",
                "--data",
                data,
                "--run",
                dir.join("run").to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--population",
                "4",
                "--generations",
                "4",
                "--samples",
                "2",
                "--resamples",
                "50",
                "--candidates",
                "drag,bending,actuation-delay,friction,plasticity,grasp-slip",
                "--no-network",
                "--quiet",
            ]
            .iter()
            .map(|s| s.to_string())
            .collect();
            argv.extend(extra.iter().map(|s| s.to_string()));
            let args = <Diag as clap::Parser>::try_parse_from(argv).unwrap().args;
            estimate(&args).unwrap();
            run(&args).unwrap();
            let text = std::fs::read_to_string(out.join("report.json")).unwrap();
            serde_json::from_str(&text).unwrap()
        };
        // A budget no diagnosis meets: the cheapest level, recorded. On this soft rope both
        // substep rules sit at the 2 ms accuracy cap, so the spectral one saves nothing and
        // is not taken.
        let tight = diagnose("tight", &["--budget-min", "1e-9"]);
        let b = tight
            .budget
            .as_ref()
            .expect("the budget's choice is recorded");
        assert_eq!(b.options, "--race 3 --probe-factor 1");
        assert!(b.estimated_s < b.full_estimated_s, "{b:?}");
        assert_eq!(tight.config.race, 3);
        assert_eq!(tight.config.probe_factor, 1);
        assert_eq!(tight.substep, Some(springs::Substep::AUTO));
        assert_eq!(tight.ranking.iter().filter(|r| r.raced_out).count(), 3);
        // At the stiffness bound the spectral substep is the cheaper rule: the scenes are
        // rebuilt under it.
        let path = backbone_path(&dir.join("run"));
        let mut file = read_backbone(&dir.join("run")).unwrap();
        file.params.stiffness = 5e4;
        write_json(&path, &file).unwrap();
        let written = dir.join("written");
        let stiff = diagnose(
            "stiff",
            &[
                "--budget-min",
                "1e-9",
                "--write-run",
                written.to_str().unwrap(),
            ],
        );
        // The run it writes keeps the rule its parameters were refitted under.
        assert_eq!(
            read_backbone(&written).unwrap().substep,
            SubstepArg::Spectral
        );
        assert_eq!(
            stiff.budget.as_ref().unwrap().options,
            "--race 3 --probe-factor 1 --substep spectral"
        );
        assert_eq!(stiff.substep, Some(springs::Substep::SPECTRAL));
        let page = std::fs::read_to_string(dir.join("stiff").join("report.html")).unwrap();
        assert!(page.contains("<code>--race 3 --probe-factor 1 --substep spectral</code>"));
        // The margin is recorded and named on the page.
        assert_eq!(stiff.budget.as_ref().unwrap().margin, gap::ESTIMATE_MARGIN);
        assert!(page.contains(&format!("counted {:.2} times", gap::ESTIMATE_MARGIN)));
        assert_eq!(stiff.config.race, 3);
        // Options given on the command line are not overruled, and nothing is recorded.
        let given = diagnose(
            "given",
            &["--budget-min", "1e-9", "--race", "0", "--probe-factor", "4"],
        );
        assert!(given.budget.is_none());
        assert_eq!(given.config.race, 0);
        assert_eq!(given.config.probe_factor, 4);
        assert_eq!(given.substep, Some(springs::Substep::AUTO));
        // The fixture is far within the default budget: the whole diagnosis, the check recorded.
        let roomy = diagnose("roomy", &[]);
        assert_eq!(roomy.budget.as_ref().unwrap().options, "");
        assert_eq!(roomy.config.race, 0);
        let page = std::fs::read_to_string(dir.join("roomy").join("report.html")).unwrap();
        assert!(!page.contains("Time budget"));
        // `report-page` writes the page again from report.json, keeping its title.
        let stiff_dir = dir.join("stiff");
        let old = std::fs::read_to_string(stiff_dir.join("report.html")).unwrap();
        std::fs::write(
            stiff_dir.join("report.html"),
            old.replace("Time budget", "x"),
        )
        .unwrap();
        let again = ReportPageArgs {
            dirs: vec![stiff_dir.clone()],
            title: None,
        };
        report_page(&again).unwrap();
        assert_eq!(
            std::fs::read_to_string(stiff_dir.join("report.html")).unwrap(),
            old
        );
        // Not a report: an error, and the page is left alone.
        std::fs::write(stiff_dir.join("report.json"), "{\"verdict\": 1}").unwrap();
        let err = report_page(&again).unwrap_err();
        assert!(
            format!("{err:#}").contains("is not a diagnosis report"),
            "{err:#}"
        );
        assert_eq!(
            std::fs::read_to_string(stiff_dir.join("report.html")).unwrap(),
            old
        );
        std::fs::remove_dir_all(&dir).ok();
    }

    /// With no effect to add, `--write-run` carries on with the better on the held-out
    /// episodes of the control refit and the model as given: a model made worse is refitted,
    /// and a one-generation refit does not replace the refit that beats it.
    #[test]
    fn write_run_keeps_the_better_of_the_control_refit_and_the_model_as_given() {
        let dir = std::env::temp_dir().join(format!("pgrd-write-run-{}", std::process::id()));
        let data = crate::cmd_fit::FIXTURE_ROPE;
        let fit = crate::cmd_fit::FitArgs {
            population: 6,
            generations: 8,
            samples: 3,
            ..crate::cmd_fit::FitArgs::quick_rope_fixture(dir.join("fitted"))
        };
        crate::cmd_fit::run(&fit).unwrap();
        let fitted = read_backbone(&dir.join("fitted")).unwrap();
        let mut worse = fitted.clone();
        worse.params.stiffness *= 0.3;
        std::fs::create_dir_all(dir.join("worse")).unwrap();
        write_json(&backbone_path(&dir.join("worse")), &worse).unwrap();
        // The worse model refitted twice, then the written model diagnosed again with a
        // one-generation refit, until one refit loses to the model it started from (the
        // third round, with these seeds).
        let mut kept = Vec::new();
        let mut given_dir = dir.join("worse");
        for (round, generations) in ["8", "8", "1", "1"].into_iter().enumerate() {
            let out = dir.join(format!("out{round}"));
            let written = dir.join(format!("written{round}"));
            let argv = [
                "diagnose",
                "--data",
                data,
                "--run",
                given_dir.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--write-run",
                written.to_str().unwrap(),
                "--population",
                "4",
                "--generations",
                generations,
                "--samples",
                "2",
                "--resamples",
                "50",
                "--candidates",
                "drag",
                "--no-network",
                "--quiet",
            ];
            let args = <Diag as clap::Parser>::try_parse_from(argv).unwrap().args;
            let d = run_diagnosis(&args);
            assert!(Candidate::parse(&d.verdict).is_err(), "{}", d.verdict);
            let given = read_backbone(&given_dir).unwrap();
            let file = read_backbone(&written).unwrap();
            let as_given = file.params == given.params;
            assert_eq!(as_given, !control_is_better(&d), "round {round}");
            if as_given {
                assert_eq!(file.substep, given.substep);
                assert_eq!(file.effects.len(), given.effects.len());
            }
            if !as_given {
                assert_eq!(
                    file.params,
                    d.refitted_model(&given.params, None).unwrap().0
                );
            }
            kept.push(as_given);
            if as_given {
                break;
            }
            given_dir = written;
        }
        // Both branches ran: the worse model lost to its refit, and a later refit lost to
        // the model it started from.
        assert_eq!(kept.first(), Some(&false));
        assert_eq!(kept.last(), Some(&true), "{kept:?}");
        std::fs::remove_dir_all(&dir).ok();
    }

    /// Runs a diagnosis and reads back its report.
    fn run_diagnosis(args: &DiagnoseArgs) -> Diagnosis {
        run(args).unwrap();
        let out = args.out.as_ref().expect("the test names --out");
        let text = std::fs::read_to_string(out.join("report.json")).unwrap();
        serde_json::from_str(&text).unwrap()
    }
}
