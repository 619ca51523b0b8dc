//! `cargo xtask fit`: CMA-ES over the backbone's five parameters on the train split.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use dataset::{Dataset, Split};
use fit::{BackboneFamily, ControllerFamily, FitConfig};
use indicatif::{ProgressBar, ProgressStyle};
use scene::Scene;

use crate::common::{
    BackboneFile, PlainProgress, ProtocolArg, SceneSetting, SubstepArg, backbone_path,
    note_glued_springs, scenes, warn_if_unconnected, write_spring_graph,
};
use crate::report::write_json;

/// Arguments of `fit`.
#[derive(clap::Args)]
pub struct FitArgs {
    /// Dataset directory.
    #[arg(long)]
    pub data: PathBuf,
    /// Run directory (created); gets backbone.json and a checkpoint.
    #[arg(long)]
    pub run: PathBuf,
    /// Candidates per generation.
    #[arg(long, default_value_t = 8)]
    pub population: usize,
    /// Generations.
    #[arg(long, default_value_t = 20)]
    pub generations: usize,
    /// Training episodes sampled per generation.
    #[arg(long, default_value_t = 8)]
    pub samples: usize,
    /// Seed of the optimiser and the sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Final selection: score the optimiser's mean and the best candidates of this many of
    /// the best generations on all training episodes and keep the best (0: the best candidate
    /// by its own generation's sampled episodes, the reference's rule).
    #[arg(long, default_value_t = 0)]
    pub rescore: usize,
    /// Most training episodes the rescoring scores: a subset of this many, drawn with the
    /// seed, when there are more (0: all).
    #[arg(long, default_value_t = 0)]
    pub rescore_scenes: usize,
    /// Window of each training episode.
    #[arg(long, value_enum, default_value_t = ProtocolArg::Paper)]
    pub protocol: ProtocolArg,
    /// Search bounds: the reference code's, or its wider set used for the paper. The
    /// threshold's upper end is raised where the tracked points are too sparse for it to give
    /// every free particle a spring (docs/pipelines.md, "The threshold's range").
    #[arg(long, value_enum, default_value_t = BoundsArg::Reference)]
    pub bounds: BoundsArg,
    /// Keep `--bounds`' threshold range as it is, however sparse the points (the rule before
    /// 2026-12-07).
    #[arg(long)]
    pub fixed_threshold_range: bool,
    /// How the simulator chooses its substep; recorded in backbone.json, and `eval`, `train`
    /// and `diagnose` use the run's.
    #[arg(long, value_enum, default_value_t = SubstepArg::Auto)]
    pub substep: SubstepArg,
    /// Join only material neighbours by springs: tracked points whose mean distance over the
    /// training recordings is at most twice the spring radius, not parts that merely touch at
    /// a window's start frame (docs/pipelines.md, "Material springs"). Recorded in
    /// backbone.json; every later stage builds the run's model the same way.
    #[arg(long)]
    pub material_springs: bool,
    /// For an `attach` dataset (a PhysTwin import): also search how the controller points join
    /// the object, their reach (0.01–0.08 m) and spring count (10–80), as PhysTwin's first stage
    /// does, starting from the rule the dataset declares. Recorded in backbone.json; every later
    /// stage builds the run's model with the rule found (docs/pipelines.md, "The controller
    /// rule").
    #[arg(long)]
    pub fit_controller: bool,
    /// With `--fit-controller`: searches from this many starting radii (1–3: the declared
    /// radius, then halfway from it to 0.01 m, then halfway to 0.08 m), keeping the one whose
    /// fit has the lowest loss over every training episode. The radius moves the loss in steps,
    /// so one search can stall at its start; each start costs a fit.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u8).range(1..=3))]
    pub controller_starts: u8,
    /// Print nothing but the final line.
    #[arg(long)]
    pub quiet: bool,
}

