//! Pieces the pipelines share: loading scenes of a split, the run directory's files, one
//! command's arguments parsed from a command line built in code.

use std::path::{Path, PathBuf};

use anyhow::Context;
use dataset::{Dataset, Split};
use scene::{Protocol, Scene, SceneConfig};
use serde::{Deserialize, Serialize};

/// `--protocol` on the command line.
#[derive(Clone, Copy, Debug, Default, clap::ValueEnum)]
pub enum ProtocolArg {
    /// Paper: 2 history frames, 37 predicted steps.
    #[default]
    Paper,
    /// DEFORM: start from frames 0-1, predict every remaining frame.
    Deform,
}

impl From<ProtocolArg> for Protocol {
    fn from(p: ProtocolArg) -> Self {
        match p {
            ProtocolArg::Paper => Protocol::Paper,
            ProtocolArg::Deform => Protocol::Deform,
        }
    }
}

/// `--substep` on the command line: how the simulator chooses its substep (docs/physics.md,
/// "Stability bound and substep choice" and "Spectral substep"). A run records the one it was
/// fitted under, and `eval`, `train`, `refine`, `render`, `diagnose` and `plan` use it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SubstepArg {
    /// Gershgorin's bound on the springs' stiffness: holds in every state where no spring is
    /// compressed below half its rest length.
    #[default]
    Auto,
    /// The largest eigenvalue of the springs' stiffness at rest (Lanczos), safety margin 0.9
    /// only: 1.6–1.9 times fewer substeps on the fitted paper, sloth, teddy and duster; none
    /// fewer on the rope and the flag, which already run at the 2 ms accuracy cap.
    Spectral,
}

/// How a run's scenes are built: its substep rule, whether its springs join material
/// neighbours only (`fit --material-springs`; docs/pipelines.md, "Material springs"), and the
/// controller rule its fit found (`fit --fit-controller`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SceneSetting {
    /// The simulator's substep rule.
    pub substep: SubstepArg,
    /// Springs only between tracked points that stay close across the training recordings.
    pub material_springs: bool,
    /// How an `attach` dataset's controller points join the object, instead of the rule its
    /// `dataset.json` declares (`None`: the dataset's).
    pub controller_springs: Option<dataset::ControllerSprings>,
}

impl From<SubstepArg> for SceneSetting {
    fn from(substep: SubstepArg) -> Self {
        SceneSetting {
            substep,
            ..SceneSetting::default()
        }
    }
}

impl SceneSetting {
    /// The scene settings: this substep, unseen start points placed by the material
    /// neighbours learned from `data`'s training split, and with material springs the pair
    /// table learned from the same split.
    pub fn scene_config(self, data: &Dataset) -> anyhow::Result<SceneConfig> {
        let config = SceneConfig {
            substep: self.substep.substep(),
            controller_springs: self.controller_springs,
            ..SceneConfig::default()
        };
        let config = config.with_neighbours_of(data).with_context(|| {
            format!(
                "learning the material neighbours of {}",
                data.root.display()
            )
        })?;
        if !self.material_springs {
            return Ok(config);
        }
        config
            .with_material_pairs_of(data)
            .with_context(|| format!("learning the material springs of {}", data.root.display()))
    }
}

impl SubstepArg {
    /// The simulator's substep rule.
    pub fn substep(self) -> springs::Substep {
        match self {
            SubstepArg::Auto => springs::Substep::AUTO,
            SubstepArg::Spectral => springs::Substep::SPECTRAL,
        }
    }

    /// The name used on the command line and in files.
    pub fn name(self) -> &'static str {
        match self {
            SubstepArg::Auto => "auto",
            SubstepArg::Spectral => "spectral",
        }
    }

    fn is_auto(&self) -> bool {
        *self == SubstepArg::Auto
    }
}

