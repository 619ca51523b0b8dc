//! `cargo xtask chain`: the user's diagnosis rounds in one resumable command. Each round
//! diagnoses the model the round before wrote (`diagnose --write-run`), so each adds at most
//! the effect its verdict names; the chain stops at the first round that adds none (`none`,
//! or `unknown` unless `--add-past-unknown` finds a library effect behind it) or at
//! `--max-rounds`, and scores the model it started from and the one it ends with once on the
//! dataset's `test` split when there is one (`cargo xtask dev-split`). `docs/gap.md`, "Chains
//! of diagnoses".

use std::path::{Path, PathBuf};

use anyhow::Context;
use dataset::{Dataset, Split};
use gap::Diagnosis;
use serde::{Deserialize, Serialize};

use crate::cmd_diagnose::{self, DiagnoseArgs};
use crate::cmd_eval::{self, EvalArgs};
use crate::common::{backbone_path, read_backbone};
use crate::report::write_json;

/// Arguments of `chain`: those of `diagnose`, applied to every round, and the round limit.
/// `--out` names the chain's directory (`round-<k>/` holds round k's report and, in `run/`,
/// the model it wrote; `chain.json` the rounds so far), `--write-run` where the final model is
/// also written, and `--with` the base effects of the first round only (later rounds take
/// theirs from the run they diagnose).
#[derive(clap::Args)]
#[command(
    mut_arg("out", |a| a.help("Chain directory (created or resumed): round-<k>/ and chain.json")),
    mut_arg("write_run", |a| a.help("Also write the chain's final model to this run directory")),
    mut_arg("with", |a| a.help("Base effects of the first round (as `diagnose --with`)")),
    mut_arg("add_past_unknown", |a| a.help(
        "With the verdict `unknown`, the round adds the effect the library's refits name on \
         their own (a significant candidate the probe outdid) and the chain goes on"
    )),
    mut_arg("estimate", |a| a.hide(true)),
    mut_arg("write_runner_up", |a| a.hide(true))
)]
pub struct ChainArgs {
    #[command(flatten)]
    pub diagnose: DiagnoseArgs,
    /// Most diagnosis rounds; each adds at most one effect. A chain stopped at this limit goes
    /// on from its last round when run again with a larger one.
    #[arg(long, default_value_t = 4)]
    pub max_rounds: usize,
    /// Follow a tie too: at the first round whose added effect was tied with another
    /// significant candidate (held-out error could not separate them), a second branch adds
    /// that runner-up instead (`diagnose --write-runner-up`) and goes on as the chain does
    /// (without branching again, within the same `--max-rounds`); the branch whose final model
    /// scores lower on the val split is the chain's final model (`<out>/branch/round-<k>/`;
    /// `branch` in `chain.json`). Give it from a chain's first run: a chain resumes only with
    /// the settings it started with.
    #[arg(long)]
    pub branch_ties: bool,
}

/// `<out>/chain.json`: what each round did, written after every round, so an interrupted
/// chain resumes after its last complete round.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ChainFile {
    /// Dataset directory, as given.
    pub data: String,
    /// The run the chain started from, as given.
    pub run: String,
    /// Every diagnosis setting but the output paths (a chain resumes only with the same).
    pub settings: String,
    /// Rounds so far, in order.
    pub rounds: Vec<ChainRound>,
    /// Why the chain stopped (absent while it can go on).
    pub stopped: Option<String>,
    /// The model the chain ends with: the last round's written run.
    pub final_run: Option<String>,
    /// The model as given and the final model on the `test` split, when the dataset has one.
    pub test: Option<TestScores>,
    /// With `--branch-ties`, the branch that took a tie's runner-up (absent without a tie).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub branch: Option<ChainBranch>,
}

/// The second branch of a `--branch-ties` chain.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChainBranch {
    /// The main chain's round whose tie it follows.
    pub fork_round: usize,
    /// The runner-up it added there instead of that round's effect.
    pub added: String,
    /// The model with it, as that round's diagnosis refitted it.
    pub start_run: String,
    /// That model (`spring-mass+bending`, …).
    pub model_start: String,
    /// Its held-out MDE there, cm.
    pub heldout_mde_start_cm: f64,
    /// Its rounds after the fork, numbered on from `fork_round`.
    pub rounds: Vec<ChainRound>,
    /// Why it stopped (absent while it can go on).
    pub stopped: Option<String>,
    /// Whether its final model is the chain's (it scored lower on the val split).
    pub chosen: bool,
}

impl ChainBranch {
    /// The branch's final model and its held-out MDE, cm.
    fn last(&self) -> (&str, f64) {
        self.rounds
            .last()
            .map_or((self.start_run.as_str(), self.heldout_mde_start_cm), |r| {
                (r.written_run.as_str(), r.heldout_mde_written_cm)
            })
    }
}

