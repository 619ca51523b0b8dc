//! `cargo xtask demo`: the main job on the bundled fixtures. For each object: fit the backbone
//! on the train episodes, evaluate it on the val episodes, write plots and point clouds. Then a
//! tour of the rest of the pipeline on the rope fixture: a residual network on its backbone,
//! rendered frames, a gap diagnosis and a planning trial, each through the same code path as
//! its own command.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use dataset::{Dataset, Split};
use scene::{Protocol, Scene, SceneConfig};

use crate::cmd_eval::{self, EvalArgs};
use crate::cmd_fit::{self, BoundsArg, FitArgs};
use crate::common::{ProtocolArg, SubstepArg};
use crate::report::write_ply;

/// Arguments of `demo`.
#[derive(clap::Args)]
pub struct DemoArgs {
    /// Directory of fixture datasets (one sub-directory per object).
    #[arg(long, default_value = "fixtures")]
    pub fixtures: PathBuf,
    /// Output directory.
    #[arg(long, default_value = "out/demo")]
    pub out: PathBuf,
    /// Only these objects (comma-separated; default: every fixture).
    #[arg(long, value_delimiter = ',')]
    pub objects: Vec<String>,
    /// CMA-ES generations per object (the full pipeline's default is 20).
    #[arg(long, default_value_t = 8)]
    pub generations: usize,
    /// Fit and evaluate the backbones only, without the tour of the rest of the pipeline on
    /// the rope (about 5 s instead of about a minute on 2 cores).
    #[arg(long)]
    pub no_tour: bool,
    /// Training steps of the tour's residual network.
    #[arg(long, default_value_t = 300)]
    pub tour_iterations: usize,
}

/// The fixture the tour runs on: planning's tasks are the rope's.
const TOUR_OBJECT: &str = "rope";

/// Runs the demo.
pub fn run(args: &DemoArgs) -> anyhow::Result<()> {
    let t0 = Instant::now();
    let mut objects: Vec<PathBuf> = std::fs::read_dir(&args.fixtures)
        .with_context(|| {
            format!(
                "reading {} (run from the repository root)",
                args.fixtures.display()
            )
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("dataset.json").is_file())
        .filter(|p| {
            args.objects.is_empty()
                || p.file_name()
                    .is_some_and(|n| args.objects.iter().any(|o| n == o.as_str()))
        })
        .collect();
    objects.sort();
    anyhow::ensure!(
        !objects.is_empty(),
        "no fixture datasets under {}",
        args.fixtures.display()
    );
    println!(
        "pgrd demo: fit the spring-mass backbone (CMA-ES, {} generations) on each fixture's train episodes, then predict its val episodes from their first frames alone.{}\n",
        args.generations,
        if args.no_tour {
            ""
        } else {
            " Then, on the rope: a residual network, rendered frames, a gap diagnosis and a planning trial."
        }
    );
    let mut rows = Vec::new();
    for dir in &objects {
        let name = dir
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("object")
            .to_string();
        let run = args.out.join(&name);
        // A fresh fit each time: the demo shows the whole job, not a cached result.
        let _ = std::fs::remove_file(run.join("fit.checkpoint.json"));
        let data = Dataset::open(dir)?;
        println!(
            "== {name}: {} episodes ({} train, {} val), {} manipulation",
            data.meta.episodes.len(),
            data.split_indices(Split::Train).len(),
            data.split_indices(Split::Val).len(),
            match data.meta.manipulation {
                dataset::Manipulation::Grasp => "grasp",
                dataset::Manipulation::Push => "push",
                dataset::Manipulation::Attach => "attach",
            }
        );
        let fitted = cmd_fit::run(&FitArgs {
            data: dir.clone(),
            run: run.clone(),
            population: 8,
            generations: args.generations,
            samples: 8,
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
            quiet: false,
        })?;
        let report = cmd_eval::run(&EvalArgs {
            data: dir.clone(),
            run: run.clone(),
            split: Split::Val,
            protocol: ProtocolArg::Paper,
            json: None,
            plot: None,
            no_emd: false,
            visual: false,
            horizon: None,
            autograd: false,
            save_predictions: None,
        })?;
        // Point clouds of the last predicted step of the first val episode, next to the truth.
        let index = data.split_indices(Split::Val)[0];
        let ep = data.load_episode(index)?;
        let window = Protocol::Paper.window(ep.frames())?;
        let config = SceneConfig::default().with_neighbours_of(&data)?;
        let scene = Scene::new(&data.meta, &ep, window, &config)?;
        let pred = scene.rollout(&fitted.params, &scene.sim_config(), Default::default())?;
        let last = pred.len() - 1;
        write_ply(&run.join("final_predicted.ply"), &pred[last], ep.colors())?;
        write_ply(
            &run.join("final_truth.ply"),
            &scene.truth[last],
            ep.colors(),
        )?;
        rows.push((
            name,
            report.metrics["mde_cm"]["mean"]
                .as_f64()
                .unwrap_or(f64::NAN),
            report.metrics["chamfer_cm"]["mean"]
                .as_f64()
                .unwrap_or(f64::NAN),
            report.metrics["emd_cm"]["mean"]
                .as_f64()
                .unwrap_or(f64::NAN),
        ));
        println!();
    }
    println!(
        "{:<10} {:>10} {:>22} {:>10}",
        "object", "MDE (cm)", "Chamfer 2-sided (cm)", "EMD (cm)"
    );
    for (name, mde, ch, emd) in &rows {
        println!("{name:<10} {mde:>10.3} {ch:>22.3} {emd:>10.3}");
    }
    println!(
        "\nwrote backbone.json, fit.svg (the CMA-ES search), springs.svg and .ply (the spring graph), eval_val.json, eval_val.svg (error per step) and final_*.ply per object under {} ({:.1} s)",
        args.out.display(),
        t0.elapsed().as_secs_f64()
    );
    let rope_mde = rows.iter().find(|r| r.0 == TOUR_OBJECT).map(|r| r.1);
    let toured = match (args.no_tour, rope_mde) {
        (true, _) => false,
        (false, None) => {
            println!("\n(no tour: it runs on the {TOUR_OBJECT} fixture, which --objects left out)");
            false
        }
        (false, Some(rope_mde)) => {
            crate::demo_tour::run(
                &crate::demo_tour::TourPaths::new(
                    &args.fixtures.join(TOUR_OBJECT),
                    &args.out.join(TOUR_OBJECT),
                    &args.out.join("tour"),
                ),
                args.tour_iterations,
                rope_mde,
            )?;
            true
        }
    };
    // An earlier run's tour stays on disk; the page shows this run's pictures only.
    crate::demo_index::write(&args.out, &rows, toured)?;
    println!(
        "\nopen {} in a browser: every object's pictures{}",
        args.out.join("index.html").display(),
        if toured { " and the tour's" } else { "" }
    );
    Ok(())
}