/// Loads every episode of `split` and builds its scene. Returns (episode index, scene) pairs.
pub fn load_scenes(
    data: &Dataset,
    split: Split,
    protocol: Protocol,
    config: &SceneConfig,
) -> anyhow::Result<Vec<(usize, Scene)>> {
    let indices = data.split_indices(split);
    anyhow::ensure!(
        !indices.is_empty(),
        "{} has no '{split}' episodes",
        data.root.display()
    );
    indices
        .into_iter()
        .map(|i| {
            let ep = data.load_episode(i)?;
            let name = || {
                let file = data.meta.episodes.get(i).map_or("?", |e| e.file.as_str());
                format!("episode {i} ({file}) of {}", data.root.display())
            };
            let window = protocol.window(ep.frames()).with_context(name)?;
            let scene = Scene::new(&data.meta, &ep, window, config).with_context(name)?;
            Ok((i, scene))
        })
        .collect()
}

/// The scenes of a split with the default scene settings and `setting` (a [`SubstepArg`] alone
/// builds the reference's springs), without their episode indices.
pub fn scenes(
    data: &Dataset,
    split: Split,
    protocol: Protocol,
    setting: impl Into<SceneSetting>,
) -> anyhow::Result<Vec<Scene>> {
    Ok(
        load_scenes(data, split, protocol, &setting.into().scene_config(data)?)?
            .into_iter()
            .map(|(_, s)| s)
            .collect(),
    )
}

/// The fitted backbone of a run: `<run>/backbone.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BackboneFile {
    /// Model name ("spring-mass").
    pub model: String,
    /// Dataset it was fitted on.
    pub dataset: String,
    /// Protocol of the training windows.
    pub protocol: String,
    /// The fitted parameters.
    pub params: springs::SpringParams,
    /// The fit's history and settings.
    pub fit: fit::FitOutcome,
    /// Fit settings.
    pub config: fit::FitConfig,
    /// Wall time of all generations, s (summed over resumed sessions).
    pub wall_s: f64,
    /// Wall time of the command that wrote this file (loading included), s.
    pub session_wall_s: f64,
    /// Library effects added to the spring-mass model, at fixed values (written by
    /// `diagnose --write-run` with the diagnosis's refitted parameters; empty for a plain fit).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub effects: Vec<gap::BaseEffect>,
    /// The per-particle stiffness field refined by `cargo xtask refine` (the paper's "Diff.
    /// Spring-Mass" baseline), with its history; absent for a plain fit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined: Option<fit::RefineOutcome>,
    /// The substep rule the parameters were fitted under (absent: `auto`); the damping and the
    /// effects' values are fitted for that integrator, so `eval` and `train` use it too.
    #[serde(default, skip_serializing_if = "SubstepArg::is_auto")]
    pub substep: SubstepArg,
    /// Springs join material neighbours only (`fit --material-springs`; absent: every pair
    /// within the radius, the reference's rule); every stage that builds this run's model
    /// uses the same rule.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub material_springs: bool,
    /// How the controller points of the `attach` dataset join the object, as `fit
    /// --fit-controller` found it (absent: the rule the dataset declares); every stage that
    /// builds this run's model uses it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub controller_springs: Option<dataset::ControllerSprings>,
    /// Each start of that search (`fit --controller-starts`): where it began, what it found
    /// and its loss over every training episode; the kept one has the lowest.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub controller_starts: Vec<fit::ControllerStart>,
}

impl BackboneFile {
    /// The object of the dataset this run was fitted on, when that dataset can still be read.
    pub fn fitted_object(&self) -> Option<String> {
        Dataset::open(&self.dataset).ok().map(|d| d.meta.object)
    }

    /// A note on stderr when `data` records another object than the dataset this run was
    /// fitted on (a rope's parameters scored on a teddy still run, but the numbers mean
    /// little); returns the note.
    pub fn note_other_object(&self, data: &Dataset) -> Option<String> {
        let fitted = self.fitted_object()?;
        (fitted != data.meta.object).then(|| {
            let note = format!(
                "note: this run was fitted on {fitted} data ({}), not on {} ({})",
                self.dataset,
                data.meta.object,
                data.root.display()
            );
            eprintln!("{note}");
            note
        })
    }

