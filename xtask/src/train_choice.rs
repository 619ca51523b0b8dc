//! `cargo xtask train --residual-scale a,b,… [--start-from m,n,…] [--loss l,…] --holdout K`: one
//! network per training recipe (loss × start mode × residual bound), and the run keeps the one
//! its held-out training episodes prefer.
//!
//! The paper's bound (0.1 m/s per axis and step) caps what the network can correct, and how much
//! room an object needs differs by an order of magnitude (`docs/residual.md`, "The bound's
//! ceiling"); a wider bound also lets the network drift further. Where training segments start
//! matters as much, and differently per object (recorded frames help some cables, hurt the
//! sheets). So the recipe is chosen like a checkpoint: each candidate is trained in its own
//! directory with held-out selection, and, in the order given (losses as listed, start modes as
//! listed within each, bounds increasing within those), a candidate replaces the choice only
//! when its selected network is a trained one and [`residual::clearly_better`] than the current
//! choice on the same held-out episodes. The val split is never read.
//!
//! A ladder's best rung may be its widest: with `--widen-bounds N`, when the choice is a
//! trained network at the widest bound of its loss and start mode, that recipe is trained at
//! N wider bounds (three, nine, … times it; `--jobs` at a time) and judged after the others by
//! the same rule. `--narrow-bounds N` does the same at the narrowest bound (a third, a ninth, …
//! of it), after any widening.
//!
//! Candidates are independent, so `--jobs N` trains N of them at once (each in a thread with a
//! rayon pool of its own); the candidates and the choice are bit for bit those of one at a
//! time when every candidate finishes its iterations (tested).

use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::Serialize;

use crate::cmd_train::{LossArg, StartArg, TrainArgs};
use crate::report::write_json;

/// One candidate recipe's outcome, in `<run>/train.json` (`recipe_choice`).
#[derive(Clone, Debug, Serialize)]
struct Candidate {
    /// Its training loss (`--loss`).
    loss: String,
    /// Where its training segments start (`--start-from`).
    start_from: String,
    /// The bound, m/s per axis and step (as written on the command line, not widened from f32).
    bound: f64,
    /// Its run directory.
    run: PathBuf,
    /// Optimiser steps it ran (fewer than `--iterations` when `--max-minutes` stopped it).
    steps_done: u64,
    /// How its training ended (`done`, or `stopped by --max-minutes at step N`).
    status: String,
    /// Optimiser step of its selected network (0: no trained network beat the untrained one).
    selected_step: u64,
    /// Held-out rollout MDE of the backbone alone on the same episodes, cm.
    backbone_heldout_mde_cm: f64,
    /// Held-out rollout MDE of its selected network, cm.
    heldout_mde_cm: f64,
    /// The same per held-out episode, cm.
    heldout_episode_mde_cm: Vec<f64>,
}

/// Sorted, distinct bounds; an error for a non-positive or non-finite one.
fn checked_bounds(bounds: &[f32]) -> anyhow::Result<Vec<f32>> {
    anyhow::ensure!(
        bounds.iter().all(|b| b.is_finite() && *b > 0.0),
        "--residual-scale values must be finite and > 0 m/s, got {bounds:?}"
    );
    let mut sorted = bounds.to_vec();
    sorted.sort_by(f32::total_cmp);
    sorted.dedup();
    Ok(sorted)
}

/// Distinct values (start modes, losses), in the order given.
fn distinct<T: Copy + PartialEq>(values: &[T]) -> Vec<T> {
    let mut out: Vec<T> = Vec::with_capacity(values.len());
    for v in values {
        if !out.contains(v) {
            out.push(*v);
        }
    }
    out
}

/// The command-line name of a value (`guided-recorded`, `distance`, …).
fn arg_name<T: clap::ValueEnum + std::fmt::Debug>(value: T) -> String {
    value
        .to_possible_value()
        .map(|v| v.get_name().to_string())
        .unwrap_or_else(|| format!("{value:?}"))
}

/// One training recipe of the choice.
#[derive(Clone, Copy, Debug)]
struct Recipe {
    loss: LossArg,
    start: StartArg,
    bound: f32,
}

/// Every recipe, losses as given, start modes as given within each, bounds increasing within
/// those.
fn recipes(losses: &[LossArg], starts: &[StartArg], bounds: &[f32]) -> Vec<Recipe> {
    losses
        .iter()
        .flat_map(|&loss| {
            starts.iter().flat_map(move |&start| {
                bounds
                    .iter()
                    .map(move |&bound| Recipe { loss, start, bound })
            })
        })
        .collect()
}

/// A candidate's directory under the run: `bound_<b>` when only bounds vary (the bound-only
/// choice's names), `<start>_bound_<b>` when start modes vary too, prefixed with `<loss>_` when
/// losses vary.
fn recipe_dir(run: &Path, recipe: Recipe, start_modes: usize, losses: usize) -> PathBuf {
    let Recipe { loss, start, bound } = recipe;
    let mut name = match start_modes {
        1 => format!("bound_{bound}"),
        _ => format!("{}_bound_{bound}", arg_name(start)),
    };
    if losses > 1 {
        name = format!("{}_{name}", arg_name(loss));
    }
    run.join(name)
}