/// `--bounds`.
#[derive(Clone, Copy, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum BoundsArg {
    /// damping [1, 1000], stiffness [10, 5e4], threshold [0.002, 0.05] m, springs [4, 200], friction [0.01, 0.5].
    Reference,
    /// damping to 1e4, stiffness to 5e5, springs to 500.
    Paper,
}

impl BoundsArg {
    /// The parameter bounds this choice names.
    pub fn bounds(self) -> springs::ParamBounds {
        match self {
            BoundsArg::Reference => springs::REFERENCE_BOUNDS,
            BoundsArg::Paper => springs::PAPER_BOUNDS,
        }
    }

    /// The choice as written on the command line.
    pub fn name(self) -> &'static str {
        match self {
            BoundsArg::Reference => "reference",
            BoundsArg::Paper => "paper",
        }
    }
}

/// `choice`'s bounds, their threshold range widened for `scenes` unless `fixed`
/// ([`fit::widen_threshold_range`]); says so when it widens, unless `quiet`.
pub fn search_bounds(
    choice: BoundsArg,
    fixed: bool,
    scenes: &[Scene],
    quiet: bool,
) -> springs::ParamBounds {
    let bounds = choice.bounds();
    if fixed {
        return bounds;
    }
    let widened = fit::widen_threshold_range(bounds, scenes);
    if widened != bounds && !quiet {
        println!(
            "threshold range widened to [{}, {:.4}] m: the tracked points are too sparse for \
             {} m to give every free particle a spring (--fixed-threshold-range keeps it)",
            widened.threshold[0], widened.threshold[1], bounds.threshold[1]
        );
    }
    widened
}

