//! pgrd pipelines: `cargo xtask <command>` (built with `--release` by the alias in
//! `.cargo/config.toml`, because users time these).

use clap::{Parser, Subcommand};

mod cmd_demo;
mod cmd_eval;
mod cmd_fit;
mod cmd_import;
mod common;
mod report;

#[derive(Parser)]
#[command(name = "cargo xtask", about = "pgrd pipelines", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Fit, evaluate and plot the backbone on every bundled fixture.
    Demo(cmd_demo::DemoArgs),
    /// Fit the backbone's parameters with CMA-ES on a dataset's train split.
    Fit(cmd_fit::FitArgs),
    /// Evaluate a run's model on a split: MDE, Chamfer, EMD per step.
    Eval(cmd_eval::EvalArgs),
    /// Convert another dataset format into a pgrd dataset.
    Import(cmd_import::ImportArgs),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Demo(args) => cmd_demo::run(&args),
        Command::Fit(args) => cmd_fit::run(&args).map(drop),
        Command::Eval(args) => cmd_eval::run(&args).map(drop),
        Command::Import(args) => cmd_import::run(&args),
    }
}
