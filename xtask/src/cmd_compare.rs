//! `cargo xtask compare --before <eval.json> --after <eval.json>`: how much lower is one model's
//! error than another's on the same episodes, and how sure is that?
//!
//! Both files are `eval` reports of the same dataset, split and protocol. The statistic is the
//! paired shrinkage `1 − Σ after / Σ before` over episodes (each episode's error the mean over
//! its steps) with a 95 % percentile interval from a paired bootstrap (`gap::paired_shrinkage`,
//! the diagnosis's). Episodes cut from one recording overlap and are not independent samples;
//! `--block N` resamples runs of N consecutive episodes (whole recordings when a recording is
//! cut into N, as the reference world's are into 10) instead, a block bootstrap.
//! `--episodes A..B` keeps only the episodes with dataset indices in that range, e.g. the
//! recordings of a val split that no choice of the model ever saw. The MDE line also gives the
//! mean paired difference, its standard error and the episodes won, the numbers the PGRD rows'
//! adoption rule judges by on held-out training recordings.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use serde::{Deserialize, Serialize};

use crate::cmd_eval::EpisodeScore;
use crate::report::write_json;

/// Arguments of `compare`.
#[derive(clap::Args, Debug)]
pub struct CompareArgs {
    /// The reference model's eval report (e.g. `runs/rope/eval_val.json`, the backbone's).
    #[arg(long)]
    pub before: PathBuf,
    /// The compared model's eval report on the same episodes (e.g. `eval_pgrd_val.json`).
    #[arg(long)]
    pub after: PathBuf,
    /// Resample blocks of this many consecutive episodes instead of single ones (episodes of
    /// one recording share frames; the reference world cuts each recording into 10).
    #[arg(long, default_value_t = 1)]
    pub block: usize,
    /// Compare only the episodes whose dataset index lies in `A..B` (half-open, as the
    /// reports' `per_episode[].episode`), e.g. `120..160` for the val episodes after the
    /// first 20 of a 100-episode training split.
    #[arg(long, value_parser = parse_range)]
    pub episodes: Option<EpisodeRange>,
    /// Bootstrap resamples.
    #[arg(long, default_value_t = 2000)]
    pub resamples: usize,
    /// Seed of the resampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Also write the comparison as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Draw it as SVG here: both models' MDE per step (when every episode is compared) and
    /// each episode's MDE under one against the other.
    #[arg(long)]
    pub plot: Option<PathBuf>,
}

/// Dataset indices `start..end` (half-open) of the episodes to compare.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct EpisodeRange {
    /// First index kept.
    pub start: usize,
    /// One past the last index kept.
    pub end: usize,
}

/// Parses `A..B` with `A < B`.
fn parse_range(text: &str) -> Result<EpisodeRange, String> {
    let (a, b) = text
        .split_once("..")
        .ok_or_else(|| format!("expected A..B (e.g. 120..160), got {text:?}"))?;
    let index = |s: &str| {
        s.trim()
            .parse::<usize>()
            .map_err(|e| format!("{s:?} in {text:?}: {e}"))
    };
    let (start, end) = (index(a)?, index(b)?);
    if start >= end {
        return Err(format!("{text:?} is empty: A must be below B"));
    }
    Ok(EpisodeRange { start, end })
}

/// What `compare` (and `screen`) read of an eval report.
#[derive(Deserialize)]
pub(crate) struct EvalFile {
    pub(crate) model: String,
    /// Absent in reports written before it was recorded.
    #[serde(default)]
    pub(crate) dataset: Option<String>,
    pub(crate) object: String,
    pub(crate) split: String,
    pub(crate) protocol: String,
    pub(crate) steps: usize,
    #[serde(default)]
    pub(crate) per_episode: Option<Vec<EpisodeScore>>,
    #[serde(default)]
    pub(crate) diverged: Option<usize>,
    /// The report's summaries (`mde_cm`, `deform_l1_m`, ...), each with its `mean`.
    #[serde(default)]
    pub(crate) metrics: serde_json::Value,
    /// Per metric, its mean over the report's episodes at each step.
    #[serde(default)]
    pub(crate) per_step_cm: serde_json::Value,
}

