//! `cargo xtask refine`: the paper's "Diff. Spring-Mass" baseline. A fitted run's stiffness is
//! let vary per tracked particle and refined by gradient descent through the backbone's
//! adjoint on the train split (`fit::refine_stiffness`); the result is a new run that `eval`
//! scores as model `diff-spring-mass`.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use dataset::{Dataset, Split};
use indicatif::{ProgressBar, ProgressStyle};

use crate::common::{ProtocolArg, backbone_path, read_backbone, scenes};
use crate::report::write_json;

/// Arguments of `refine`.
#[derive(clap::Args)]
pub struct RefineArgs {
    /// Dataset directory (the one the run was fitted on).
    #[arg(long)]
    pub data: PathBuf,
    /// Fitted run directory (its backbone.json; left unchanged).
    #[arg(long)]
    pub run: PathBuf,
    /// New run directory for the refined model (created; gets backbone.json and a checkpoint).
    #[arg(long)]
    pub out: PathBuf,
    /// Adam iterations.
    #[arg(long, default_value_t = 200)]
    pub iterations: usize,
    /// Training episodes per iteration.
    #[arg(long, default_value_t = 4)]
    pub batch: usize,
    /// Adam step size on the log stiffness factors.
    #[arg(long, default_value_t = 0.05)]
    pub lr: f64,
    /// Bound on each log factor (3: stiffness within e^±3 of the fitted value).
    #[arg(long, default_value_t = 3.0)]
    pub max_log_factor: f32,
    /// Steps of each window rolled out (default: the whole window); shorter windows keep the
    /// adjoint from growing over long recordings such as DEFORM's.
    #[arg(long)]
    pub steps: Option<usize>,
    /// How often (iterations) the field is scored on all training episodes; the best is kept.
    #[arg(long, default_value_t = 25)]
    pub check_every: usize,
    /// Seed of the episode sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Scale each episode's gradient to unit norm before the batch mean, so that one episode
    /// whose contacts switched or whose adjoint grew cannot take the step (`false`: the plain
    /// mean, the gradient of the batch's loss).
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    pub scene_norm: bool,
    /// Window of each training episode.
    #[arg(long, value_enum, default_value_t = ProtocolArg::Paper)]
    pub protocol: ProtocolArg,
    /// Print nothing but the final line.
    #[arg(long)]
    pub quiet: bool,
}