/// Index of the chosen candidate (`per_episode` and `selected_step` in the candidates' order):
/// the first, replaced by a later one only when that one is clearly better than the current
/// choice.
///
/// A candidate whose selected network is the step-0 one never replaces the choice: every such
/// network is the backbone itself (trained without `--init-from`; before, an untrained network
/// near it), so their held-out errors are equal or differ by float rounding (10⁻⁶ cm) that can
/// be consistently signed, which the one-standard-error rule alone would call clearly better.
fn choose(per_episode: &[Vec<f64>], selected_step: &[u64]) -> usize {
    let mut best = 0;
    for (i, errors) in per_episode.iter().enumerate().skip(1) {
        let trained = selected_step.get(i).is_some_and(|&s| s > 0);
        if trained && residual::clearly_better(errors, &per_episode[best]) {
            best = i;
        }
    }
    best
}

/// [`choose`] over the candidates' held-out records.
fn choose_among(candidates: &[Candidate]) -> usize {
    let errors: Vec<Vec<f64>> = candidates
        .iter()
        .map(|c| c.heldout_episode_mde_cm.clone())
        .collect();
    let steps: Vec<u64> = candidates.iter().map(|c| c.selected_step).collect();
    choose(&errors, &steps)
}

/// A bound as the command line would write it (0.9, not 0.8999999761581421).
fn as_written(bound: f32) -> f64 {
    bound.to_string().parse().unwrap_or(f64::from(bound))
}

/// Which end of a ladder to extend.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Edge {
    /// Past the widest bound: three, nine, … times it (`--widen-bounds`).
    Wide,
    /// Below the narrowest bound: a third, a ninth, … of it (`--narrow-bounds`).
    Narrow,
}

/// `bound` times `factor`, rounded to six significant digits so that a ladder 0.1, 0.3 widens to
/// 0.9 and 2.7 (and narrows to 0.0333333) rather than to their f32 neighbours.
fn scaled(bound: f32, factor: f64) -> f32 {
    let next = factor * f64::from(bound);
    format!("{next:.5e}").parse().unwrap_or(next as f32)
}

/// Three times `bound` ([`scaled`]).
fn three_times(bound: f32) -> f32 {
    scaled(bound, 3.0)
}

/// A third of `bound` ([`scaled`]).
fn a_third(bound: f32) -> f32 {
    scaled(bound, 1.0 / 3.0)
}

/// The next `count` rungs past one end of a ladder: when the chosen candidate
/// (`recipes[chosen]`, `trained` when its selected network is not the untrained one) sits at
/// the `edge` bound of its loss and start mode (widest or narrowest), that loss and start mode
/// at three, nine, … times (or a third, a ninth, … of) that bound; empty otherwise (a choice
/// inside the ladder, or no trained network chosen, needs no further rung).
fn edge_rungs(
    recipes: &[Recipe],
    chosen: usize,
    trained: bool,
    count: usize,
    edge: Edge,
) -> Vec<Recipe> {
    let Some(&Recipe { loss, start, bound }) = recipes.get(chosen) else {
        return Vec::new();
    };
    let same = recipes
        .iter()
        .filter(|r| r.loss == loss && r.start == start)
        .map(|r| r.bound);
    let (end, step): (f32, fn(f32) -> f32) = match edge {
        Edge::Wide => (same.fold(bound, f32::max), three_times),
        Edge::Narrow => (same.fold(bound, f32::min), a_third),
    };
    if !trained || bound != end {
        return Vec::new();
    }
    std::iter::successors(Some(step(end)), |&b| Some(step(b)))
        .take(count)
        .map(|bound| Recipe { loss, start, bound })
        .collect()
}

/// Extends the ladder past `edge` (`--widen-bounds room` or `--narrow-bounds room`): when the
/// choice among `candidates` (one per recipe, in order) is a trained network at its recipe's
/// `edge` bound, appends `room` further rungs of that recipe ([`edge_rungs`]), trains them
/// with `train` (given every recipe and the range to train) and returns the bounds added; the
/// caller chooses again among all. One batch, whatever `--jobs` is, so the rungs tried depend
/// on the held-out errors alone.
fn extend_ladder(
    recipes: &mut Vec<Recipe>,
    candidates: &mut Vec<Candidate>,
    room: usize,
    edge: Edge,
    train: impl FnOnce(&[Recipe], std::ops::Range<usize>) -> anyhow::Result<Vec<Candidate>>,
) -> anyhow::Result<Vec<f64>> {
    let chosen = choose_among(candidates);
    let trained = candidates.get(chosen).is_some_and(|c| c.selected_step > 0);
    let next = edge_rungs(recipes, chosen, trained, room, edge);
    if next.is_empty() {
        return Ok(Vec::new());
    }
    let from = recipes.len();
    let added = next.iter().map(|r| as_written(r.bound)).collect();
    recipes.extend(next);
    let more = train(recipes, from..recipes.len())?;
    anyhow::ensure!(
        more.len() == recipes.len() - from,
        "{} of {} further candidates ran",
        more.len(),
        recipes.len() - from
    );
    candidates.extend(more);
    Ok(added)
}