    /// How this run's scenes are built (substep rule, material springs, controller rule).
    pub fn setting(&self) -> SceneSetting {
        SceneSetting {
            substep: self.substep,
            material_springs: self.material_springs,
            controller_springs: self.controller_springs,
        }
    }

    /// The model's name in reports: `spring-mass`, or `spring-mass+drag+...` with effects;
    /// `diff-spring-mass` for a refined stiffness field.
    pub fn label(&self) -> String {
        let model = if self.refined.is_some() {
            "diff-spring-mass".to_string()
        } else {
            self.model.clone()
        };
        std::iter::once(model)
            .chain(self.effects.iter().map(|e| e.effect.name().to_string()))
            .collect::<Vec<_>>()
            .join("+")
    }

    /// Builds the backbone options of the run's effects for scenes of `data`. Effects that
    /// depend on where a particle lies on the object use the material frame of `data`'s train
    /// split under `protocol` (the frame the diagnosis fitted them in, when it ran on the same
    /// dataset and protocol).
    pub fn options_for(
        &self,
        data: &Dataset,
        protocol: Protocol,
    ) -> anyhow::Result<residual::BackboneOptionsFn> {
        let field = self
            .refined
            .as_ref()
            .map(|r| std::sync::Arc::new(r.log_factor.clone()));
        let with_field = move |mut options: springs::BackboneOptions| {
            if let Some(f) = &field {
                options.effects.push(Box::new(springs::StiffnessField {
                    log_factor: f.clone(),
                }));
            }
            options
        };
        if self.effects.is_empty() {
            return Ok(std::sync::Arc::new(move || {
                with_field(springs::BackboneOptions::default())
            }));
        }
        // The frame depends on the tracked positions only, not on the integrator.
        let train = scenes(data, Split::Train, protocol, SubstepArg::Auto)?;
        let frame = gap::material_frame(&train)?;
        let effects = self.effects.clone();
        Ok(std::sync::Arc::new(move || {
            with_field(gap::backbone_options(&effects, &frame))
        }))
    }
}

/// Prints a warning when free particles of `scene`'s backbone have no spring: they fall
/// freely, almost always because the threshold is below the particle spacing.
pub fn warn_if_unconnected(
    scene: &Scene,
    params: &springs::SpringParams,
    options: springs::BackboneOptions,
) -> anyhow::Result<springs::Backbone> {
    let bb = scene.backbone(params, &scene.sim_config(), options)?;
    let loose = bb.unconnected_free_particles();
    if loose > 0 {
        eprintln!(
            "warning: {loose} of {} free particles have no spring (threshold {} m is below \
             their spacing?); they fall freely",
            bb.held().iter().filter(|h| **h < 0).count(),
            params.threshold
        );
    }
    Ok(bb)
}

/// Writes `bb`'s spring graph at its rest shape (the scene's start frame) as a PLY with one
/// vertex per particle and one edge per spring, for a point-cloud viewer (MeshLab, CloudCompare,
/// Blender), and the same seen across its thinnest axis as an SVG beside it, for a browser:
/// where the threshold joined the object, where it glued touching parts, which particles hang
/// loose. Colours: held particles blue, free particles without a spring red,
/// the scene's added particles (hidden chain particles, volume fill) light grey, tracked ones
/// dark grey.
pub fn write_spring_graph(
    path: &Path,
    object: &str,
    scene: &Scene,
    bb: &springs::Backbone,
) -> anyhow::Result<()> {
    let connected = bb.connected_particles();
    let colors: Vec<[f32; 3]> = (0..bb.num_particles())
        .map(
            |i| match (bb.held()[i] >= 0, connected[i], i < scene.tracked) {
                (true, _, _) => [0.12, 0.47, 0.71],
                (false, false, _) => [0.84, 0.15, 0.16],
                (false, true, true) => [0.3, 0.3, 0.3],
                (false, true, false) => [0.7, 0.7, 0.7],
            },
        )
        .collect();
    crate::report::write_ply_edges(path, bb.rest_positions(), Some(&colors), bb.springs())?;
    crate::plots::springs_svg(
        &path.with_extension("svg"),
        object,
        bb.rest_positions(),
        bb.springs(),
        &colors,
    )
}