/// One metric's paired comparison.
#[derive(Debug, Serialize)]
pub struct MetricComparison {
    /// Metric name as in the eval report (`mde_cm`, `chamfer_cm`, `emd_cm`).
    pub metric: String,
    /// Mean over episodes of the reference model's error, cm.
    pub before_cm: f64,
    /// Mean over episodes of the compared model's error, cm.
    pub after_cm: f64,
    /// `1 − Σ after / Σ before` (positive: the compared model errs less).
    pub shrinkage: f64,
    /// 95 % percentile interval of the shrinkage over resamples.
    pub ci95: [f64; 2],
    /// Mean over episodes of `before − after`, cm (positive: the compared model errs less).
    pub mean_difference_cm: f64,
    /// Standard error of that mean from the per-episode differences' spread, cm
    /// (`residual::paired_difference`); absent for a single episode. The adoption rule of the
    /// PGRD rows (`docs/RESULTS.md`) asks for a mean difference above one of these on held-out
    /// training recordings.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub difference_se_cm: Option<f64>,
    /// Episodes on which the compared model's error is lower.
    pub lower_after: usize,
}

/// The whole comparison (`--json`).
#[derive(Debug, Serialize)]
pub struct Comparison {
    /// Model names, reference first.
    pub models: [String; 2],
    /// Object both reports scored.
    pub object: String,
    /// Split both reports scored.
    pub split: String,
    /// Protocol of both reports.
    pub protocol: String,
    /// Episodes paired.
    pub episodes: usize,
    /// The range of dataset indices kept (`--episodes`); absent: every episode.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub episode_range: Option<EpisodeRange>,
    /// Episodes per resampled block (the last one may be shorter).
    pub block: usize,
    /// Blocks resampled.
    pub blocks: usize,
    /// Bootstrap resamples.
    pub resamples: usize,
    /// Seed of the resampling.
    pub seed: u64,
    /// MDE, two-sided Chamfer and (when both reports have it) EMD.
    pub metrics: Vec<MetricComparison>,
}

/// A note when the two reports name different datasets (compared as the directories they
/// name): episodes are paired by index, which pairs nothing real across two datasets unless
/// one is a copy of the other.
fn other_datasets(before: &EvalFile, after: &EvalFile) -> Option<String> {
    let (a, b) = (before.dataset.as_ref()?, after.dataset.as_ref()?);
    let same = match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
        (Ok(x), Ok(y)) => x == y,
        _ => a == b,
    };
    (!same).then(|| {
        format!(
            "the reports were made on different datasets ({a} and {b}); the comparison pairs \
             their episodes by index, which is right only if one dataset is a copy of the other"
        )
    })
}

/// Fewer resampling units than this make the interval coarse (with k units a bootstrap has at
/// most C(2k − 1, k) distinct resamples, 10 for k = 3), so the command says so.
const FEW_UNITS: usize = 10;