/// Copies `from` to `to` through a temporary file and a rename.
fn copy_atomic(from: &Path, to: &Path) -> anyhow::Result<()> {
    let bytes = std::fs::read(from).with_context(|| format!("reading {}", from.display()))?;
    dataset::write_atomic(to, &bytes).with_context(|| format!("writing {}", to.display()))
}

/// Trains one network per start mode of `args.start_from` and bound of `args.residual_scale`,
/// and keeps the chosen one in `args.run`.
pub fn run(args: &TrainArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.holdout > 0 || args.select_on_val,
        "several --residual-scale, --start-from or --loss values, or --widen-bounds or \
         --narrow-bounds, need \
         --holdout K: the recipe is chosen on held-out training episodes, never on the val split \
         (or --select-on-val, on a development dataset's val split)"
    );
    anyhow::ensure!(
        args.init_from.is_none(),
        "--init-from starts one network; it cannot start several bounds, start modes or losses"
    );
    let bounds = checked_bounds(&args.residual_scale)?;
    let starts = distinct(&args.start_from);
    let losses = distinct(&args.loss);
    let mut recipes = recipes(&losses, &starts, &bounds);
    let shape = (starts.len(), losses.len());
    let backbone = args.run.join("backbone.json");
    anyhow::ensure!(
        backbone.exists(),
        "{} not found: fit the backbone first (cargo xtask fit)",
        backbone.display()
    );
    let mut candidates = train_range(args, shape, &recipes, 0..recipes.len())?;
    let mut extend = |edge: Edge, room: usize, recipes: &mut Vec<Recipe>| {
        extend_ladder(recipes, &mut candidates, room, edge, |recipes, todo| {
            if !args.quiet {
                let list: Vec<String> = recipes[todo.clone()]
                    .iter()
                    .map(|r| format!("{} m/s", r.bound))
                    .collect();
                let (edge, verb) = match edge {
                    Edge::Wide => ("widest", "widening"),
                    Edge::Narrow => ("narrowest", "narrowing"),
                };
                eprintln!(
                    "the choice is a trained network at the ladder's {edge} bound: {verb} to {}",
                    list.join(", ")
                );
            }
            train_range(args, shape, recipes, todo)
        })
    };
    let widened = extend(Edge::Wide, args.widen_bounds, &mut recipes)?;
    let narrowed = extend(Edge::Narrow, args.narrow_bounds, &mut recipes)?;
    let chosen_at = choose_among(&candidates);
    let chosen = &candidates[chosen_at];
    for file in ["residual.safetensors", "residual.json"] {
        copy_atomic(&chosen.run.join(file), &args.run.join(file))?;
    }
    // A candidate trained before `train` drew its curves has no picture to copy.
    if chosen.run.join("train.svg").exists() {
        copy_atomic(&chosen.run.join("train.svg"), &args.run.join("train.svg"))?;
    }
    let mut report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(chosen.run.join("train.json"))?)?;
    report["recipe_choice"] = serde_json::json!({
        "rule": "candidates in order (losses as given, start modes as given, bounds \
                 increasing; bounds added by --widen-bounds after them, then those added by \
                 --narrow-bounds); a later one replaces the choice when its trained network is \
                 clearly better on the held-out episodes",
        "widened_bounds": widened,
        "narrowed_bounds": narrowed,
        "chosen": { "loss": chosen.loss, "start_from": chosen.start_from, "bound": chosen.bound },
        "candidates": candidates,
    });
    let report_path = args.run.join("train.json");
    write_json(&report_path, &report)?;
    print!("{}", summary_table(&candidates, chosen_at, args.iterations));
    println!(
        "{} loss, {} start, bound {} m/s chosen -> {}",
        chosen.loss,
        chosen.start_from,
        chosen.bound,
        report_path.display()
    );
    Ok(())
}

/// The candidates one per line, in the order they were judged, the chosen one marked: what a
/// user reads to see how clear the choice was and which candidates a time limit cut short.
fn summary_table(candidates: &[Candidate], chosen: usize, iterations: usize) -> String {
    let backbone = candidates
        .first()
        .map_or(f64::NAN, |c| c.backbone_heldout_mde_cm);
    let episodes = candidates
        .first()
        .map_or(0, |c| c.heldout_episode_mde_cm.len());
    let mut out = format!(
        "recipe choice: held-out rollout MDE on {episodes} training episodes (backbone {backbone:.3} cm)\n\
         {:<10} {:<16} {:>13} {:>13} {:>9} {:>11}\n",
        "loss", "start", "bound", "steps", "selected", "held-out"
    );
    let mut cut_any = false;
    for (i, c) in candidates.iter().enumerate() {
        let cut = c.status.starts_with("stopped");
        cut_any |= cut;
        let steps = format!(
            "{} / {iterations}{}",
            c.steps_done,
            if cut { "*" } else { "" }
        );
        let bound = format!("{} m/s", c.bound);
        let mark = if i == chosen { "  <- chosen" } else { "" };
        out.push_str(&format!(
            "{:<10} {:<16} {bound:>13} {steps:>13} {:>9} {:>8.3} cm{mark}\n",
            c.loss, c.start_from, c.selected_step, c.heldout_mde_cm,
        ));
    }
    if cut_any {
        out.push_str("* stopped by --max-minutes\n");
    }
    out
}