/// Runs the fit and writes `<run>/backbone.json`.
pub fn run(args: &FitArgs) -> anyhow::Result<BackboneFile> {
    let t0 = Instant::now();
    let data = Dataset::open(&args.data)?;
    // The search starts from the dataset's own rule; a dataset whose controller points are
    // joined like the object (`import phystwin --controller-like-object`) starts from
    // PhysTwin's defaults.
    let controller_start = if args.fit_controller {
        anyhow::ensure!(
            data.meta.manipulation == dataset::Manipulation::Attach,
            "--fit-controller searches how an `attach` dataset's controller points join the \
             object, and {} is a `{}` dataset (its grippers have no springs of their own)",
            args.data.display(),
            format!("{:?}", data.meta.manipulation).to_lowercase()
        );
        Some(
            data.meta
                .controller_springs
                .unwrap_or(dataset::ControllerSprings::PHYSTWIN),
        )
    } else {
        None
    };
    let setting = SceneSetting {
        substep: args.substep,
        material_springs: args.material_springs,
        controller_springs: controller_start,
    };
    let scenes = scenes(&data, Split::Train, args.protocol.into(), setting)?;
    std::fs::create_dir_all(&args.run)
        .with_context(|| format!("creating {}", args.run.display()))?;
    let bounds = search_bounds(args.bounds, args.fixed_threshold_range, &scenes, args.quiet);
    let config = FitConfig {
        population: args.population,
        generations: args.generations,
        samples: args.samples,
        sigma0: 0.2,
        seed: args.seed,
        rescore: args.rescore,
        rescore_scenes: args.rescore_scenes,
        rescore_start: false,
    };
    anyhow::ensure!(
        config.population >= 2 && config.samples >= 1 && config.generations >= 1,
        "--population must be >= 2, --samples >= 1 and --generations >= 1"
    );
    let checkpoint = args.run.join("fit.checkpoint.json");
    let starts = if controller_start.is_some() {
        usize::from(args.controller_starts)
    } else {
        1
    };
    let bar = if args.quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new((starts * config.generations) as u64)
    };
    bar.set_style(ProgressStyle::with_template(
        "fit {bar:30} {pos}/{len} generations  {msg}  [{elapsed} < {eta}]",
    )?);
    let mut plain = PlainProgress::new(args.quiet);
    let mut progress = |start: usize, g: &fit::Generation| {
        bar.set_position((start * config.generations + g.index) as u64 + 1);
        let line = format!(
            "best {:.3e} m² (gen {:.3e}, {} diverged, {:.1} s)",
            g.best_so_far, g.best_loss, g.diverged, g.wall_s
        );
        if plain.as_mut().is_some_and(PlainProgress::due) {
            let of_start = match starts {
                1 => String::new(),
                n => format!(" of start {}/{n}", start + 1),
            };
            println!(
                "generation {}/{}{of_start}: {line}",
                g.index + 1,
                config.generations
            );
        }
        bar.set_message(line);
    };
    let ck = Some(checkpoint.as_path());
    let (outcome, controller_starts) = match controller_start {
        Some(declared) => {
            let found = fit::fit_controller(
                &scenes,
                bounds,
                declared,
                starts,
                &config,
                ck,
                &mut progress,
            )?;
            (found.outcome, found.starts)
        }
        None => {
            let family = BackboneFamily::new(bounds)?;
            let outcome = fit::fit(&scenes, &family, &config, ck, &mut |g| progress(0, g))?;
            (outcome, Vec::new())
        }
    };
    bar.finish();
    if let Some(g) = outcome.resumed_from {
        println!("resumed from generation {g} ({})", checkpoint.display());
    }
    if let Some(r) = &outcome.rescored {
        let kept = &r.contenders[r.chosen];
        println!(
            "rescored {} contenders on {} of {} train episodes: kept {} (loss {:.3e} m²)",
            r.contenders.len(),
            r.scenes,
            scenes.len(),
            kept.generation
                .map_or("the optimiser's mean".to_string(), |g| format!(
                    "generation {g}'s best"
                )),
            kept.loss
        );
    }
    // A mean loss at the penalty means the kept candidate diverged on every episode it was
    // scored on: its parameters are whatever CMA-ES drew last, not a fit, so nothing is written.
    anyhow::ensure!(
        outcome.best_loss < fit::PENALTY,
        "every rollout of the kept candidate diverged on {} (its loss is the divergence \
         penalty, {:.0e} m²): no parameters within the bounds simulate this data, and nothing \
         was written to {}; check the dataset's units and scale (positions in metres, gravity \
         in m/s², fps)",
        args.data.display(),
        fit::PENALTY,
        backbone_path(&args.run).display()
    );
    let params = BackboneFamily::params(&outcome.best);
    let controller_springs = controller_start.map(|_| ControllerFamily::rule(&outcome.best));
    if let Some(scene) = scenes.first() {
        let bb = warn_if_unconnected(scene, &params, Default::default())?;
        let ply = args.run.join("springs.ply");
        crate::plots::or_warn(
            write_spring_graph(&ply, &data.meta.object, scene, &bb),
            &ply.display().to_string(),
        );
    }
    if !args.material_springs {
        note_glued_springs(&data, &scenes, &params)?;
    }
    let generations_wall: f64 = outcome.history.iter().map(|g| g.wall_s).sum();
    let file = BackboneFile {
        model: "spring-mass".into(),
        dataset: args.data.display().to_string(),
        protocol: scene::Protocol::from(args.protocol).name().into(),
        params,
        fit: outcome,
        config,
        wall_s: generations_wall,
        session_wall_s: t0.elapsed().as_secs_f64(),
        effects: Vec::new(),
        refined: None,
        substep: args.substep,
        material_springs: args.material_springs,
        controller_springs,
        controller_starts: controller_starts.clone(),
    };
    write_json(&backbone_path(&args.run), &file)?;
    let fit_svg = args.run.join("fit.svg");
    crate::plots::or_warn(
        crate::plots::fit_svg(&fit_svg, &data.meta.object, &file.fit.history),
        &fit_svg.display().to_string(),
    );
    println!(
        "fitted {} on {} train episodes in {:.1} s: stiffness {:.0} N/m, damping {:.1} N·s/m, threshold {:.4} m, max springs {}, friction {:.3}; loss {:.3e} m² -> {} (and fit.svg, springs.svg, springs.ply)",
        data.meta.object,
        scenes.len(),
        t0.elapsed().as_secs_f64(),
        params.stiffness,
        params.damping,
        params.threshold,
        params.max_springs,
        params.ground_friction,
        file.fit.best_loss,
        backbone_path(&args.run).display()
    );
    if let Some(rule) = controller_springs {
        println!(
            "controller points: each joined to up to {} particles within {:.4} m",
            rule.max_springs, rule.radius_m
        );
        if controller_starts.len() > 1 {
            let each: Vec<String> = controller_starts
                .iter()
                .map(|s| {
                    format!(
                        "from {:.4} m: {:.4} m, {} springs, loss {:.3e} m²",
                        s.start_radius_m, s.found.radius_m, s.found.max_springs, s.train_loss_m2
                    )
                })
                .collect();
            println!(
                "  {} starts, the lowest loss over every training episode kept: {}",
                controller_starts.len(),
                each.join("; ")
            );
        }
    }
    Ok(file)
}