pub fn run(args: &CompareArgs) -> anyhow::Result<()> {
    let before = read_eval(&args.before)?;
    let after = read_eval(&args.after)?;
    if let Some(note) = other_datasets(&before, &after) {
        eprintln!("note: {note}");
    }
    let c = compare(
        &before,
        &after,
        args.episodes,
        args.block,
        args.resamples,
        args.seed,
    )
    .with_context(|| format!("{} vs {}", args.before.display(), args.after.display()))?;
    let range = c
        .episode_range
        .map(|r| format!(" (dataset indices {}..{})", r.start, r.end))
        .unwrap_or_default();
    println!(
        "{} ({} split, {} protocol): {} -> {}, {} episodes{range} in {} resampled block(s) of {}",
        c.object, c.split, c.protocol, c.models[0], c.models[1], c.episodes, c.blocks, c.block
    );
    for m in &c.metrics {
        println!(
            "  {:<11} {:>8.3} -> {:>8.3} cm   shrinkage {:+6.1} %   95 % interval [{:+.1}, {:+.1}] %",
            m.metric,
            m.before_cm,
            m.after_cm,
            100.0 * m.shrinkage,
            100.0 * m.ci95[0],
            100.0 * m.ci95[1],
        );
        if m.metric == "mde_cm" {
            let se = match m.difference_se_cm {
                Some(se) if se > 0.0 => format!(
                    " ± {se:.3} (standard error; {:+.2} of them)",
                    m.mean_difference_cm / se
                ),
                _ => String::new(),
            };
            println!(
                "  {:<11} paired before − after {:+.3} cm{se}, lower after on {} of {} episodes",
                "", m.mean_difference_cm, m.lower_after, c.episodes
            );
        }
    }
    if c.blocks < FEW_UNITS {
        println!(
            "  note: only {} resampling unit(s); the interval is coarse and says little",
            c.blocks
        );
    }
    if c.block == 1 {
        println!(
            "  note: single episodes resampled; if they are cut from fewer, longer recordings \
             they overlap and the interval is too narrow (--block)"
        );
    }
    if let Some(path) = &args.json {
        write_json(path, &c)?;
    }
    if let Some(path) = &args.plot {
        plot(path, &before, &after, &c, args.episodes.is_none())?;
    }
    Ok(())
}

/// Writes `compare --plot`: the per-step curves only when every episode is compared (the
/// reports' per-step means are over all their episodes).
fn plot(
    path: &Path,
    before: &EvalFile,
    after: &EvalFile,
    c: &Comparison,
    all_episodes: bool,
) -> anyhow::Result<()> {
    let curve = |f: &EvalFile| -> Option<Vec<f64>> {
        f.per_step_cm["mde_cm"]
            .as_array()?
            .iter()
            .map(serde_json::Value::as_f64)
            .collect()
    };
    let curves = match (curve(before), curve(after)) {
        (Some(b), Some(a)) if all_episodes => Some((b, a)),
        _ => None,
    };
    let in_range = |e: &&EpisodeScore| {
        c.episode_range
            .is_none_or(|r| (r.start..r.end).contains(&e.episode))
    };
    let mde = |f: &EvalFile| -> Vec<f64> {
        f.per_episode
            .iter()
            .flatten()
            .filter(in_range)
            .map(|e| e.mde_cm)
            .collect()
    };
    let pairs: Vec<(f64, f64)> = mde(before).into_iter().zip(mde(after)).collect();
    crate::plots::compare_svg(
        path,
        &crate::plots::CompareCurves {
            title: format!("{} ({} split, {} protocol)", c.object, c.split, c.protocol),
            labels: [
                format!("before: {}", c.models[0]),
                format!("after: {}", c.models[1]),
            ],
            per_step: curves.as_ref().map(|(b, a)| [b.as_slice(), a.as_slice()]),
            pairs: &pairs,
        },
    )
}

pub(crate) fn read_eval(path: &Path) -> anyhow::Result<EvalFile> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{} is not an eval report", path.display()))
}

