//! pgrd pipelines: `cargo xtask <command>` (built with `--release` by the alias in
//! `.cargo/config.toml`, because users time these).

use clap::{Parser, Subcommand};

/// mimalloc instead of glibc's malloc, which returns the residual network's freed buffers to the
/// system after every call and faults them back in (`docs/plan-log.md`, "Planning speed").
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

mod cmd_chain;
mod cmd_compare;
mod cmd_demo;
mod cmd_diagnose;
mod cmd_ensemble;
mod cmd_eval;
mod cmd_fit;
mod cmd_gen;
mod cmd_import;
mod cmd_metrics;
mod cmd_plan;
mod cmd_refine;
mod cmd_render;
mod cmd_score;
mod cmd_screen;
mod cmd_train;
mod common;
mod demo_index;
mod demo_tour;
mod eval_horizon;
mod eval_save;
mod plots;
mod report;
mod staged;
mod train_choice;
mod train_resume;

#[derive(Parser)]
#[command(name = "cargo xtask", about = "pgrd pipelines", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Fit, evaluate and plot the backbone on every bundled fixture, then tour the rest of the
    /// pipeline (network, rendering, diagnosis, planning) on the rope.
    Demo(cmd_demo::DemoArgs),
    /// Generate a reference-world dataset with known, switchable effects.
    Gen(cmd_gen::GenArgs),
    /// Diagnose the sim-to-real gap of a fitted run: where, which effect, how far it shrinks.
    Diagnose(cmd_diagnose::DiagnoseArgs),
    /// Diagnose again and again, each round adding the effect its verdict names, until `none` /
    /// `unknown` or `--max-rounds`; resumable; scores the start and final models on `test`.
    Chain(cmd_chain::ChainArgs),
    /// Write a diagnosis's report.html again from its report.json (this version's page).
    ReportPage(cmd_diagnose::ReportPageArgs),
    /// Score a run's backbone with one effect added at fixed settings, each against the model
    /// without it (paired bootstrap), with no refit; one run directory per setting.
    Screen(cmd_screen::ScreenArgs),
    /// Check the diagnosis on reference-world data with withheld effects.
    DiagnoseBench(cmd_diagnose::DiagnoseBenchArgs),
    /// Fit the backbone's parameters with CMA-ES on a dataset's train split.
    Fit(cmd_fit::FitArgs),
    /// Refine a fitted run's stiffness per tracked particle by gradient descent through the
    /// simulator (the paper's "Diff. Spring-Mass" baseline); writes a new run.
    Refine(cmd_refine::RefineArgs),
    /// Evaluate a run's model on a split: MDE, Chamfer, EMD per step.
    Eval(cmd_eval::EvalArgs),
    /// Score trajectories predicted elsewhere (laid out as `eval --save-predictions` writes
    /// them) on a dataset's episodes as `eval` scores pgrd's; `compare` pairs the reports.
    Score(cmd_score::ScoreArgs),
    /// Paired comparison of two eval reports on the same episodes: shrinkage with a bootstrap
    /// interval.
    Compare(cmd_compare::CompareArgs),
    /// Point-cloud metrics of two .npy clouds as JSON (MDE, Chamfer, EMD).
    Metrics(cmd_metrics::MetricsArgs),
    /// Render a run's predicted and the ground-truth frames of an episode (a recording's own
    /// tracked points where it has no ground-truth Gaussians); J, F, LPIPS.
    Render(cmd_render::RenderArgs),
    /// MPPI planning with a run's model, executed in closed loop in the reference world.
    Plan(cmd_plan::PlanArgs),
    /// Train the residual network (PGRD) on top of a run's fitted backbone.
    Train(cmd_train::TrainArgs),
    /// Combine trained residual networks (e.g. several seeds) into one model whose residual is
    /// their mean; writes a run that `eval`, `render` and `plan` use as PGRD.
    Ensemble(cmd_ensemble::EnsembleArgs),
    /// Convert another dataset format into a pgrd dataset.
    Import(cmd_import::ImportArgs),
    /// Copy a dataset with its last training episodes as `val` and its `val` as `test`: choose
    /// models on training recordings, score them once on the rest.
    DevSplit(cmd_import::DevSplitArgs),
    /// Merge chosen splits of several datasets of one object into a new dataset, in order.
    Merge(cmd_import::MergeArgs),
}

fn main() -> anyhow::Result<()> {
    let command = Cli::parse().command;
    set_thread_count(&command);
    match command {
        Command::Demo(args) => cmd_demo::run(&args),
        Command::Gen(args) => cmd_gen::run(&args),
        Command::Diagnose(args) if args.estimate => cmd_diagnose::estimate(&args),
        Command::Diagnose(args) => cmd_diagnose::run(&args).map(drop),
        Command::Chain(args) => cmd_chain::run(&args).map(drop),
        Command::ReportPage(args) => cmd_diagnose::report_page(&args),
        Command::DiagnoseBench(args) => cmd_diagnose::run_bench(&args).map(drop),
        Command::Screen(args) => cmd_screen::run(&args).map(drop),
        Command::Fit(args) => cmd_fit::run(&args).map(drop),
        Command::Refine(args) => cmd_refine::run(&args),
        Command::Eval(args) => cmd_eval::run(&args).map(drop),
        Command::Score(args) => cmd_score::run(&args).map(drop),
        Command::Compare(args) => cmd_compare::run(&args),
        Command::Import(args) => cmd_import::run(&args),
        Command::DevSplit(args) => cmd_import::dev_split(&args),
        Command::Merge(args) => cmd_import::merge(&args),
        Command::Metrics(args) => cmd_metrics::run(&args),
        Command::Plan(args) => cmd_plan::run(&args),
        Command::Render(args) => cmd_render::run(&args),
        Command::Train(args) => cmd_train::run(&args),
        Command::Ensemble(args) => cmd_ensemble::run(&args),
    }
}

/// Sets `RAYON_NUM_THREADS`, when the user has not, to the threads the command runs with
/// (`train`'s `--threads`, every core otherwise: rayon's own default).
///
/// candle's CPU matmul asks for its thread count on every call: from `RAYON_NUM_THREADS` when
/// set, otherwise by opening and parsing `/proc/cpuinfo` (`num_cpus::get_physical`). Training
/// multiplies matrices thousands of times a step, and those reads took about 40 % of its wall
/// time on a 2-core host, most of it in the kernel (`docs/BENCHMARKS.md`, "Training: candle's
/// thread count"). With the variable set the question is an environment lookup. The trained
/// weights came out the same bits with and without it (measured there).
fn set_thread_count(command: &Command) {
    if std::env::var_os("RAYON_NUM_THREADS").is_some() {
        return;
    }
    let threads = match command {
        Command::Train(args) => args.threads.max(1),
        _ => std::thread::available_parallelism().map_or(1, std::num::NonZeroUsize::get),
    };
    // SAFETY: `main` calls this before anything spawns a thread, so no other thread can be
    // reading or writing the environment (the one condition `set_var` has).
    #[allow(unsafe_code)]
    unsafe {
        std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
    }
}