/// Trains recipe `k` of `recipes` in its own directory under `args.run` and reads its held-out
/// selection. `progress` shares one display among candidates training at once.
fn train_candidate(
    args: &TrainArgs,
    (start_modes, losses): (usize, usize),
    k: usize,
    recipes: &[Recipe],
    recipe: Recipe,
    progress: Option<&indicatif::MultiProgress>,
) -> anyhow::Result<Candidate> {
    let Recipe { loss, start, bound } = recipe;
    let dir = recipe_dir(&args.run, recipe, start_modes, losses);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    copy_atomic(&args.run.join("backbone.json"), &dir.join("backbone.json"))?;
    if !args.quiet {
        crate::cmd_train::above_bars(progress, || {
            eprintln!(
                "loss {}, start {}, bound {bound} m/s ({} of {}) -> {}",
                arg_name(loss),
                arg_name(start),
                k + 1,
                recipes.len(),
                dir.display()
            )
        });
    }
    let mut one = args.clone();
    one.residual_scale = vec![bound];
    one.start_from = vec![start];
    one.loss = vec![loss];
    // A candidate is one network: it neither chooses nor extends the ladder again.
    one.widen_bounds = 0;
    one.narrow_bounds = 0;
    one.run = dir.clone();
    one.progress = progress.map(|multi| {
        let label = format!("{} {} {bound} m/s ", arg_name(loss), arg_name(start));
        (multi.clone(), label)
    });
    crate::cmd_train::run(&one).with_context(|| {
        format!(
            "training with loss {}, start {} and bound {bound}",
            arg_name(loss),
            arg_name(start)
        )
    })?;
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("train.json"))?)?;
    let per_episode: Vec<f64> = report["selection"]["best_episode_mde_cm"]
        .as_array()
        .map(|a| a.iter().filter_map(serde_json::Value::as_f64).collect())
        .unwrap_or_default();
    let (Some(selected_step), Some(backbone_mde), Some(steps_done), false) = (
        report["selection"]["best_step"].as_u64(),
        report["selection"]["backbone_mde_cm"].as_f64(),
        report["steps_done"].as_u64(),
        per_episode.is_empty(),
    ) else {
        anyhow::bail!(
            "{} records no held-out selection",
            dir.join("train.json").display()
        );
    };
    Ok(Candidate {
        loss: arg_name(loss),
        start_from: arg_name(start),
        bound: bound.to_string().parse()?,
        run: dir,
        steps_done,
        status: report["status"].as_str().unwrap_or("unknown").to_string(),
        selected_step,
        backbone_heldout_mde_cm: backbone_mde,
        heldout_mde_cm: per_episode.iter().sum::<f64>() / per_episode.len() as f64,
        heldout_episode_mde_cm: per_episode,
    })
}

/// Trains `recipes[todo]`, `args.jobs` at a time, and returns their candidates in order.
fn train_range(
    args: &TrainArgs,
    shape: (usize, usize),
    recipes: &[Recipe],
    todo: std::ops::Range<usize>,
) -> anyhow::Result<Vec<Candidate>> {
    let jobs = args.jobs.clamp(1, todo.len().max(1));
    if jobs == 1 {
        todo.map(|k| train_candidate(args, shape, k, recipes, recipes[k], None))
            .collect()
    } else {
        train_at_once(args, shape, recipes, todo, jobs)
    }
}