/// Pairs the two reports' episodes and compares each metric both report.
pub(crate) fn compare(
    before: &EvalFile,
    after: &EvalFile,
    range: Option<EpisodeRange>,
    block: usize,
    resamples: usize,
    seed: u64,
) -> anyhow::Result<Comparison> {
    for (what, a, b) in [
        ("object", &before.object, &after.object),
        ("split", &before.split, &after.split),
        ("protocol", &before.protocol, &after.protocol),
    ] {
        if a != b {
            bail!("the reports differ in {what} ({a} against {b})");
        }
    }
    if before.steps != after.steps {
        bail!(
            "the reports' rollouts differ in length ({} against {} steps)",
            before.steps,
            after.steps
        );
    }
    let episodes = |f: &EvalFile| -> anyhow::Result<Vec<EpisodeScore>> {
        f.per_episode.clone().with_context(|| {
            format!(
                "the {} report has no per-episode errors (written by an older version: run \
                 `eval` again)",
                f.model
            )
        })
    };
    let (mut b, mut a) = (episodes(before)?, episodes(after)?);
    if let Some(r) = range {
        for v in [&mut b, &mut a] {
            v.retain(|e| (r.start..r.end).contains(&e.episode));
        }
        if b.is_empty() && a.is_empty() {
            bail!(
                "no episode of the reports has a dataset index in {}..{}",
                r.start,
                r.end
            );
        }
    }
    let ids = |v: &[EpisodeScore]| v.iter().map(|e| e.episode).collect::<Vec<_>>();
    if ids(&b) != ids(&a) {
        let only = |x: &[EpisodeScore], y: &[EpisodeScore]| {
            let y = ids(y);
            ids(x)
                .into_iter()
                .filter(|i| !y.contains(i))
                .collect::<Vec<_>>()
        };
        bail!(
            "the reports scored different episodes (only before: {:?}; only after: {:?}); a \
             diverged rollout is left out of its report",
            only(&b, &a),
            only(&a, &b)
        );
    }
    if b.is_empty() {
        bail!("the reports have no episodes");
    }
    if block == 0 {
        bail!("--block must be at least 1");
    }
    let mut metrics = Vec::new();
    type Field = fn(&EpisodeScore) -> Option<f64>;
    let fields: [(&str, Field); 3] = [
        ("mde_cm", |e| Some(e.mde_cm)),
        ("chamfer_cm", |e| Some(e.chamfer_cm)),
        ("emd_cm", |e| e.emd_cm),
    ];
    for (name, get) in fields {
        let (Some(x), Some(y)) = (
            b.iter().map(get).collect::<Option<Vec<f64>>>(),
            a.iter().map(get).collect::<Option<Vec<f64>>>(),
        ) else {
            continue;
        };
        // Resampling blocks of episodes with their summed errors is the block bootstrap of
        // the same ratio, since the shrinkage only needs the sums.
        let sums = |v: &[f64]| {
            v.chunks(block)
                .map(|c| c.iter().sum())
                .collect::<Vec<f64>>()
        };
        let s = gap::paired_shrinkage(&sums(&x), &sums(&y), resamples, seed)
            .with_context(|| name.to_string())?;
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        // The statistic `train`'s held-out selection judges by (`residual::clearly_better`).
        let difference_se_cm = residual::paired_difference(&y, &x).map(|(_, se)| se);
        let (before_cm, after_cm) = (mean(&x), mean(&y));
        metrics.push(MetricComparison {
            metric: name.into(),
            before_cm,
            after_cm,
            shrinkage: s.shrinkage,
            ci95: s.ci95,
            mean_difference_cm: before_cm - after_cm,
            difference_se_cm,
            lower_after: x.iter().zip(&y).filter(|(p, q)| p > q).count(),
        });
    }
    Ok(Comparison {
        models: [before.model.clone(), after.model.clone()],
        object: before.object.clone(),
        split: before.split.clone(),
        protocol: before.protocol.clone(),
        episodes: b.len(),
        episode_range: range,
        block,
        blocks: b.len().div_ceil(block),
        resamples,
        seed,
        metrics,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(model: &str, mde: &[f64], emd: bool) -> EvalFile {
        EvalFile {
            model: model.into(),
            object: "rope".into(),
            split: "val".into(),
            protocol: "paper".into(),
            steps: 37,
            per_episode: Some(
                mde.iter()
                    .enumerate()
                    .map(|(i, &m)| EpisodeScore {
                        episode: 100 + i,
                        mde_cm: m,
                        chamfer_cm: 2.0 * m,
                        emd_cm: emd.then_some(m),
                    })
                    .collect(),
            ),
            dataset: None,
            diverged: Some(0),
            metrics: serde_json::Value::Null,
            per_step_cm: serde_json::Value::Null,
        }
    }

    #[test]
    fn reports_of_two_datasets_get_a_note_and_of_one_dataset_none() {
        let with = |d: &str| EvalFile {
            dataset: Some(d.into()),
            ..report("spring-mass", &[1.0], false)
        };
        let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/../fixtures/rope");
        let dotted = concat!(env!("CARGO_MANIFEST_DIR"), "/../fixtures/./rope/");
        assert!(other_datasets(&with(fixture), &with(dotted)).is_none());
        let other = concat!(env!("CARGO_MANIFEST_DIR"), "/../fixtures/flag");
        let note = other_datasets(&with(fixture), &with(other)).unwrap();
        assert!(note.contains("different datasets"), "{note}");
        // Older reports name no dataset: nothing to say.
        assert!(other_datasets(&report("a", &[1.0], false), &with(other)).is_none());
    }

    #[test]
    fn halved_errors_shrink_by_half() {
        let b = report("spring-mass", &[2.0, 4.0, 1.0, 3.0], true);
        let a = report("pgrd", &[1.0, 2.0, 0.5, 1.5], true);
        let c = compare(&b, &a, None, 1, 500, 3).unwrap();
        assert_eq!(c.metrics.len(), 3);
        for m in &c.metrics {
            assert!((m.shrinkage - 0.5).abs() < 1e-12, "{m:?}");
            // Every resample halves the error too.
            assert!((m.ci95[0] - 0.5).abs() < 1e-12 && (m.ci95[1] - 0.5).abs() < 1e-12);
        }
        assert!((c.metrics[0].before_cm - 2.5).abs() < 1e-12);
        assert!((c.metrics[0].after_cm - 1.25).abs() < 1e-12);
    }

    #[test]
    fn one_block_gives_a_point_interval_and_single_episodes_do_not() {
        let b = report("spring-mass", &[2.0, 2.0, 2.0, 2.0, 2.0, 2.0], false);
        let a = report("pgrd", &[1.0, 3.0, 1.5, 2.5, 1.0, 2.2], false);
        let whole = compare(&b, &a, None, 6, 500, 0).unwrap();
        assert_eq!((whole.blocks, whole.metrics.len()), (1, 2));
        let m = &whole.metrics[0];
        assert_eq!(m.ci95, [m.shrinkage, m.shrinkage]);
        let single = compare(&b, &a, None, 1, 500, 0).unwrap();
        let m1 = &single.metrics[0];
        assert_eq!(m1.shrinkage, m.shrinkage);
        assert!(
            m1.ci95[0] < m1.shrinkage && m1.shrinkage < m1.ci95[1],
            "{m1:?}"
        );
        // Blocks of 4 leave a short last block: 2 blocks.
        assert_eq!(compare(&b, &a, None, 4, 10, 0).unwrap().blocks, 2);
    }

    #[test]
    fn mismatched_reports_are_refused_with_the_reason() {
        let b = report("spring-mass", &[2.0, 2.0, 2.0], true);
        let mut a = report("pgrd", &[1.0, 1.0], true);
        let e = compare(&b, &a, None, 1, 10, 0).unwrap_err().to_string();
        assert!(e.contains("only before: [102]"), "{e}");
        a = report("pgrd", &[1.0, 1.0, 1.0], true);
        a.split = "train".into();
        let e = compare(&b, &a, None, 1, 10, 0).unwrap_err().to_string();
        assert!(e.contains("split"), "{e}");
        a = report("pgrd", &[1.0, 1.0, 1.0], true);
        a.per_episode = None;
        let e = compare(&b, &a, None, 1, 10, 0).unwrap_err().to_string();
        assert!(e.contains("run `eval` again"), "{e}");
        a = report("pgrd", &[1.0, 1.0, 1.0], true);
        assert!(compare(&b, &a, None, 0, 10, 0).is_err());
        a.per_episode = Some(Vec::new());
        let mut b0 = report("spring-mass", &[], true);
        b0.per_episode = Some(Vec::new());
        assert!(compare(&b0, &a, None, 1, 10, 0).is_err());
    }

    #[test]
    fn a_range_keeps_only_its_episodes() {
        // Episodes 100..106; the first two are twice as bad after, the rest halved.
        let b = report("spring-mass", &[1.0, 1.0, 2.0, 2.0, 2.0, 2.0], false);
        let a = report("pgrd", &[2.0, 2.0, 1.0, 1.0, 1.0, 1.0], false);
        let r = parse_range("102..106").unwrap();
        let c = compare(&b, &a, Some(r), 1, 200, 0).unwrap();
        assert_eq!((c.episodes, c.episode_range), (4, Some(r)));
        assert!((c.metrics[0].shrinkage - 0.5).abs() < 1e-12);
        let all = compare(&b, &a, None, 1, 200, 0).unwrap();
        assert!((all.metrics[0].shrinkage - (1.0 - 8.0 / 10.0)).abs() < 1e-12);
        let e = compare(&b, &a, Some(parse_range("0..100").unwrap()), 1, 10, 0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("0..100"), "{e}");
        for bad in ["", "5", "7..7", "9..3", "a..4", "1..b"] {
            assert!(parse_range(bad).is_err(), "{bad:?}");
        }
        assert_eq!(
            parse_range(" 3 .. 8").unwrap(),
            EpisodeRange { start: 3, end: 8 }
        );
        // The picture of a range counts its episodes only, and leaves out the per-step
        // curves, which are means over every episode of a report.
        let dir = std::env::temp_dir().join(format!("pgrd-compare-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let with_steps = |mut f: EvalFile| {
            f.per_step_cm = serde_json::json!({ "mde_cm": [1.0, 2.0] });
            f
        };
        let (b, a) = (with_steps(b), with_steps(a));
        let path = dir.join("c.svg");
        plot(&path, &b, &a, &c, false).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.contains("after: pgrd lower on 4 of 4"), "{svg}");
        assert!(!svg.contains("MDE per step"));
        plot(&path, &b, &a, &all, true).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.contains("after: pgrd lower on 4 of 6"), "{svg}");
        assert!(svg.contains("MDE per step"));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn the_paired_difference_has_its_standard_error_and_wins() {
        // Differences before − after: 1, 0, -1, 2 (mean 0.5, sample sd sqrt(5/3)).
        let b = report("pgrd", &[3.0, 2.0, 1.0, 4.0], false);
        let a = report("pgrd", &[2.0, 2.0, 2.0, 2.0], false);
        let c = compare(&b, &a, None, 1, 10, 0).unwrap();
        let m = &c.metrics[0];
        assert!((m.mean_difference_cm - 0.5).abs() < 1e-12, "{m:?}");
        let se = (5.0f64 / 3.0).sqrt() / 2.0;
        assert!((m.difference_se_cm.unwrap() - se).abs() < 1e-12, "{m:?}");
        assert_eq!(m.lower_after, 2);
        // A single episode has no spread to judge by.
        let one = compare(
            &report("pgrd", &[3.0], false),
            &report("pgrd", &[2.0], false),
            None,
            1,
            10,
            0,
        )
        .unwrap();
        assert_eq!(one.metrics[0].difference_se_cm, None);
        assert_eq!(one.metrics[0].lower_after, 1);
    }

    #[test]
    fn emd_is_compared_only_when_both_have_it() {
        let b = report("spring-mass", &[2.0, 3.0], true);
        let a = report("pgrd", &[1.0, 2.0], false);
        let c = compare(&b, &a, None, 1, 10, 0).unwrap();
        let names: Vec<_> = c.metrics.iter().map(|m| m.metric.as_str()).collect();
        assert_eq!(names, ["mde_cm", "chamfer_cm"]);
    }
}