/// Runs the refinement and writes `<out>/backbone.json`.
pub fn run(args: &RefineArgs) -> anyhow::Result<()> {
    let t0 = Instant::now();
    anyhow::ensure!(
        !crate::common::same_directory(&args.out, &args.run),
        "--out must be a new run directory, not the fitted run"
    );
    anyhow::ensure!(
        args.lr.is_finite() && args.lr > 0.0,
        "--lr must be finite and > 0, got {}",
        args.lr
    );
    let data = Dataset::open(&args.data)?;
    let mut file = read_backbone(&args.run)?;
    anyhow::ensure!(
        file.refined.is_none(),
        "{} is already refined; refine the run it came from",
        args.run.display()
    );
    let scenes = scenes(&data, Split::Train, args.protocol.into(), file.setting())?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let config = fit::RefineConfig {
        iterations: args.iterations,
        batch: args.batch,
        learning_rate: args.lr,
        max_log_factor: args.max_log_factor,
        steps: args.steps,
        check_every: args.check_every,
        seed: args.seed,
        scene_norm: args.scene_norm,
    };
    let checkpoint = args.out.join("refine.checkpoint.json");
    let bar = if args.quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(config.iterations as u64)
    };
    bar.set_style(ProgressStyle::with_template(
        "refine {bar:30} {pos}/{len} iterations  {msg}  [{elapsed} < {eta}]",
    )?);
    let mut last_check = None;
    // The run's effects, if any, at their fitted values: the field is refined on top of them
    // (refused when the adjoint would hold one of them fixed).
    let model = file.options_for(&data, args.protocol.into())?;
    let mut plain = crate::common::PlainProgress::new(args.quiet);
    let outcome = fit::refine_stiffness(
        &scenes,
        &file.params,
        &*model,
        &config,
        Some(&checkpoint),
        &mut |s| {
            bar.set_position(s.iteration as u64 + 1);
            if s.train_loss_m2.is_some() {
                last_check = s.train_loss_m2;
                // A full check is the line a log wants; the bar shows every step.
                if plain
                    .as_mut()
                    .is_some_and(crate::common::PlainProgress::due)
                {
                    println!(
                        "iteration {}/{}: all train {:.3e} m², |grad| {:.2e}",
                        s.iteration + 1,
                        config.iterations,
                        last_check.unwrap_or(f64::NAN),
                        s.grad_norm
                    );
                }
            }
            bar.set_message(format!(
                "batch {:.3e} m², all train {}, |grad| {:.2e}{}",
                s.batch_loss_m2,
                last_check.map_or("-".into(), |l| format!("{l:.3e} m²")),
                s.grad_norm,
                if s.failed > 0 {
                    format!(", {} failed", s.failed)
                } else {
                    String::new()
                }
            ));
        },
    )?;
    bar.finish();
    let (lo, hi) = outcome
        .log_factor
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), x| {
            (a.min(*x), b.max(*x))
        });
    let (before, after, kept) = (
        outcome.initial_loss_m2,
        outcome.best_loss_m2,
        outcome.best_iteration,
    );
    if kept.is_none() {
        let mut norms: Vec<f64> = outcome
            .history
            .iter()
            .map(|s| s.grad_norm)
            .filter(|g| g.is_finite())
            .collect();
        norms.sort_by(f64::total_cmp);
        eprintln!(
            "no checked field beat the fitted backbone; batch gradient norms: median {:.1e}, largest finite {:.1e}. \
             Where contacts switch or the window is long the gradient says little: try --steps (a shorter window){}",
            norms.get(norms.len() / 2).copied().unwrap_or(f64::NAN),
            norms.last().copied().unwrap_or(f64::NAN),
            if config.scene_norm {
                ""
            } else {
                " or --scene-norm true"
            }
        );
    }
    let svg = args.out.join("refine.svg");
    let drawn = crate::plots::refine_svg(&svg, &data.meta.object, &outcome);
    file.dataset = args.data.display().to_string();
    file.refined = Some(outcome);
    write_json(&backbone_path(&args.out), &file)?;
    crate::plots::or_warn(drawn, &svg.display().to_string());
    println!(
        "refined {} on {} train episodes in {:.1} s: loss {:.3e} -> {:.3e} m² ({}), stiffness factors e^[{:.2}, {:.2}] -> {}",
        data.meta.object,
        scenes.len(),
        t0.elapsed().as_secs_f64(),
        before,
        after,
        kept.map_or("no iteration beat the fitted backbone".into(), |i| format!(
            "kept iteration {i}"
        )),
        lo,
        hi,
        backbone_path(&args.out).display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fitted_run_named_another_way_is_still_refused_as_the_output() {
        let run = std::env::temp_dir().join(format!("pgrd-refine-same-{}", std::process::id()));
        std::fs::create_dir_all(&run).unwrap();
        let dotted = run.join(".");
        for out in [run.clone(), dotted] {
            let args: RefineArgs = crate::common::parse_command(
                "refine",
                &[
                    "--data".into(),
                    "no-such-dataset".into(),
                    "--run".into(),
                    run.display().to_string(),
                    "--out".into(),
                    out.display().to_string(),
                ],
            )
            .unwrap();
            let err = super::run(&args).expect_err("refused").to_string();
            assert!(
                err.contains("not the fitted run"),
                "{}: {err}",
                out.display()
            );
        }
        std::fs::remove_dir_all(&run).ok();
    }
}