/// `<out>/chain.svg`: the main chain's held-out MDE, the model it started from and each
/// round's written model, labelled with the effect the round added or what it wrote.
fn draw(out: &Path, chain: &ChainFile) {
    let Some(first) = chain.rounds.first() else {
        return;
    };
    let mut steps = vec![(first.model_diagnosed.clone(), first.heldout_mde_as_given_cm)];
    steps.extend(chain.rounds.iter().map(|r| {
        let label = match &r.added {
            Some(effect) => format!("+ {effect}"),
            None => r.written.clone(),
        };
        (label, r.heldout_mde_written_cm)
    }));
    let path = out.join("chain.svg");
    let object = Path::new(&chain.data)
        .file_name()
        .map_or_else(|| chain.data.clone(), |n| n.to_string_lossy().into_owned());
    crate::plots::or_warn(
        crate::plots::chain_svg(&path, &object, &steps),
        &path.display().to_string(),
    );
}

/// One round of a chain.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChainRound {
    /// 1, 2, …
    pub round: usize,
    /// The run diagnosed.
    pub diagnosed_run: String,
    /// Its model (`spring-mass+drag`, …).
    pub model_diagnosed: String,
    /// The verdict: an effect, `none` or `unknown`.
    pub verdict: String,
    /// The effect the round added: the verdict's, or with `--add-past-unknown` the library's
    /// own verdict behind an `unknown`; absent when none was added (the chain stops there).
    pub added: Option<String>,
    /// Held-out MDE shrinkage against the control refit of the effect added, else of the
    /// probe for `unknown`; absent otherwise.
    pub shrinkage: Option<f64>,
    /// 95 % bootstrap interval of `shrinkage`.
    pub ci95: Option<[f64; 2]>,
    /// Held-out MDE of the model diagnosed, as given, cm.
    pub heldout_mde_as_given_cm: f64,
    /// Held-out MDE of the model the round wrote, cm.
    pub heldout_mde_written_cm: f64,
    /// What the round wrote: `with <effect>`, `control refit` or `as given`.
    pub written: String,
    /// The run it wrote.
    pub written_run: String,
    /// Its model.
    pub model_written: String,
    /// Speed options the diagnosis's time budget chose (empty: none).
    pub budget_options: String,
    /// Wall time of the round, s.
    pub wall_s: f64,
    /// With `--branch-ties`: the tied candidate the round did not add, written as a model of
    /// its own (absent without a tie, and after the chain's first tie).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub runner_up: Option<RunnerUp>,
}

/// A tie's runner-up, written by a round (`diagnose --write-runner-up`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunnerUp {
    /// The candidate.
    pub effect: String,
    /// The run holding the model with it.
    pub run: String,
    /// That model's held-out MDE, cm.
    pub heldout_mde_cm: f64,
}

/// The chain's start and end models on the `test` split (scored once, after the rounds).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TestScores {
    /// Test episodes.
    pub episodes: usize,
    /// MDE of the model the chain started from, cm.
    pub mde_as_given_cm: f64,
    /// MDE of the final model, cm.
    pub mde_final_cm: f64,
    /// `1 − final / as given`.
    pub shrinkage: f64,
}