/// Trains `recipes[todo]` `jobs` at a time, each worker thread in a rayon pool of its own with
/// `args.threads` workers (so one candidate's rollouts never wait for another's), and returns
/// the candidates in the recipes' order. After a failure no further candidate starts; the
/// first failure in the recipes' order is returned.
fn train_at_once(
    args: &TrainArgs,
    shape: (usize, usize),
    recipes: &[Recipe],
    todo: std::ops::Range<usize>,
    jobs: usize,
) -> anyhow::Result<Vec<Candidate>> {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

    let pools = (0..jobs)
        .map(|_| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(args.threads.max(1))
                .build()
        })
        .collect::<Result<Vec<_>, _>>()
        .context("building the candidates' thread pools")?;
    let multi = indicatif::MultiProgress::new();
    let (first, end) = (todo.start, todo.end);
    let next = AtomicUsize::new(first);
    let failed = AtomicBool::new(false);
    let results: Mutex<Vec<Option<anyhow::Result<Candidate>>>> =
        Mutex::new(todo.clone().map(|_| None).collect());
    std::thread::scope(|scope| {
        for pool in &pools {
            let (next, failed, results, multi) = (&next, &failed, &results, &multi);
            scope.spawn(move || {
                while !failed.load(Ordering::SeqCst) {
                    let k = next.fetch_add(1, Ordering::SeqCst);
                    if k >= end {
                        break;
                    }
                    let Some(&recipe) = recipes.get(k) else { break };
                    let outcome = pool
                        .install(|| train_candidate(args, shape, k, recipes, recipe, Some(multi)));
                    if outcome.is_err() {
                        failed.store(true, Ordering::SeqCst);
                    }
                    if let Ok(mut r) = results.lock() {
                        r[k - first] = Some(outcome);
                    }
                }
            });
        }
    });
    // A panicking worker re-raises its panic when the scope ends, so the lock is not poisoned
    // here; take the results either way.
    let results = results.into_inner().unwrap_or_else(|p| p.into_inner());
    let mut candidates = Vec::with_capacity(todo.len());
    let mut first_failure = None;
    for outcome in results {
        match outcome {
            Some(Ok(c)) => candidates.push(c),
            Some(Err(e)) => {
                first_failure.get_or_insert(e);
            }
            None => {}
        }
    }
    if let Some(e) = first_failure {
        return Err(e);
    }
    anyhow::ensure!(
        candidates.len() == todo.len(),
        "only {} of {} candidates ran",
        candidates.len(),
        todo.len()
    );
    Ok(candidates)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(clap::Parser)]
    struct Cli {
        #[command(flatten)]
        train: TrainArgs,
    }

    /// `cargo xtask train` arguments parsed from `argv` (its first item the command's name).
    fn parse<'a>(argv: impl IntoIterator<Item = &'a str>) -> TrainArgs {
        <Cli as clap::Parser>::try_parse_from(argv).unwrap().train
    }

    #[test]
    fn bounds_are_sorted_distinct_and_positive() {
        assert_eq!(
            checked_bounds(&[1.0, 0.1, 0.5, 1.0]).unwrap(),
            vec![0.1, 0.5, 1.0]
        );
        for bad in [0.0, -0.1, f32::NAN, f32::INFINITY] {
            assert!(checked_bounds(&[0.1, bad]).is_err(), "{bad}");
        }
    }

    #[test]
    fn several_recipes_without_held_out_episodes_are_refused() {
        for extra in [
            ["--start-from", "guided,recorded"],
            ["--residual-scale", "0.1,1"],
            ["--loss", "mse,distance"],
        ] {
            let args = parse(
                ["train", "--data", "no-such-data", "--run", "no-such-run"]
                    .into_iter()
                    .chain(extra),
            );
            let err = crate::cmd_train::run(&args).unwrap_err().to_string();
            assert!(err.contains("--holdout"), "{err}");
        }
    }

    #[test]
    fn start_modes_keep_their_order_and_command_line_names() {
        use StartArg::*;
        assert_eq!(
            distinct(&[Recorded, Guided, Recorded, GuidedRecorded]),
            vec![Recorded, Guided, GuidedRecorded]
        );
        let names: Vec<String> = [Guided, Recorded, GuidedRecorded, Rollout]
            .into_iter()
            .map(arg_name)
            .collect();
        assert_eq!(names, ["guided", "recorded", "guided-recorded", "rollout"]);
    }

    #[test]
    fn recipes_run_losses_then_start_modes_then_bounds_each_in_its_own_directory() {
        use LossArg::*;
        use StartArg::*;
        let all = recipes(&[Distance, Mse], &[Recorded, Guided], &[0.1, 0.3]);
        let order: Vec<(LossArg, StartArg, f32)> =
            all.iter().map(|r| (r.loss, r.start, r.bound)).collect();
        assert_eq!(
            order,
            [
                (Distance, Recorded, 0.1),
                (Distance, Recorded, 0.3),
                (Distance, Guided, 0.1),
                (Distance, Guided, 0.3),
                (Mse, Recorded, 0.1),
                (Mse, Recorded, 0.3),
                (Mse, Guided, 0.1),
                (Mse, Guided, 0.3),
            ]
        );
        let run = Path::new("run");
        let dir = |r: Recipe, starts, losses| recipe_dir(run, r, starts, losses);
        // One loss keeps the names of earlier runs; several prefix the loss.
        assert_eq!(dir(all[1], 1, 1), run.join("bound_0.3"));
        assert_eq!(dir(all[2], 2, 1), run.join("guided_bound_0.1"));
        assert_eq!(dir(all[2], 2, 2), run.join("distance_guided_bound_0.1"));
        assert_eq!(dir(all[5], 1, 2), run.join("mse_bound_0.3"));
        let names: Vec<PathBuf> = all.iter().map(|&r| dir(r, 2, 2)).collect();
        assert!(
            names
                .iter()
                .enumerate()
                .all(|(i, n)| !names[..i].contains(n))
        );
        // The losses parse from one comma-separated flag, in the order given.
        let argv = [
            "train",
            "--data",
            "d",
            "--run",
            "r",
            "--loss",
            "distance,mse",
        ];
        assert_eq!(parse(argv).loss, [Distance, Mse]);
        assert_eq!(parse(argv[..5].iter().copied()).loss, [Mse]);
    }

    #[test]
    fn candidates_trained_at_once_are_those_trained_one_after_another() {
        let dir = std::env::temp_dir().join(format!("pgrd-train-jobs-{}", std::process::id()));
        let data = crate::cmd_fit::FIXTURE_ROPE;
        let fit = crate::cmd_fit::FitArgs::quick_rope_fixture(dir.join("one"));
        crate::cmd_fit::run(&fit).unwrap();
        for run in ["two", "three"] {
            std::fs::create_dir_all(dir.join(run)).unwrap();
            std::fs::copy(
                dir.join("one/backbone.json"),
                dir.join(run).join("backbone.json"),
            )
            .unwrap();
        }
        let train = |run: &str, jobs: &str, widen: &str, narrow: &str| -> serde_json::Value {
            let run = dir.join(run);
            let argv = [
                "train",
                "--data",
                data,
                "--run",
                run.to_str().unwrap(),
                "--iterations",
                "4",
                "--holdout",
                "1",
                "--select-every",
                "2",
                "--residual-scale",
                "0.1,1",
                "--start-from",
                "guided,recorded",
                "--jobs",
                jobs,
                "--widen-bounds",
                widen,
                "--narrow-bounds",
                narrow,
                "--quiet",
            ];
            crate::cmd_train::run(&parse(argv)).unwrap();
            let text = std::fs::read_to_string(run.join("train.json")).unwrap();
            serde_json::from_str::<serde_json::Value>(&text).unwrap()["recipe_choice"].clone()
        };
        let one = train("one", "1", "0", "0");
        let two = train("two", "2", "0", "0");
        let candidates = one["candidates"].as_array().unwrap();
        assert_eq!(candidates.len(), 4);
        assert_eq!(one["chosen"], two["chosen"]);
        for (a, b) in candidates.iter().zip(two["candidates"].as_array().unwrap()) {
            for key in [
                "start_from",
                "bound",
                "selected_step",
                "steps_done",
                "heldout_episode_mde_cm",
            ] {
                assert_eq!(a[key], b[key], "{key}");
            }
            // The networks themselves, bit for bit.
            let net = |c: &serde_json::Value| {
                let run = std::path::PathBuf::from(c["run"].as_str().unwrap());
                std::fs::read(run.join("train_ckpt.safetensors")).unwrap()
            };
            assert!(net(a) == net(b), "{}", a["run"]);
        }
        // Extending the ladder keeps its candidates, each in its own directory of the run, and
        // trains 3 m/s only when the choice is a trained network at 1 m/s, a third of 0.1 m/s
        // only when it is one at 0.1 m/s.
        let three = train("three", "2", "1", "1");
        let extended = three["candidates"].as_array().unwrap();
        for (a, b) in candidates.iter().zip(extended) {
            assert_eq!(a["heldout_episode_mde_cm"], b["heldout_episode_mde_cm"]);
        }
        for c in extended {
            let run = std::path::PathBuf::from(c["run"].as_str().unwrap());
            assert_eq!(run.parent(), Some(dir.join("three").as_path()));
        }
        let chosen = candidates
            .iter()
            .find(|c| {
                c["start_from"] == one["chosen"]["start_from"]
                    && c["bound"] == one["chosen"]["bound"]
            })
            .unwrap();
        let trained = chosen["selected_step"].as_u64() > Some(0);
        let at = |bound: f64| trained && chosen["bound"] == bound;
        let wider: Vec<f64> = if at(1.0) { vec![3.0] } else { vec![] };
        let narrower: Vec<f64> = if at(0.1) { vec![0.0333333] } else { vec![] };
        assert_eq!(three["widened_bounds"], serde_json::json!(wider));
        assert_eq!(three["narrowed_bounds"], serde_json::json!(narrower));
        assert_eq!(extended.len(), 4 + wider.len() + narrower.len());
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn the_summary_marks_the_choice_and_the_candidates_a_time_limit_cut() {
        let candidate = |loss: &str, bound: f64, steps: u64, status: &str, mde: f64| Candidate {
            loss: loss.to_string(),
            start_from: "recorded".to_string(),
            bound,
            run: PathBuf::from("run"),
            steps_done: steps,
            status: status.to_string(),
            selected_step: steps / 2,
            backbone_heldout_mde_cm: 5.22,
            heldout_mde_cm: mde,
            heldout_episode_mde_cm: vec![mde; 20],
        };
        let all = [
            candidate("mse", 0.1, 1000, "done", 4.2051),
            candidate(
                "distance",
                0.3,
                861,
                "stopped by --max-minutes at step 861",
                3.9,
            ),
        ];
        let table = summary_table(&all, 1, 1000);
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(lines.len(), 5, "{table}");
        assert!(lines[0].contains("20 training episodes (backbone 5.220 cm)"));
        assert!(lines[2].contains("1000 / 1000") && lines[2].contains("4.205 cm"));
        assert!(!lines[2].contains("chosen") && !lines[2].contains('*'));
        assert!(lines[3].contains("861 / 1000*") && lines[3].ends_with("<- chosen"));
        assert_eq!(lines[4], "* stopped by --max-minutes");
        // Without a cut candidate there is no footnote.
        assert_eq!(summary_table(&all[..1], 0, 1000).lines().count(), 3);
    }

    #[test]
    fn a_wider_bound_must_be_clearly_better() {
        let narrow = vec![4.0, 5.0, 6.0, 5.0];
        // Lower on average but not on every episode by much: not clearly better.
        let noisy = vec![3.0, 6.5, 5.0, 5.2];
        // Lower on every episode by about 1 cm: clearly better.
        let wide = vec![3.1, 3.9, 5.0, 4.0];
        let trained = [250, 250, 250, 250];
        assert_eq!(choose(&[narrow.clone(), noisy.clone()], &trained[..2]), 0);
        assert_eq!(choose(&[narrow.clone(), wide.clone()], &trained[..2]), 1);
        // Compared with the current choice, not with the narrowest.
        let wider = vec![3.0, 4.0, 4.9, 4.1];
        assert_eq!(
            choose(
                &[narrow.clone(), wide.clone(), wider.clone()],
                &trained[..3]
            ),
            1
        );
        let widest = vec![2.0, 2.9, 4.0, 3.0];
        assert_eq!(
            choose(
                &[narrow.clone(), noisy.clone(), wide.clone(), widest.clone()],
                &trained
            ),
            3
        );
        // An untrained (step-0) network never replaces the choice, however its errors compare.
        assert_eq!(choose(&[narrow.clone(), wide.clone()], &[250, 0]), 0);
        assert_eq!(choose(&[narrow, wide, widest], &[0, 0, 500]), 2);
    }

    #[test]
    fn a_ladder_widens_by_threes_only_past_a_trained_choice_at_its_edge() {
        use LossArg::*;
        use StartArg::*;
        let widened: Vec<f32> = [0.1, 0.3, 1.0, 3.0].map(three_times).to_vec();
        assert_eq!(widened, [0.3, 0.9, 3.0, 9.0]);
        assert_eq!(as_written(0.9), 0.9);
        // Guided at 0.1 and 1, recorded at 0.1 and 0.3.
        let ladder = [
            Recipe {
                loss: Mse,
                start: Guided,
                bound: 0.1,
            },
            Recipe {
                loss: Mse,
                start: Guided,
                bound: 1.0,
            },
            Recipe {
                loss: Mse,
                start: Recorded,
                bound: 0.1,
            },
            Recipe {
                loss: Mse,
                start: Recorded,
                bound: 0.3,
            },
        ];
        let bounds = |r: Vec<Recipe>| -> Vec<(StartArg, f32)> {
            r.iter().map(|r| (r.start, r.bound)).collect()
        };
        // At the edge of its own start mode, trained: the next rungs of that start mode.
        assert_eq!(
            bounds(edge_rungs(&ladder, 1, true, 2, Edge::Wide)),
            [(Guided, 3.0), (Guided, 9.0)]
        );
        assert_eq!(
            bounds(edge_rungs(&ladder, 3, true, 1, Edge::Wide)),
            [(Recorded, 0.9)]
        );
        // Inside the ladder, untrained, nothing asked, or no such candidate: none.
        assert!(edge_rungs(&ladder, 0, true, 2, Edge::Wide).is_empty());
        assert!(edge_rungs(&ladder, 2, true, 2, Edge::Wide).is_empty());
        assert!(edge_rungs(&ladder, 1, false, 2, Edge::Wide).is_empty());
        assert!(edge_rungs(&ladder, 1, true, 0, Edge::Wide).is_empty());
        assert!(edge_rungs(&ladder, 9, true, 2, Edge::Wide).is_empty());
        // The widened rungs of a start mode are its widest from then on.
        let mut longer = ladder.to_vec();
        longer.extend(edge_rungs(&ladder, 1, true, 1, Edge::Wide));
        assert_eq!(
            bounds(edge_rungs(&longer, 4, true, 1, Edge::Wide)),
            [(Guided, 9.0)]
        );
        assert!(edge_rungs(&longer, 1, true, 1, Edge::Wide).is_empty());
        // The other end: a third, a ninth, … of the narrowest bound of the chosen start mode.
        let narrowed: Vec<f32> = [0.1, 0.3, 1.0].map(a_third).to_vec();
        assert_eq!(narrowed, [0.0333333, 0.1, 0.333333]);
        assert_eq!(as_written(a_third(0.1)), 0.0333333);
        assert_eq!(
            bounds(edge_rungs(&ladder, 0, true, 2, Edge::Narrow)),
            [(Guided, 0.0333333), (Guided, 0.0111111)]
        );
        assert_eq!(
            bounds(edge_rungs(&ladder, 2, true, 1, Edge::Narrow)),
            [(Recorded, 0.0333333)]
        );
        assert!(edge_rungs(&ladder, 1, true, 2, Edge::Narrow).is_empty());
        assert!(edge_rungs(&ladder, 3, true, 2, Edge::Narrow).is_empty());
        assert!(edge_rungs(&ladder, 0, false, 2, Edge::Narrow).is_empty());
        // The flag parses; with one recipe it still goes through the choice.
        for flag in ["--widen-bounds", "--narrow-bounds"] {
            let args = parse(["train", "--data", "d", "--run", "r", flag, "2"]);
            assert_eq!(args.widen_bounds + args.narrow_bounds, 2);
            let err = crate::cmd_train::run(&args).unwrap_err().to_string();
            assert!(err.contains("--holdout"), "{err}");
        }
    }

    /// A trained candidate for `recipe` with these held-out errors, for the ladder tests.
    fn stand_in(recipe: &Recipe, errors: Vec<f64>) -> Candidate {
        Candidate {
            loss: arg_name(recipe.loss),
            start_from: arg_name(recipe.start),
            bound: as_written(recipe.bound),
            run: PathBuf::from(format!("bound_{}", recipe.bound)),
            steps_done: 10,
            status: "done".into(),
            selected_step: 10,
            backbone_heldout_mde_cm: 6.0,
            heldout_mde_cm: errors.iter().sum::<f64>() / errors.len() as f64,
            heldout_episode_mde_cm: errors,
        }
    }

    #[test]
    fn widened_rungs_are_judged_in_order_by_the_same_rule() {
        use LossArg::*;
        use StartArg::*;
        // Held-out errors by bound: better up to 3 m/s, worse at 9, best at 27, worse beyond.
        let errors = |bound: f32| -> Vec<f64> {
            let level = match bound {
                b if b < 0.2 => 5.0,
                b if b < 0.5 => 4.0,
                b if b < 2.0 => 3.0,
                b if b < 5.0 => 2.0,
                b if b < 20.0 => 2.5,
                b if b < 50.0 => 1.5,
                _ => 2.5,
            };
            (0..6).map(|e| level + 0.01 * f64::from(e)).collect()
        };
        let candidate = |r: &Recipe| stand_in(r, errors(r.bound));
        let run = |ladder: &[f32], room: usize| -> (Vec<f64>, Vec<usize>, f64) {
            let mut recipes = recipes(&[Mse], &[Guided], ladder);
            let mut candidates: Vec<Candidate> = recipes.iter().map(candidate).collect();
            let mut batches = Vec::new();
            let widened = extend_ladder(
                &mut recipes,
                &mut candidates,
                room,
                Edge::Wide,
                |all, todo| {
                    batches.push(todo.len());
                    Ok(all[todo].iter().map(candidate).collect())
                },
            )
            .unwrap();
            let chosen = candidates[choose_among(&candidates)].bound;
            (widened, batches, chosen)
        };
        // One batch of the rungs asked: 9 m/s loses to 3, and 27 still replaces 3.
        assert_eq!(run(&[0.1, 0.3, 1.0], 2), (vec![3.0, 9.0], vec![2], 3.0));
        assert_eq!(
            run(&[0.1, 0.3, 1.0], 4),
            (vec![3.0, 9.0, 27.0, 81.0], vec![4], 27.0)
        );
        // None asked, or the choice inside the ladder: the ladder as given.
        assert_eq!(run(&[0.1, 0.3, 1.0], 0), (vec![], vec![], 1.0));
        assert_eq!(run(&[0.3, 3.0, 9.0], 2), (vec![], vec![], 3.0));
    }

    #[test]
    fn narrowed_rungs_are_judged_after_the_others_by_the_same_rule() {
        use LossArg::*;
        use StartArg::*;
        // Held-out errors by bound: best at 0.1 among the ladder, as good on average but not
        // clearly better at a third of it, clearly better at a ninth, bad below.
        let errors = |bound: f32| -> Vec<f64> {
            (0..6)
                .map(|e| {
                    let odd = f64::from(e % 2);
                    match bound {
                        b if b < 0.005 => 5.0,
                        b if b < 0.02 => 2.0 + 0.1 * odd,
                        b if b < 0.05 => 2.5 + 1.1 * odd,
                        b if b < 0.2 => 3.0 + 0.1 * odd,
                        b if b < 0.5 => 4.0,
                        _ => 5.0,
                    }
                })
                .collect()
        };
        let candidate = |r: &Recipe| stand_in(r, errors(r.bound));
        let run = |ladder: &[f32], wide: usize, narrow: usize| {
            let mut recipes = recipes(&[Mse], &[Guided], ladder);
            let mut candidates: Vec<Candidate> = recipes.iter().map(candidate).collect();
            let mut added = Vec::new();
            for (edge, room) in [(Edge::Wide, wide), (Edge::Narrow, narrow)] {
                let more = extend_ladder(&mut recipes, &mut candidates, room, edge, |all, todo| {
                    Ok(all[todo].iter().map(candidate).collect())
                })
                .unwrap();
                added.push(more);
            }
            (added, candidates[choose_among(&candidates)].bound)
        };
        // 0.1 is chosen at the narrow end: a third ties with it (kept), a ninth replaces it.
        assert_eq!(
            run(&[0.1, 0.3, 1.0], 2, 2),
            (vec![vec![], vec![0.0333333, 0.0111111]], 0.0111111)
        );
        assert_eq!(
            run(&[0.1, 0.3, 1.0], 0, 1),
            (vec![vec![], vec![0.0333333]], 0.1)
        );
        // A choice inside the ladder: nothing added at either end.
        assert_eq!(
            run(&[0.004, 0.0111111, 0.1], 2, 2),
            (vec![vec![], vec![]], 0.0111111)
        );
    }

    #[test]
    fn step_zero_networks_that_differ_by_rounding_keep_the_narrowest() {
        // Seen on the rope (session 20): three step-0 networks, held-out errors within 2e-6 cm,
        // the widest lower on every episode, so the one-standard-error rule alone picks it.
        let narrow = vec![0.9188515, 1.1586323, 2.1989870, 1.4545840, 0.8495014];
        let wide = vec![0.9188538, 1.1586309, 2.1989832, 1.4545829, 0.8494976];
        assert!(residual::clearly_better(&wide, &narrow));
        assert_eq!(choose(&[narrow, wide], &[0, 0]), 0);
    }
}