/// Prints a note when the reference construction glues parts together: some of `scenes` (the
/// training split's) start with springs between tracked points whose mean distance over the
/// training recordings is beyond [`scene::MATERIAL_PAIR_FACTOR`] times the threshold, as happens
/// when episodes are cut from longer recordings where the object lies across itself
/// (docs/pipelines.md, "Material springs"). Silent when there is nothing to say or the table
/// cannot be learned (too many points, particle counts that disagree).
pub fn note_glued_springs(
    data: &Dataset,
    scenes: &[Scene],
    params: &springs::SpringParams,
) -> anyhow::Result<()> {
    use rayon::prelude::*;
    let episodes = data
        .split_indices(Split::Train)
        .into_iter()
        .map(|i| data.load_episode(i))
        .collect::<Result<Vec<_>, _>>()?;
    let Some(pairs) = dataset::MaterialPairs::learn(&episodes) else {
        return Ok(());
    };
    let counts: Vec<usize> = scenes
        .par_iter()
        .map(|s| s.glued_springs(params, &pairs))
        .collect::<Result<_, _>>()?;
    let glued = counts.iter().filter(|&&c| c > 0).count();
    if glued > 0 {
        println!(
            "note: {glued} of {} training episodes start with springs between points that lie \
             more than {} m apart on average over the training recordings ({} springs): parts \
             touching at an episode's first frame are glued for its whole rollout; \
             `--material-springs` joins material neighbours only (docs/pipelines.md, \
             \"Material springs\")",
            scenes.len(),
            (scene::MATERIAL_PAIR_FACTOR * params.threshold * 1000.0).round() / 1000.0,
            counts.iter().sum::<usize>()
        );
    }
    Ok(())
}

/// Path of the backbone file in a run directory.
pub fn backbone_path(run: &Path) -> PathBuf {
    run.join("backbone.json")
}

/// Reads `<run>/backbone.json`.
pub fn read_backbone(run: &Path) -> anyhow::Result<BackboneFile> {
    let path = backbone_path(run);
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("reading {} (run `cargo xtask fit` first)", path.display()))?;
    let file: BackboneFile =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    anyhow::ensure!(
        file.model == "spring-mass",
        "{}: model '{}'; this pgrd reads spring-mass runs only",
        path.display(),
        file.model
    );
    Ok(file)
}

/// The run's residual network, `<run>/residual.safetensors`, when it has one (the model is then
/// PGRD; without it, the fitted backbone alone).
pub fn read_residual(run: &Path) -> anyhow::Result<Option<residual::ResidualNet>> {
    let path = run.join("residual.safetensors");
    if !path.exists() {
        if run.join("residual.json").exists() {
            // A run whose weights were moved or not written yet: say which model this is.
            eprintln!(
                "note: {} has residual.json but no residual.safetensors; using the backbone alone",
                run.display()
            );
        }
        return Ok(None);
    }
    residual::ResidualNet::load(&path)
        .map(Some)
        .with_context(|| format!("loading {}", path.display()))
}

/// How a residual network is evaluated when nothing needs its gradient.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NetworkPath {
    /// Candle's fused forward-only kernels (`residual::predict_batch`), two to four times
    /// faster, the most for ensembles (`docs/BENCHMARKS.md`, "Forward-only evaluation").
    ForwardOnly,
    /// The autograd operations training runs (`residual::hybrid_rollout`, `residual::predict`):
    /// what `eval` ran until session 82, so it reproduces the numbers documented before then
    /// to the digit. The two agree to float rounding per step (`crates/residual/tests/batch.rs`),
    /// which contact and friction amplify over a long window (the rope's 37-step episodes:
    /// up to 0.02 cm per episode, 0.001-0.002 cm on a 20-episode mean).
    Autograd,
}

impl NetworkPath {
    /// The name reports give it.
    pub fn label(self) -> &'static str {
        match self {
            NetworkPath::ForwardOnly => "forward-only",
            NetworkPath::Autograd => "autograd",
        }
    }
}

