//! The demo's tour of the pipeline after the backbone, on the rope fixture: each stage runs
//! through its own command's code with the arguments a user would type, so the tour shows
//! (and keeps working with) what `train`, `eval`, `render`, `diagnose` and `plan` do.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;

use crate::{cmd_compare, cmd_diagnose, cmd_eval, cmd_plan, cmd_render, cmd_train};

/// Where the tour reads and writes.
pub struct TourPaths {
    /// The fixture dataset.
    pub data: PathBuf,
    /// The demo's fitted run of that fixture (its `backbone.json`).
    pub fitted: PathBuf,
    /// The tour's output directory.
    pub out: PathBuf,
}

impl TourPaths {
    /// The tour of `data`, starting from the backbone fitted in `fitted`, writing to `out`.
    pub fn new(data: &Path, fitted: &Path, out: &Path) -> Self {
        Self {
            data: data.to_path_buf(),
            fitted: fitted.to_path_buf(),
            out: out.to_path_buf(),
        }
    }

    fn run(&self) -> PathBuf {
        self.out.join("run")
    }
}

/// The commands the tour runs, in its order.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Command {
    Train,
    Eval,
    Compare,
    Render,
    Diagnose,
    Plan,
}

impl Command {
    fn name(self) -> &'static str {
        match self {
            Command::Train => "train",
            Command::Eval => "eval",
            Command::Compare => "compare",
            Command::Render => "render",
            Command::Diagnose => "diagnose",
            Command::Plan => "plan",
        }
    }
}

/// One stage: its command and the command line a user would type after
/// `cargo xtask <command>`.
struct Stage {
    command: Command,
    argv: Vec<String>,
}

/// The tour's stages in order.
fn stages(p: &TourPaths, iterations: usize) -> Vec<Stage> {
    let data = p.data.display().to_string();
    let run = p.run().display().to_string();
    let out = |sub: &str| p.out.join(sub).display().to_string();
    let stage = |command, argv: &[&str]| Stage {
        command,
        argv: argv.iter().map(|a| a.to_string()).collect(),
    };
    vec![
        stage(
            Command::Train,
            &[
                "--data",
                &data,
                "--run",
                &run,
                "--iterations",
                &iterations.to_string(),
                "--quiet",
            ],
        ),
        stage(
            Command::Eval,
            &[
                "--data",
                &data,
                "--run",
                &run,
                "--save-predictions",
                &out("predictions"),
            ],
        ),
        stage(
            Command::Compare,
            &[
                "--before",
                &p.fitted.join("eval_val.json").display().to_string(),
                "--after",
                &p.run().join("eval_pgrd_val.json").display().to_string(),
                "--plot",
                &out("compare.svg"),
            ],
        ),
        stage(
            Command::Render,
            &["--data", &data, "--run", &run, "--out", &out("render")],
        ),
        stage(
            Command::Diagnose,
            &["--data", &data, "--run", &run, "--out", &out("report")],
        ),
        stage(
            Command::Plan,
            &[
                "--task",
                "rope-lift",
                "--run",
                &run,
                "--trials",
                "1",
                "--json",
                &out("plan/rope-lift.json"),
            ],
        ),
    ]
}

fn parse<T: clap::Args>(stage: &Stage) -> anyhow::Result<T> {
    let name = stage.command.name();
    crate::common::parse_command(name, &stage.argv)
        .with_context(|| format!("the demo's `{name}` stage"))
}