/// The rope fixture, for tests.
#[cfg(test)]
pub(crate) const FIXTURE_ROPE: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../fixtures/rope");

/// A copy of the rope fixture in `dir` whose gravity is a million times too strong and points
/// up: data no parameters can simulate, so every rollout diverges. For tests.
#[cfg(test)]
pub(crate) fn diverging_rope_fixture(dir: &std::path::Path) {
    std::fs::create_dir_all(dir).unwrap();
    for entry in std::fs::read_dir(FIXTURE_ROPE).unwrap() {
        let path = entry.unwrap().path();
        std::fs::copy(&path, dir.join(path.file_name().unwrap())).unwrap();
    }
    let index = dir.join("dataset.json");
    let mut json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&index).unwrap()).unwrap();
    json["gravity"] = serde_json::json!([0.0, 0.0, 1e6]);
    std::fs::write(&index, json.to_string()).unwrap();
}

#[cfg(test)]
impl FitArgs {
    /// The cheapest fit of the rope fixture into `run` (two candidates, one generation, one
    /// sample), for tests that need a run directory with a backbone.
    pub(crate) fn quick_rope_fixture(run: PathBuf) -> Self {
        FitArgs {
            data: FIXTURE_ROPE.into(),
            run,
            population: 2,
            generations: 1,
            samples: 1,
            seed: 0,
            rescore: 0,
            rescore_scenes: 0,
            protocol: ProtocolArg::Paper,
            bounds: BoundsArg::Reference,
            fixed_threshold_range: false,
            substep: SubstepArg::Auto,
            material_springs: false,
            fit_controller: false,
            controller_starts: 3,
            quiet: true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::common::read_backbone;

    #[test]
    fn the_run_records_its_substep_rule_and_older_runs_read_as_auto() {
        let dir = std::env::temp_dir().join(format!("pgrd-fit-substep-{}", std::process::id()));
        let args = FitArgs {
            substep: SubstepArg::Spectral,
            ..FitArgs::quick_rope_fixture(dir.clone())
        };
        run(&args).unwrap();
        let path = backbone_path(&dir);
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains(r#""substep": "spectral""#), "{text}");
        assert_eq!(read_backbone(&dir).unwrap().substep, SubstepArg::Spectral);
        // Its search, drawn beside it.
        let svg = std::fs::read_to_string(dir.join("fit.svg")).unwrap();
        assert!(svg.contains("fit: rope, CMA-ES"), "{svg}");
        // And its spring graph, drawn too: every spring an edge between two of its particles.
        let drawn = std::fs::read_to_string(dir.join("springs.svg")).unwrap();
        assert!(drawn.contains("springs: rope,"), "{drawn}");
        let ply = std::fs::read_to_string(dir.join("springs.ply")).unwrap();
        let count = |element: &str| -> usize {
            let line = ply.lines().find(|l| l.starts_with(element)).unwrap();
            line.rsplit(' ').next().unwrap().parse().unwrap()
        };
        let (vertices, edges) = (count("element vertex"), count("element edge"));
        let body: Vec<&str> = ply.split("end_header\n").nth(1).unwrap().lines().collect();
        assert_eq!(body.len(), vertices + edges);
        assert!(edges > vertices, "{edges} springs for {vertices} particles");
        for line in &body[vertices..] {
            let ends: Vec<usize> = line.split(' ').map(|v| v.parse().unwrap()).collect();
            assert!(ends.len() == 2 && ends[0] != ends[1] && ends.iter().all(|&v| v < vertices));
        }
        // A run written before the field existed was fitted with the default rule.
        let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
        json.as_object_mut().unwrap().remove("substep");
        std::fs::write(&path, serde_json::to_string(&json).unwrap()).unwrap();
        let old = read_backbone(&dir).unwrap();
        assert_eq!(old.substep, SubstepArg::Auto);
        // ... and writes no key, so older readers still parse it.
        assert!(!serde_json::to_string(&old).unwrap().contains("substep"));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn the_run_records_material_springs_and_older_runs_read_as_reference_springs() {
        let dir = std::env::temp_dir().join(format!("pgrd-fit-material-{}", std::process::id()));
        let args = FitArgs {
            material_springs: true,
            ..FitArgs::quick_rope_fixture(dir.clone())
        };
        run(&args).unwrap();
        let path = backbone_path(&dir);
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains(r#""material_springs": true"#), "{text}");
        let setting = read_backbone(&dir).unwrap().setting();
        assert!(setting.material_springs);
        let data = Dataset::open(FIXTURE_ROPE).unwrap();
        assert!(
            setting
                .scene_config(&data)
                .unwrap()
                .material_pairs
                .is_some()
        );
        let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
        json.as_object_mut().unwrap().remove("material_springs");
        std::fs::write(&path, serde_json::to_string(&json).unwrap()).unwrap();
        let old = read_backbone(&dir).unwrap();
        assert!(!old.material_springs);
        assert!(
            old.setting()
                .scene_config(&data)
                .unwrap()
                .material_pairs
                .is_none()
        );
        assert!(
            !serde_json::to_string(&old)
                .unwrap()
                .contains("material_springs")
        );
        std::fs::remove_dir_all(&dir).ok();
    }

    /// `--fit-controller` on a PhysTwin import: the rule found is recorded, every later stage
    /// builds its scenes with it, and a dataset without controller points refuses the flag.
    #[test]
    fn the_run_records_the_controller_rule_it_found_and_grasp_data_refuses_the_search() {
        let root = std::env::temp_dir().join(format!("pgrd-fit-ctrl-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let case =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/phystwin/rope_lift");
        let opts = dataset::import::phystwin::PhysTwinOptions {
            every: 1,
            episode_frames: 12,
            stride_frames: 6,
            ..Default::default()
        };
        dataset::import::phystwin::import(&case, &root.join("data"), &opts).unwrap();
        let run_dir = root.join("run");
        let args = FitArgs {
            data: root.join("data"),
            population: 4,
            generations: 2,
            protocol: ProtocolArg::Deform,
            fit_controller: true,
            ..FitArgs::quick_rope_fixture(run_dir.clone())
        };
        let file = run(&args).unwrap();
        let rule = file.controller_springs.expect("the rule found is recorded");
        assert!((0.01..=0.08).contains(&rule.radius_m), "{rule:?}");
        assert!((10..=80).contains(&rule.max_springs), "{rule:?}");
        assert_eq!(file.fit.names.len(), 7);
        // Three starts by default, each checkpointed; the kept one has the lowest loss.
        assert_eq!(file.controller_starts.len(), 3);
        let kept = file
            .controller_starts
            .iter()
            .min_by(|a, b| a.train_loss_m2.total_cmp(&b.train_loss_m2))
            .unwrap();
        assert_eq!(kept.found, rule);
        assert!(run_dir.join("fit.checkpoint.start2.json").is_file());
        let read = read_backbone(&run_dir).unwrap();
        assert_eq!(read.controller_springs, Some(rule));
        let data = Dataset::open(root.join("data")).unwrap();
        let train = scenes(&data, Split::Train, scene::Protocol::Deform, read.setting()).unwrap();
        let anchors = train[0]
            .anchors()
            .expect("the controller points are anchors");
        assert_eq!(
            (anchors.radius_m, anchors.max_springs),
            (rule.radius_m, rule.max_springs)
        );
        // A plain fit of the same data keeps the dataset's rule and writes no key.
        let plain = run(&FitArgs {
            fit_controller: false,
            ..FitArgs {
                run: root.join("plain"),
                ..args
            }
        })
        .unwrap();
        assert_eq!(plain.controller_springs, None);
        let text = std::fs::read_to_string(backbone_path(&root.join("plain"))).unwrap();
        assert!(!text.contains("controller_springs"), "{text}");
        let err = run(&FitArgs {
            fit_controller: true,
            ..FitArgs::quick_rope_fixture(root.join("rope"))
        })
        .unwrap_err();
        assert!(format!("{err:#}").contains("`attach` dataset"), "{err:#}");
        std::fs::remove_dir_all(&root).ok();
    }

    /// Data no parameters can simulate (gravity a million times too strong, upward) is a
    /// clear error, and no backbone.json is written from the divergence penalty's candidate.
    #[test]
    fn a_fit_whose_every_rollout_diverges_is_an_error() {
        let root = std::env::temp_dir().join(format!("pgrd-fit-diverged-{}", std::process::id()));
        let data = root.join("data");
        diverging_rope_fixture(&data);
        let run_dir = root.join("run");
        let args = FitArgs {
            data: data.clone(),
            ..FitArgs::quick_rope_fixture(run_dir.clone())
        };
        let err = run(&args).unwrap_err().to_string();
        assert!(err.contains("diverged") && err.contains("units"), "{err}");
        assert!(!backbone_path(&run_dir).exists());
        std::fs::remove_dir_all(&root).ok();
    }

    /// Settings that cannot search are refused before any work, not reported as data that no
    /// parameters simulate.
    #[test]
    fn a_fit_that_cannot_search_is_refused_up_front() {
        let dir = std::env::temp_dir().join(format!("pgrd-fit-settings-{}", std::process::id()));
        for (population, samples, generations) in [(1, 1, 1), (2, 0, 1), (2, 1, 0)] {
            let args = FitArgs {
                population,
                samples,
                generations,
                ..FitArgs::quick_rope_fixture(dir.clone())
            };
            let err = run(&args).unwrap_err().to_string();
            assert!(err.contains("--generations >= 1"), "{err}");
            assert!(!backbone_path(&dir).exists());
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A run scored on another object's data says so; on its own object's data it is quiet.
    #[test]
    fn a_run_notes_data_of_another_object() {
        let dir = std::env::temp_dir().join(format!("pgrd-fit-object-{}", std::process::id()));
        run(&FitArgs::quick_rope_fixture(dir.clone())).unwrap();
        let file = read_backbone(&dir).unwrap();
        assert_eq!(file.fitted_object().as_deref(), Some("rope"));
        let rope = Dataset::open(FIXTURE_ROPE).unwrap();
        assert_eq!(file.note_other_object(&rope), None);
        let teddy =
            Dataset::open(concat!(env!("CARGO_MANIFEST_DIR"), "/../fixtures/teddy")).unwrap();
        let note = file.note_other_object(&teddy).expect("a note");
        assert!(
            note.contains("fitted on rope data") && note.contains("not on teddy"),
            "{note}"
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