/// Runs `chain`.
pub fn run(args: &ChainArgs) -> anyhow::Result<ChainFile> {
    let d = &args.diagnose;
    anyhow::ensure!(
        !d.estimate,
        "chain runs diagnoses; use `diagnose --estimate` to estimate one"
    );
    anyhow::ensure!(args.max_rounds >= 1, "--max-rounds must be at least 1");
    anyhow::ensure!(
        d.write_runner_up.is_none(),
        "a chain writes each round's models itself; --branch-ties follows a tie's runner-up"
    );
    let out = d
        .out
        .as_deref()
        .context("--out names the chain's directory")?;
    if let Some(dir) = &d.write_run {
        anyhow::ensure!(
            !dir.starts_with(out),
            "--write-run {} is inside the chain's directory; name a directory outside it",
            dir.display()
        );
        cmd_diagnose::check_write_run(dir, &d.run)?;
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let path = out.join("chain.json");
    let settings = settings_of(d, args.branch_ties);
    let mut chain = if path.exists() {
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        let chain: ChainFile = serde_json::from_str(&text)
            .with_context(|| format!("{} is not a chain's record", path.display()))?;
        anyhow::ensure!(
            chain.settings == settings,
            "{} holds a chain of other data, run or diagnosis settings ({} from {}); \
             resume it with the same ones, or name another --out",
            out.display(),
            chain.data,
            chain.run
        );
        if !chain.rounds.is_empty() && !d.quiet {
            println!(
                "resuming the chain in {}: {} round(s) done",
                out.display(),
                chain.rounds.len()
            );
        }
        chain
    } else {
        ChainFile {
            data: d.data.display().to_string(),
            run: d.run.display().to_string(),
            settings,
            rounds: Vec::new(),
            stopped: None,
            final_run: None,
            test: None,
            branch: None,
        }
    };
    while chain.rounds.len() < args.max_rounds
        && chain.rounds.last().is_none_or(|r| r.added.is_some())
    {
        let k = chain.rounds.len() + 1;
        let diagnosed = chain
            .rounds
            .last()
            .map_or_else(|| d.run.clone(), |r| PathBuf::from(&r.written_run));
        // Only the chain's first tie forks a branch.
        let runner_up = args.branch_ties && chain.rounds.iter().all(|r| r.runner_up.is_none());
        let round = run_round(d, out, k, &diagnosed, runner_up, args.max_rounds)?;
        chain.rounds.push(round);
        chain.stopped = None;
        chain.final_run = chain.rounds.last().map(|r| r.written_run.clone());
        chain.test = None;
        write_json(&path, &chain)?;
        draw(out, &chain);
    }
    let last = chain.rounds.last().context("the chain ran no round")?;
    chain.stopped = Some(stop_reason(last, args.max_rounds));
    let mut final_run = PathBuf::from(&last.written_run);
    let main_final_cm = last.heldout_mde_written_cm;
    let fork = chain
        .rounds
        .iter()
        .find_map(|r| r.runner_up.clone().map(|u| (r.round, u)));
    if let Some((fork_round, up)) = fork {
        let mut branch = match chain.branch.take() {
            Some(b) => b,
            None => ChainBranch {
                fork_round,
                model_start: read_backbone(Path::new(&up.run))?.label(),
                added: up.effect,
                start_run: up.run,
                heldout_mde_start_cm: up.heldout_mde_cm,
                rounds: Vec::new(),
                stopped: None,
                chosen: false,
            },
        };
        let dir = out.join("branch");
        let chosen = follow_branch(
            &mut branch,
            args.max_rounds,
            main_final_cm,
            |k, diagnosed| run_round(d, &dir, k, diagnosed, false, args.max_rounds),
            |branch| {
                chain.branch = Some(branch.clone());
                chain.test = None;
                write_json(&path, &chain)
            },
        )?;
        if chosen {
            final_run = PathBuf::from(branch.last().0);
        }
        chain.branch = Some(branch);
    }
    chain.final_run = Some(final_run.display().to_string());
    if let Some(dir) = &d.write_run {
        let file = read_backbone(&final_run)?;
        cmd_diagnose::check_write_run(dir, &d.run)?;
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        write_json(&backbone_path(dir), &file)?;
    }
    chain.test = test_scores(d, out, &final_run)?;
    write_json(&path, &chain)?;
    draw(out, &chain);
    print_summary(&chain, d);
    Ok(chain)
}

/// The settings a chain must resume with: every diagnosis argument but the output paths and
/// the printing, and `--branch-ties` (named only when given, so chains recorded before it
/// resume as they were).
fn settings_of(d: &DiagnoseArgs, branch_ties: bool) -> String {
    let mut s = d.clone();
    s.out = None;
    s.write_run = None;
    s.quiet = false;
    let ties = if branch_ties { " --branch-ties" } else { "" };
    format!("{s:?}{ties}")
}

/// Runs a branch's rounds (`next_round(k, model)` diagnoses round k's model) until one adds
/// no effect or `max_rounds` is reached, saving after each; then marks it chosen when its
/// final model scores lower on the val split than the main chain's (`main_final_cm`; a tie
/// keeps the main chain). A branch with rounds done resumes after them.
fn follow_branch(
    branch: &mut ChainBranch,
    max_rounds: usize,
    main_final_cm: f64,
    mut next_round: impl FnMut(usize, &Path) -> anyhow::Result<ChainRound>,
    mut save: impl FnMut(&ChainBranch) -> anyhow::Result<()>,
) -> anyhow::Result<bool> {
    while branch.fork_round + branch.rounds.len() < max_rounds
        && branch.rounds.last().is_none_or(|r| r.added.is_some())
    {
        let k = branch.fork_round + branch.rounds.len() + 1;
        let round = next_round(k, Path::new(branch.last().0))?;
        branch.rounds.push(round);
        branch.stopped = None;
        branch.chosen = false;
        save(branch)?;
    }
    branch.stopped = Some(match branch.rounds.last() {
        Some(r) => stop_reason(r, max_rounds),
        None => format!("round limit {max_rounds}: the fork was the last round"),
    });
    // Both branches' held-out MDEs are on the same val split.
    branch.chosen = branch.last().1 < main_final_cm;
    Ok(branch.chosen)
}

/// Why a chain (or its branch) whose last round is `last` stops.
fn stop_reason(last: &ChainRound, max_rounds: usize) -> String {
    if let Some(added) = &last.added {
        format!(
            "round limit {max_rounds}: round {} still added {added}; run the chain again with a \
             larger --max-rounds to go on",
            last.round
        )
    } else {
        format!(
            "round {}: verdict {}, no effect left to add",
            last.round, last.verdict
        )
    }
}

/// Diagnoses round `k`'s model (`diagnosed`: the run given, or the model the round before
/// wrote) and writes the model it refitted to `<out>/round-<k>/run`; with `runner_up`, a tie's
/// runner-up also to `<out>/round-<k>/run-runner-up`.
fn run_round(
    d: &DiagnoseArgs,
    out: &Path,
    k: usize,
    diagnosed: &Path,
    runner_up: bool,
    max_rounds: usize,
) -> anyhow::Result<ChainRound> {
    let dir = out.join(format!("round-{k}"));
    let written = dir.join("run");
    let runner_up_run = dir.join("run-runner-up");
    let given = read_backbone(diagnosed)?;
    if !d.quiet {
        println!(
            "== chain round {k} (at most {max_rounds}): diagnosing {} ({})",
            given.label(),
            diagnosed.display()
        );
    }
    let round_args = DiagnoseArgs {
        run: diagnosed.to_path_buf(),
        out: Some(dir.clone()),
        write_run: Some(written.clone()),
        write_runner_up: runner_up.then(|| runner_up_run.clone()),
        // The first round's base effects as the user named them; later rounds take the
        // model the round before wrote, effects and all.
        with: if k == 1 { d.with.clone() } else { None },
        ..d.clone()
    };
    let diagnosis = cmd_diagnose::run(&round_args)?;
    let model_written = read_backbone(&written)?.label();
    let mut round = round_record(
        k,
        &diagnosis,
        d.add_past_unknown,
        diagnosed,
        given.label(),
        &written,
        model_written,
    )?;
    if runner_up
        && let Some(added) = cmd_diagnose::effect_to_add(&diagnosis, d.add_past_unknown)?
        && let Some(other) = cmd_diagnose::runner_up(&diagnosis, added)
        && let Some(entry) = diagnosis.ranking.iter().find(|r| r.effect == other.name())
    {
        round.runner_up = Some(RunnerUp {
            effect: entry.effect.clone(),
            run: runner_up_run.display().to_string(),
            heldout_mde_cm: entry.heldout_mde_after_cm,
        });
    }
    Ok(round)
}

/// What a round did, from its diagnosis.
fn round_record(
    k: usize,
    diagnosis: &Diagnosis,
    add_past_unknown: bool,
    diagnosed: &Path,
    model_diagnosed: String,
    written_run: &Path,
    model_written: String,
) -> anyhow::Result<ChainRound> {
    let verdict = diagnosis.verdict.clone();
    let added =
        cmd_diagnose::effect_to_add(diagnosis, add_past_unknown)?.map(|c| c.name().to_string());
    let ranked = match &added {
        Some(e) => diagnosis.ranking.iter().find(|r| &r.effect == e),
        None if verdict == "unknown" => diagnosis.probe.as_ref(),
        None => None,
    };
    let (written, heldout_written) = if let Some(e) = &added {
        let after = ranked.map_or(f64::NAN, |r| r.heldout_mde_after_cm);
        (format!("with {e}"), after)
    } else if cmd_diagnose::control_is_better(diagnosis) {
        (
            "control refit".to_string(),
            diagnosis.control.heldout_mde_cm,
        )
    } else {
        ("as given".to_string(), diagnosis.backbone_as_given.mde_cm)
    };
    Ok(ChainRound {
        round: k,
        diagnosed_run: diagnosed.display().to_string(),
        model_diagnosed,
        verdict,
        added,
        shrinkage: ranked.map(|r| r.shrinkage),
        ci95: ranked.map(|r| r.ci95),
        heldout_mde_as_given_cm: diagnosis.backbone_as_given.mde_cm,
        heldout_mde_written_cm: heldout_written,
        written,
        written_run: written_run.display().to_string(),
        model_written,
        budget_options: (diagnosis.budget.as_ref()).map_or(String::new(), |b| b.options.clone()),
        wall_s: diagnosis.wall_s,
        runner_up: None,
    })
}

/// The model the chain started from and the final one, scored once on the `test` split when
/// the dataset has one; reports in `<out>/eval_test_{as_given,final}.json`.
fn test_scores(
    d: &DiagnoseArgs,
    out: &Path,
    final_run: &Path,
) -> anyhow::Result<Option<TestScores>> {
    let data = Dataset::open(&d.data)?;
    let episodes = data.split_indices(Split::Test).len();
    if episodes == 0 {
        return Ok(None);
    }
    let mde = |run: &Path, name: &str| -> anyhow::Result<f64> {
        let report = cmd_eval::run(&EvalArgs {
            data: d.data.clone(),
            run: run.to_path_buf(),
            split: Split::Test,
            protocol: d.protocol,
            json: Some(out.join(format!("eval_test_{name}.json"))),
            plot: Some(out.join(format!("eval_test_{name}.svg"))),
            no_emd: false,
            visual: false,
            horizon: None,
            autograd: false,
            save_predictions: None,
        })?;
        report.metrics["mde_cm"]["mean"]
            .as_f64()
            .context("an eval report without its MDE")
    };
    let before = mde(&d.run, "as_given")?;
    let after = mde(final_run, "final")?;
    Ok(Some(TestScores {
        episodes,
        mde_as_given_cm: before,
        mde_final_cm: after,
        shrinkage: 1.0 - after / before,
    }))
}

/// One line per round.
fn print_rounds(rounds: &[ChainRound]) {
    println!(
        "  round  verdict                    shrinkage [95 %]        held-out MDE, cm: as given -> written  wrote                       time"
    );
    for r in rounds {
        let verdict = match &r.added {
            Some(a) if *a != r.verdict => format!("{} (added {a})", r.verdict),
            _ => r.verdict.clone(),
        };
        let shrink = match (r.shrinkage, r.ci95) {
            (Some(s), Some([lo, hi])) => {
                format!("{:.1} % [{:.1}, {:.1}]", 100.0 * s, 100.0 * lo, 100.0 * hi)
            }
            _ => "-".to_string(),
        };
        println!(
            "  {:<6} {:<26} {:<23} {:>26.3} -> {:<8.3} {:<27} {:.0} s{}",
            r.round,
            verdict,
            shrink,
            r.heldout_mde_as_given_cm,
            r.heldout_mde_written_cm,
            r.written,
            r.wall_s,
            if r.budget_options.is_empty() {
                String::new()
            } else {
                format!(" ({})", r.budget_options)
            }
        );
    }
}

fn print_summary(chain: &ChainFile, d: &DiagnoseArgs) {
    println!("chain of diagnoses on {} from {}:", chain.data, chain.run);
    print_rounds(&chain.rounds);
    if let Some(stopped) = &chain.stopped {
        println!("  stopped at {stopped}");
    }
    let (Some(first), Some(last)) = (chain.rounds.first(), chain.rounds.last()) else {
        return;
    };
    let (mut model, mut run, mut mde) = (
        last.model_written.as_str(),
        last.written_run.as_str(),
        last.heldout_mde_written_cm,
    );
    if let Some(b) = &chain.branch {
        let took = chain
            .rounds
            .iter()
            .find(|r| r.round == b.fork_round)
            .and_then(|r| r.added.as_deref())
            .unwrap_or("-");
        println!(
            "  branch from round {}: {} instead of {took} (tied there), held-out {:.3} cm",
            b.fork_round, b.added, b.heldout_mde_start_cm
        );
        print_rounds(&b.rounds);
        if let Some(stopped) = &b.stopped {
            println!("  the branch stopped at {stopped}");
        }
        let (branch_run, branch_mde) = b.last();
        println!(
            "  final model from the {}: held-out {:.3} cm (main chain) against {:.3} cm (branch)",
            if b.chosen { "branch" } else { "main chain" },
            last.heldout_mde_written_cm,
            branch_mde
        );
        if b.chosen {
            run = branch_run;
            mde = branch_mde;
            model = b
                .rounds
                .last()
                .map_or(b.model_start.as_str(), |r| &r.model_written);
        }
    }
    println!(
        "  final model {model} in {run}{}",
        d.write_run.as_ref().map_or(String::new(), |w| format!(
            " (also written to {})",
            w.display()
        ))
    );
    println!(
        "  held-out (the val split, which every round chose on): {:.3} cm as given -> {mde:.3} cm final",
        first.heldout_mde_as_given_cm
    );
    match &chain.test {
        Some(t) => println!(
            "  test split ({} episodes, scored once): {:.3} cm as given -> {:.3} cm final ({:.1} % lower)",
            t.episodes,
            t.mde_as_given_cm,
            t.mde_final_cm,
            100.0 * t.shrinkage
        ),
        None => println!(
            "  note: the rounds chose on the val split, so its numbers flatter the final model; \
             run the chain on a `cargo xtask dev-split` copy, whose test split it scores once"
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Whether a verdict names an effect.
    fn adds_effect(verdict: &str) -> bool {
        gap::Candidate::parse(verdict).is_ok()
    }

    #[derive(clap::Parser)]
    enum Cmd {
        Gen(crate::cmd_gen::GenArgs),
        DevSplit(crate::cmd_import::DevSplitArgs),
        Fit(crate::cmd_fit::FitArgs),
        Chain(ChainArgs),
    }

    fn cmd(argv: &[&str]) -> Cmd {
        <Cmd as clap::Parser>::try_parse_from(std::iter::once("xtask").chain(argv.iter().copied()))
            .unwrap()
    }

    /// A small chain: the flag with a strong actuation delay its backbone lacks, tiny refits.
    fn chain_args(dir: &Path, out: &str, extra: &[&str]) -> ChainArgs {
        let data = dir.join("dev");
        let run = dir.join("fitted");
        let out = dir.join(out);
        let mut argv = vec![
            "chain",
            "--data",
            data.to_str().unwrap(),
            "--run",
            run.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--population",
            "4",
            "--generations",
            "3",
            "--samples",
            "2",
            "--resamples",
            "200",
            "--candidates",
            "actuation-delay,drag,bending",
            "--no-probe",
            "--quiet",
        ];
        argv.extend_from_slice(extra);
        match cmd(&argv) {
            Cmd::Chain(args) => args,
            _ => unreachable!(),
        }
    }

    fn prepare(dir: &Path) {
        let raw = dir.join("raw");
        let dev = dir.join("dev");
        let fitted = dir.join("fitted");
        let steps = [
            vec![
                "gen",
                "--object",
                "flag",
                "--preset",
                "fixture",
                "--effects",
                "actuation-delay",
                "--episodes",
                "6",
                "--val",
                "3",
                "--episodes-per-recording",
                "1",
                "--out",
                raw.to_str().unwrap(),
            ],
            vec![
                "dev-split",
                "--data",
                raw.to_str().unwrap(),
                "--out",
                dev.to_str().unwrap(),
                "--hold-out",
                "2",
            ],
            vec![
                "fit",
                "--data",
                dev.to_str().unwrap(),
                "--run",
                fitted.to_str().unwrap(),
                "--population",
                "4",
                "--generations",
                "4",
                "--samples",
                "2",
                "--quiet",
            ],
        ];
        for argv in steps {
            match cmd(&argv) {
                Cmd::Gen(a) => crate::cmd_gen::run(&a).unwrap(),
                Cmd::DevSplit(a) => crate::cmd_import::dev_split(&a).unwrap(),
                Cmd::Fit(a) => drop(crate::cmd_fit::run(&a).unwrap()),
                Cmd::Chain(_) => unreachable!(),
            }
        }
    }

    fn read_chain(out: &Path) -> ChainFile {
        serde_json::from_str(&std::fs::read_to_string(out.join("chain.json")).unwrap()).unwrap()
    }

    /// Each round diagnoses what the round before wrote, adds at most the effect its verdict
    /// names, and the chain stops at the first verdict that adds none; the start and final
    /// models are scored on the test split; a chain stopped by its round limit and resumed
    /// with a larger one ends where an uninterrupted chain does, and a finished chain run
    /// again redoes nothing.
    #[test]
    fn a_chain_adds_one_effect_a_round_and_resumes_where_it_stopped() {
        let dir = std::env::temp_dir().join(format!("pgrd-chain-{}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        prepare(&dir);

        let whole = run(&chain_args(&dir, "whole", &[])).unwrap();
        let rounds = &whole.rounds;
        // The delay the backbone lacks is strong: the chain adds at least it.
        assert!(rounds.len() >= 2, "{rounds:?}");
        assert_eq!(rounds[0].verdict, "actuation-delay");
        let (last, earlier) = rounds.split_last().unwrap();
        assert!(!adds_effect(&last.verdict), "{}", last.verdict);
        assert_eq!(last.added, None);
        for (k, r) in rounds.iter().enumerate() {
            assert_eq!(r.round, k + 1);
            if let Some(added) = &r.added {
                assert_eq!(added, &r.verdict);
                assert_eq!(r.written, format!("with {added}"));
                assert_eq!(r.model_written, format!("{}+{added}", r.model_diagnosed));
            } else {
                assert_eq!(r.model_written, r.model_diagnosed);
            }
        }
        for (r, next) in earlier.iter().zip(&rounds[1..]) {
            assert!(r.added.is_some());
            assert_eq!(next.diagnosed_run, r.written_run);
            assert_eq!(next.model_diagnosed, r.model_written);
            // The written model scores on the held-out episodes what its round said it would.
            let (a, b) = (next.heldout_mde_as_given_cm, r.heldout_mde_written_cm);
            assert!((a - b).abs() <= 1e-9 * b, "{a} vs {b}");
        }
        assert_eq!(whole.final_run.as_deref(), Some(last.written_run.as_str()));
        assert!(whole.stopped.as_deref().unwrap().contains("no effect left"));
        let test = whole.test.as_ref().expect("the dev split has a test split");
        assert_eq!(test.episodes, 3);
        assert!(test.mde_final_cm.is_finite() && test.mde_as_given_cm.is_finite());
        // The picture labels the start and every round's written model with its error.
        let svg = std::fs::read_to_string(dir.join("whole/chain.svg")).unwrap();
        let start = format!(
            "{}: {:.3}",
            rounds[0].model_diagnosed, rounds[0].heldout_mde_as_given_cm
        );
        assert!(svg.contains(&start), "{start}");
        let first = format!("+ actuation-delay: {:.3}", rounds[0].heldout_mde_written_cm);
        assert!(svg.contains(&first), "{first}");

        // A finished chain run again reads its rounds and redoes none.
        let report = dir.join("whole/round-1/report.json");
        let stamp = std::fs::metadata(&report).unwrap().modified().unwrap();
        let again = run(&chain_args(&dir, "whole", &[])).unwrap();
        assert_eq!(again.rounds, whole.rounds);
        assert_eq!(
            std::fs::metadata(&report).unwrap().modified().unwrap(),
            stamp
        );

        // Stopped by the round limit, then resumed: the same verdicts, models and scores.
        let limited = run(&chain_args(&dir, "limited", &["--max-rounds", "1"])).unwrap();
        assert_eq!(limited.rounds.len(), 1);
        assert!(limited.stopped.as_deref().unwrap().contains("round limit"));
        let resumed = run(&chain_args(&dir, "limited", &["--max-rounds", "9"])).unwrap();
        assert_eq!(resumed.rounds.len(), whole.rounds.len());
        for (a, b) in resumed.rounds.iter().zip(&whole.rounds) {
            assert_eq!(a.verdict, b.verdict);
            assert_eq!(a.model_written, b.model_written);
            assert_eq!(a.heldout_mde_written_cm, b.heldout_mde_written_cm);
        }
        assert_eq!(read_chain(&dir.join("limited")).rounds, resumed.rounds);

        // The final model never replaces the run the chain started from.
        let fitted = dir.join("fitted");
        let err = run(&chain_args(
            &dir,
            "other",
            &["--write-run", fitted.to_str().unwrap()],
        ))
        .unwrap_err();
        assert!(
            err.to_string().contains("is the diagnosed run itself"),
            "{err}"
        );
        assert!(!dir.join("other").exists());

        // Other settings on the same chain directory are refused, not mixed in.
        let err = run(&chain_args(&dir, "limited", &["--seed", "1"])).unwrap_err();
        assert!(
            err.to_string()
                .contains("other data, run or diagnosis settings"),
            "{err}"
        );
        let err = run(&chain_args(&dir, "whole", &["--branch-ties"])).unwrap_err();
        assert!(err.to_string().contains("other data"), "{err}");

        // With `--branch-ties` the main chain is the same; a branch only where a round tied.
        let ties = run(&chain_args(&dir, "ties", &["--branch-ties"])).unwrap();
        for (a, b) in ties.rounds.iter().zip(&whole.rounds) {
            assert_eq!(a.verdict, b.verdict);
            assert_eq!(a.heldout_mde_written_cm, b.heldout_mde_written_cm);
        }
        let fork = ties.rounds.iter().find(|r| r.runner_up.is_some());
        assert_eq!(
            fork.map(|r| r.round),
            ties.branch.as_ref().map(|b| b.fork_round)
        );
        if ties.branch.as_ref().is_none_or(|b| !b.chosen) {
            assert_eq!(
                ties.final_run,
                whole.final_run.map(|r| r.replace("whole", "ties"))
            );
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    /// `--add-past-unknown` carries the chain past an `unknown` whose library refits name an
    /// effect (the stored paper-magnet report: drag significant, the probe far better), and
    /// records what the written model scores; without it that round adds nothing.
    #[test]
    fn past_an_unknown_the_round_adds_the_library_verdict_only_when_asked() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../crates/gap/tests/data/paper-magnet-x4-seed0.json"
        );
        let d: Diagnosis = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        assert_eq!(d.verdict, "unknown");
        let record = |past: bool| {
            round_record(
                2,
                &d,
                past,
                Path::new("in"),
                "spring-mass".into(),
                Path::new("out"),
                "x".into(),
            )
            .unwrap()
        };
        let past = record(true);
        let drag = d.ranking.iter().find(|r| r.effect == "drag").unwrap();
        assert_eq!(past.added.as_deref(), Some("drag"));
        assert_eq!(past.written, "with drag");
        assert_eq!(past.heldout_mde_written_cm, drag.heldout_mde_after_cm);
        assert_eq!(past.shrinkage, Some(drag.shrinkage));
        let stop = record(false);
        assert_eq!(stop.added, None);
        assert_eq!(stop.shrinkage, d.probe.as_ref().map(|p| p.shrinkage));
        assert!(stop.written == "control refit" || stop.written == "as given");
    }

    /// A round's tie names its runner-up: the tied candidate of largest shrinkage other than
    /// the one added (the stored rope report: grasp slip and plasticity tied, plasticity
    /// chosen by the signature); no runner-up for an effect outside the tie or a report
    /// without one.
    #[test]
    fn the_runner_up_is_the_other_tied_candidate() {
        let read = |name: &str| -> Diagnosis {
            let path = format!(
                "{}/../crates/gap/tests/data/{name}",
                env!("CARGO_MANIFEST_DIR")
            );
            serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
        };
        let tied = read("rope-grasp-slip-x64-seed57.json");
        let c = |n: &str| gap::Candidate::parse(n).unwrap();
        assert_eq!(tied.verdict, "plasticity");
        let up = |added| cmd_diagnose::runner_up(&tied, c(added)).map(|u| u.name());
        assert_eq!(up("plasticity"), Some("grasp-slip"));
        assert_eq!(up("grasp-slip"), Some("plasticity"));
        assert_eq!(up("actuation-delay"), None);
        let untied = read("paper-magnet-x4-seed0.json");
        assert!(untied.tie_break.is_none());
        assert_eq!(cmd_diagnose::runner_up(&untied, c("drag")), None);
    }

    /// A made-up round: adds `added` (or nothing) and writes a model scoring `mde` cm.
    fn fake_round(k: usize, diagnosed: &Path, added: Option<&str>, mde: f64) -> ChainRound {
        ChainRound {
            round: k,
            diagnosed_run: diagnosed.display().to_string(),
            model_diagnosed: "m".into(),
            verdict: added.unwrap_or("none").into(),
            added: added.map(Into::into),
            shrinkage: None,
            ci95: None,
            heldout_mde_as_given_cm: mde + 0.1,
            heldout_mde_written_cm: mde,
            written: "w".into(),
            written_run: format!("branch/round-{k}/run"),
            model_written: "m".into(),
            budget_options: String::new(),
            wall_s: 0.0,
            runner_up: None,
        }
    }

    fn fork_at(round: usize) -> ChainBranch {
        ChainBranch {
            fork_round: round,
            added: "bending".into(),
            start_run: "round-2/run-runner-up".into(),
            model_start: "spring-mass+bending".into(),
            heldout_mde_start_cm: 3.0,
            rounds: Vec::new(),
            stopped: None,
            chosen: false,
        }
    }

    /// A branch goes on from its fork's model, numbering its rounds after the fork, until a
    /// round adds nothing or the round limit; it saves after every round, resumes after the
    /// rounds it has, and is chosen only when it ends lower on val than the main chain.
    #[test]
    fn a_branch_runs_from_its_fork_and_wins_only_when_lower() {
        // Round 3 adds drag, round 4 adds nothing (2.5 cm).
        let script = |k: usize, model: &Path| {
            let added = (k == 3).then_some("drag");
            Ok(fake_round(k, model, added, if k == 3 { 2.7 } else { 2.5 }))
        };
        let mut saved = Vec::new();
        let mut b = fork_at(2);
        let chosen = follow_branch(&mut b, 9, 2.6, script, |b| {
            saved.push(b.rounds.len());
            Ok(())
        })
        .unwrap();
        assert!(chosen && b.chosen);
        assert_eq!(saved, [1, 2]);
        let rounds: Vec<usize> = b.rounds.iter().map(|r| r.round).collect();
        assert_eq!(rounds, [3, 4]);
        assert_eq!(b.rounds[0].diagnosed_run, "round-2/run-runner-up");
        assert_eq!(b.rounds[1].diagnosed_run, b.rounds[0].written_run);
        assert!(b.stopped.as_deref().unwrap().contains("no effect left"));
        assert_eq!(b.last(), ("branch/round-4/run", 2.5));

        // Resumed: nothing is redone; a main chain at or below the branch keeps the final model.
        let again = follow_branch(&mut b, 9, 2.5, |_, _| panic!("redone"), |_| Ok(())).unwrap();
        assert!(!again && !b.chosen);

        // The round limit stops it; a fork at the limit has no rounds and its start competes.
        let mut limited = fork_at(2);
        follow_branch(&mut limited, 3, 1.0, script, |_| Ok(())).unwrap();
        assert_eq!(limited.rounds.len(), 1);
        assert!(
            limited
                .stopped
                .as_deref()
                .unwrap()
                .contains("round limit 3")
        );
        let mut at_limit = fork_at(2);
        let chosen = follow_branch(&mut at_limit, 2, 3.5, script, |_| Ok(())).unwrap();
        assert!(chosen && at_limit.rounds.is_empty());
        assert_eq!(at_limit.last(), ("round-2/run-runner-up", 3.0));
    }
}