/// Rolls the run's model out over `scene`'s window: the backbone with `params`, plus the
/// residual network when `net` is given (it needs the episode's `history`), evaluated by
/// `path`. Returns the tracked particles' positions after each step (`scene.window.steps`
/// entries), m.
pub fn predict_tracked(
    scene: &Scene,
    params: &springs::SpringParams,
    options: &residual::BackboneOptionsFn,
    net: Option<&residual::ResidualNet>,
    history: Option<&residual::History>,
    path: NetworkPath,
) -> anyhow::Result<Vec<Vec<glam::Vec3>>> {
    Ok(match (net, history) {
        (Some(net), Some(history)) => {
            let bb = scene.backbone(params, &scene.sim_config(), options())?;
            let positions = match path {
                NetworkPath::ForwardOnly => {
                    let job = residual::PredictJob {
                        backbone: &bb,
                        init: &scene.init,
                        history,
                        actions: &scene.actions,
                        steps: scene.window.steps,
                    };
                    let mut results = residual::predict_batch(net, &[job])?;
                    anyhow::ensure!(results.len() == 1, "one job, {} results", results.len());
                    results.remove(0)?
                }
                NetworkPath::Autograd => {
                    residual::hybrid_rollout(net, &bb, scene, history, Default::default())?
                        .positions
                }
            };
            positions
                .into_iter()
                .map(|mut p| {
                    p.truncate(scene.tracked);
                    p
                })
                .collect()
        }
        (Some(_), None) => anyhow::bail!("the residual network needs the episode's history"),
        _ => scene.rollout(params, &scene.sim_config(), options())?,
    })
}

/// A command's arguments parsed as its command line would be.
#[derive(clap::Parser)]
struct CommandLine<T: clap::Args> {
    #[command(flatten)]
    args: T,
}

/// The arguments of `cargo xtask <command> <args...>`, parsed by the command's own parser, so
/// that a pipeline calling another command in code takes that command's defaults and checks.
pub fn parse_command<T: clap::Args>(command: &str, args: &[String]) -> anyhow::Result<T> {
    let argv = std::iter::once(command.to_string()).chain(args.iter().cloned());
    let parsed = <CommandLine<T> as clap::Parser>::try_parse_from(argv)
        .with_context(|| format!("the command line of `{command}`"))?;
    Ok(parsed.args)
}

/// Whether two paths name one directory (`runs/a/` and `./runs/a` do); paths that cannot be
/// resolved (not there yet) are compared as written.
pub fn same_directory(a: &Path, b: &Path) -> bool {
    match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
        (Ok(x), Ok(y)) => x == y,
        _ => a == b,
    }
}

/// `--…-min(utes)` values: finite and >= 0 (a NaN or negative budget would silently mean
/// "none" or "stop at once").
pub fn parse_minutes(text: &str) -> Result<f64, String> {
    let v: f64 = text.parse().map_err(|e| format!("{e}"))?;
    if v.is_finite() && v >= 0.0 {
        Ok(v)
    } else {
        Err(format!("{v} minutes: must be finite and >= 0"))
    }
}

/// Plain progress lines for a command whose progress bar nobody sees: stderr (where the bar
/// draws) is not a terminal, so a job writing to a log would otherwise say nothing until it
/// ends. At most one line per [`PlainProgress::EVERY_S`], so short runs stay quiet.
pub struct PlainProgress {
    last: std::time::Instant,
}

impl PlainProgress {
    /// Seconds between two lines.
    pub const EVERY_S: f64 = 10.0;

    /// Lines for a command that is not `quiet` and whose stderr is not a terminal; `None`
    /// otherwise.
    pub fn new(quiet: bool) -> Option<Self> {
        (!quiet && !std::io::IsTerminal::is_terminal(&std::io::stderr())).then(|| PlainProgress {
            last: std::time::Instant::now(),
        })
    }

    /// Whether a line is due now (and, if so, counts it as printed).
    pub fn due(&mut self) -> bool {
        let due = self.last.elapsed().as_secs_f64() >= Self::EVERY_S;
        if due {
            self.last = std::time::Instant::now();
        }
        due
    }
}