/// Runs the tour; `backbone_mde_cm` is the fitted backbone's val MDE, printed beside the
/// network's.
pub fn run(p: &TourPaths, iterations: usize, backbone_mde_cm: f64) -> anyhow::Result<()> {
    let t0 = Instant::now();
    println!(
        "\n== the rest of the pipeline on the {} fixture, under {}",
        p.data.display(),
        p.out.display()
    );
    // A fresh run each time (training and diagnosis resume from what they find): the backbone
    // the demo just fitted, nothing else.
    if p.out.exists() {
        std::fs::remove_dir_all(&p.out).with_context(|| format!("clearing {}", p.out.display()))?;
    }
    std::fs::create_dir_all(p.run()).with_context(|| format!("creating {}", p.run().display()))?;
    std::fs::copy(
        p.fitted.join("backbone.json"),
        p.run().join("backbone.json"),
    )
    .with_context(|| format!("copying {}/backbone.json", p.fitted.display()))?;
    for stage in stages(p, iterations) {
        println!(
            "\n-- cargo xtask {} {}",
            stage.command.name(),
            stage.argv.join(" ")
        );
        let t = Instant::now();
        match stage.command {
            Command::Train => cmd_train::run(&parse(&stage)?)?,
            Command::Eval => {
                let report = cmd_eval::run(&parse(&stage)?)?;
                let mde = report.metrics["mde_cm"]["mean"]
                    .as_f64()
                    .unwrap_or(f64::NAN);
                let train = dataset::Dataset::open(&p.data)?
                    .split_indices(dataset::Split::Train)
                    .len();
                println!(
                    "val MDE: spring-mass {backbone_mde_cm:.3} cm, pgrd {mde:.3} cm ({}). A \
                     fixture's {train} training episodes are too few for a network to learn \
                     from; docs/RESULTS.md has each object's network trained on 100 episodes.",
                    if mde < backbone_mde_cm {
                        "the network lower"
                    } else {
                        "the network no lower"
                    }
                );
            }
            Command::Compare => cmd_compare::run(&parse(&stage)?)?,
            Command::Render => cmd_render::run(&parse(&stage)?)?,
            Command::Diagnose => drop(cmd_diagnose::run(&parse(&stage)?)?),
            Command::Plan => cmd_plan::run(&parse(&stage)?)?,
        }
        println!("({:.1} s)", t.elapsed().as_secs_f64());
    }
    println!(
        "\nthe tour wrote under {}: run/ (backbone.json, residual.safetensors, train.json, \
         train.svg (the training curves), eval_pgrd_val.json), predictions/ (each val episode's predicted and recorded \
         trajectories, safetensors), compare.svg (both models' error per step and per \
         episode), render/ (frames and compare.gif), report/report.html (open \
         it in a browser), plan/ (rope-lift.json, .svg and a GIF per model) ({:.1} s)",
        p.out.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every stage's command line parses as its command's own: a renamed or removed option
    /// fails here, not in a user's demo.
    #[test]
    fn every_stage_parses_as_its_command() {
        let p = TourPaths::new(
            Path::new("fixtures/rope"),
            Path::new("out/demo/rope"),
            Path::new("out/demo/tour"),
        );
        let stages = stages(&p, 300);
        let order: Vec<_> = stages.iter().map(|s| s.command).collect();
        use Command::*;
        assert_eq!(order, [Train, Eval, Compare, Render, Diagnose, Plan]);
        for s in &stages {
            match s.command {
                Train => {
                    let a: cmd_train::TrainArgs = parse(s).unwrap();
                    assert_eq!(a.iterations, 300);
                    assert_eq!(a.run, Path::new("out/demo/tour/run"));
                }
                Eval => drop(parse::<cmd_eval::EvalArgs>(s).unwrap()),
                Compare => {
                    let a: cmd_compare::CompareArgs = parse(s).unwrap();
                    assert_eq!(a.before, Path::new("out/demo/rope/eval_val.json"));
                    assert_eq!(a.after, Path::new("out/demo/tour/run/eval_pgrd_val.json"));
                }
                Render => drop(parse::<cmd_render::RenderArgs>(s).unwrap()),
                Diagnose => drop(parse::<cmd_diagnose::DiagnoseArgs>(s).unwrap()),
                Plan => {
                    let a: cmd_plan::PlanArgs = parse(s).unwrap();
                    assert_eq!(a.task, "rope-lift");
                }
            }
        }
        let bad = Stage {
            command: Train,
            argv: vec!["--no-such-option".into()],
        };
        assert!(parse::<cmd_train::TrainArgs>(&bad).is_err());
    }
}
