//! `cargo xtask screen`: a run's backbone with one effect added at fixed settings, each scored on
//! a split against the backbone without it, with no refit.
//!
//! The diagnosis refits an effect with the backbone's parameters; a screen asks the cheaper
//! question first: does the model as fitted get better with the effect at this strength? Each
//! setting becomes a run directory under `--out` (`<effect>_<v1>[_<v2>]/backbone.json`, the run's
//! backbone with the effect appended to its `effects`), scored by `eval` exactly as `eval`
//! scores any run, so `eval --split test` on the kept setting's directory scores it once more.
//! `without/` holds the run's backbone unchanged. Each setting is compared with `without` by
//! `compare`'s paired (block) bootstrap. A residual network in the run is not used: it was
//! trained on the backbone without the effect.
//!
//! Resumable: a setting whose directory already holds the same backbone and an eval report of
//! the same dataset, split, protocol and metrics is read, not scored again.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use dataset::{Dataset, Split};
use gap::{BaseEffect, Candidate};
use scene::Protocol;
use serde::Serialize;

use crate::cmd_compare::{EvalFile, MetricComparison, compare, read_eval};
use crate::cmd_eval::EvalArgs;
use crate::common::{ProtocolArg, backbone_path, read_backbone};
use crate::report::write_json;

/// Arguments of `screen`.
#[derive(clap::Args, Debug)]
pub struct ScreenArgs {
    /// Dataset directory.
    #[arg(long)]
    pub data: PathBuf,
    /// Run directory holding backbone.json (the model the effect is added to).
    #[arg(long)]
    pub run: PathBuf,
    /// The effect added: a library effect or an extra (`gravity-scale`; `bending-damping` and
    /// `twist` on `chain` datasets), not one the run's model already has.
    #[arg(long)]
    pub effect: String,
    /// The settings scored, comma-separated, each in the units and ranges of the effect's
    /// parameters (`docs/gap.md`, Candidates); an effect with several parameters takes each
    /// setting's values colon-separated in their order, e.g. `--effect plasticity --values
    /// 0.01:5,0.02:20`.
    #[arg(
        long,
        required = true,
        value_delimiter = ',',
        allow_hyphen_values = true
    )]
    pub values: Vec<String>,
    /// Split scored (a development copy's `val`, from `dev-split`, keeps `test` for the kept
    /// setting).
    #[arg(long, default_value = "val")]
    pub split: Split,
    /// Evaluation protocol.
    #[arg(long, value_enum, default_value_t = ProtocolArg::Paper)]
    pub protocol: ProtocolArg,
    /// Directory of the screen: one run per setting, `without/`, and `screen.json`.
    #[arg(long)]
    pub out: PathBuf,
    /// Resample blocks of this many consecutive episodes (as `compare --block`).
    #[arg(long, default_value_t = 1)]
    pub block: usize,
    /// Bootstrap resamples.
    #[arg(long, default_value_t = 2000)]
    pub resamples: usize,
    /// Seed of the resampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Skip exact EMD (faster on large clouds).
    #[arg(long)]
    pub no_emd: bool,
    /// Also score values outside the ranges the diagnosis searches (finite, and positive for
    /// a parameter searched on a log scale); a strength the integrator cannot hold shows as
    /// diverged rollouts in its row.
    #[arg(long)]
    pub beyond_range: bool,
}

/// One scored model of a screen.
#[derive(Debug, Serialize)]
pub struct ScreenRow {
    /// The effect's parameter values (empty for the model without it).
    pub values: Vec<f64>,
    /// The setting's run directory.
    pub run: String,
    /// Its eval report.
    pub eval: String,
    /// MDE over the split, cm (absent when the setting failed).
    pub mde_cm: Option<f64>,
    /// DEFORM's `deform_l1_m` (the `deform` protocol only), m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub deform_l1_m: Option<f64>,
    /// Against the model without the effect, per metric (absent for that model and for a
    /// failed setting).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub against_without: Vec<MetricComparison>,
    /// The report was already there (a resumed screen) and was read, not scored again.
    pub reused: bool,
    /// Why the setting has no scores (e.g. rollouts that diverged).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// `screen.json`.
#[derive(Debug, Serialize)]
pub struct ScreenReport {
    /// The effect added.
    pub effect: String,
    /// Its parameters' names, in the order of each row's values.
    pub parameters: Vec<String>,
    /// The screened run.
    pub run: String,
    /// The model without the effect (`spring-mass+...`).
    pub model: String,
    /// Dataset directory.
    pub dataset: String,
    /// Split scored.
    pub split: String,
    /// Protocol.
    pub protocol: String,
    /// Episodes per resampled block.
    pub block: usize,
    /// Bootstrap resamples.
    pub resamples: usize,
    /// Seed of the resampling.
    pub seed: u64,
    /// The run's model as it is.
    pub without: ScreenRow,
    /// One row per setting, in the order given.
    pub settings: Vec<ScreenRow>,
    /// Index into `settings` of the lowest MDE (absent when every setting failed).
    pub lowest_mde: Option<usize>,
    /// Wall time, s.
    pub wall_s: f64,
}

/// The settings of `--values`, each checked against the effect's parameter count and ranges
/// (with `beyond_range`, only finite and, on a log scale, positive; a note for each value
/// outside its range).
fn parse_settings(
    effect: Candidate,
    values: &[String],
    beyond_range: bool,
) -> anyhow::Result<Vec<BaseEffect>> {
    if values.is_empty() {
        bail!("--values: give at least one setting");
    }
    let params = effect.parameters();
    values
        .iter()
        .map(|v| {
            let spec = format!("{}={}", effect.name(), v.trim());
            if !beyond_range {
                return BaseEffect::parse(&spec).with_context(|| {
                    format!(
                        "--values '{v}' (the ranges are the diagnosis's search box; \
                         --beyond-range scores other values too)"
                    )
                });
            }
            let x = v
                .split(':')
                .map(|x| x.trim().parse::<f64>())
                .collect::<Result<Vec<_>, _>>()
                .map_err(|_| anyhow::anyhow!("--values '{v}': not a number"))?;
            if x.len() != params.len() {
                bail!(
                    "--values '{v}': {} takes {} value(s), got {}",
                    effect.name(),
                    params.len(),
                    x.len()
                );
            }
            for (p, &x) in params.iter().zip(&x) {
                let log = matches!(p.scale, cmaes::Scale::Log);
                if !x.is_finite() || (log && x <= 0.0) {
                    bail!(
                        "--values '{v}': {} = {x} must be finite{}",
                        p.name,
                        if log { " and positive" } else { "" }
                    );
                }
                if !(p.lower..=p.upper).contains(&x) {
                    eprintln!(
                        "note: {} {} = {x} lies outside the diagnosis's range [{}, {}]",
                        effect.name(),
                        p.name,
                        p.lower,
                        p.upper
                    );
                }
            }
            Ok(BaseEffect { effect, values: x })
        })
        .collect()
}

/// A setting's directory name: `<effect>_<v1>[_<v2>...]`.
fn setting_dir(effect: &BaseEffect) -> String {
    std::iter::once(effect.effect.name().to_string())
        .chain(effect.values.iter().map(|v| v.to_string()))
        .collect::<Vec<_>>()
        .join("_")
}

/// The eval report `dir` already holds for this exact backbone and scoring, if any.
fn reusable(dir: &Path, backbone: &str, json: &Path, want: &Want) -> Option<EvalFile> {
    // Compared as text: a JSON value read back holds an f32 as its shortest decimal, not as
    // the f64 it widens to.
    let old = std::fs::read_to_string(backbone_path(dir)).ok()?;
    let report = read_eval(json).ok()?;
    let same = old == backbone
        && report.dataset.as_deref() == Some(want.dataset.as_str())
        && report.split == want.split
        && report.protocol == want.protocol
        && report.diverged == Some(0)
        && report.metrics.get("emd_cm").is_some() == want.emd;
    same.then_some(report)
}

/// What a reusable report must have been scored on.
struct Want {
    dataset: String,
    split: String,
    protocol: String,
    emd: bool,
}

/// Writes `backbone` into `dir` and scores it with `eval` (or reads the report a previous
/// screen left there).
fn score(
    args: &ScreenArgs,
    dir: &Path,
    backbone: &crate::common::BackboneFile,
    want: &Want,
) -> anyhow::Result<(EvalFile, bool)> {
    let json = eval_path(dir, args.split);
    // The text `write_json` writes.
    let text = serde_json::to_string_pretty(backbone)?;
    if let Some(report) = reusable(dir, &text, &json, want) {
        println!("  (read {}: scored by an earlier screen)", json.display());
        return Ok((report, true));
    }
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    write_json(&backbone_path(dir), backbone)?;
    crate::cmd_eval::run(&EvalArgs {
        data: args.data.clone(),
        run: dir.to_path_buf(),
        split: args.split,
        protocol: args.protocol,
        json: Some(json.clone()),
        plot: None,
        no_emd: args.no_emd,
        visual: false,
        horizon: None,
        autograd: false,
        save_predictions: None,
    })?;
    Ok((read_eval(&json)?, false))
}

/// The eval report a setting's run directory holds for `split`.
fn eval_path(dir: &Path, split: Split) -> PathBuf {
    dir.join(format!("eval_{split}.json"))
}

impl ScreenRow {
    /// The row of the model at `values` in `dir`, before it is scored.
    fn unscored(values: Vec<f64>, dir: &Path, split: Split) -> Self {
        ScreenRow {
            values,
            run: dir.display().to_string(),
            eval: eval_path(dir, split).display().to_string(),
            mde_cm: None,
            deform_l1_m: None,
            against_without: Vec::new(),
            reused: false,
            error: None,
        }
    }
}

fn mean_of(report: &EvalFile, key: &str) -> Option<f64> {
    report.metrics.get(key)?.get("mean")?.as_f64()
}

/// Runs the screen and writes `<out>/screen.json`.
pub fn run(args: &ScreenArgs) -> anyhow::Result<ScreenReport> {
    let t0 = Instant::now();
    let data = Dataset::open(&args.data)?;
    let backbone = read_backbone(&args.run)?;
    backbone.note_other_object(&data);
    let effect = Candidate::parse(args.effect.trim()).with_context(|| {
        let names: Vec<_> = Candidate::LIBRARY
            .iter()
            .chain(&Candidate::EXTRA)
            .map(|c| c.name())
            .collect();
        format!("--effect: one of {}", names.join(", "))
    })?;
    if effect == Candidate::ExternalField {
        bail!(
            "--effect: external-field is the diagnosis's probe for unknown gaps, not an effect to add"
        );
    }
    if let Some(b) = backbone.effects.iter().find(|b| b.effect == effect) {
        bail!(
            "the run's model already has {} ({}); screen it from a run without it",
            effect.name(),
            b.label()
        );
    }
    if matches!(effect, Candidate::BendingDamping | Candidate::Twist)
        && data.meta.structure != dataset::Structure::Chain
    {
        bail!(
            "{} acts along a cable's order and needs a `chain` dataset (e.g. `xtask import \
             deform`); {} is not one",
            effect.name(),
            args.data.display()
        );
    }
    let settings = parse_settings(effect, &args.values, args.beyond_range)?;
    if args.block == 0 {
        bail!("--block must be at least 1");
    }
    if args.out.join("without").canonicalize().ok() == args.run.canonicalize().ok() {
        bail!("--out: the screen would overwrite the run it screens; give another directory");
    }
    let protocol: Protocol = args.protocol.into();
    let want = Want {
        dataset: args.data.display().to_string(),
        split: args.split.to_string(),
        protocol: protocol.name().to_string(),
        emd: !args.no_emd,
    };
    let n = settings.len();
    println!(
        "screen: {} + {} at {n} setting(s) on {} ({}), each against the model without it",
        backbone.label(),
        effect.name(),
        data.meta.object,
        args.split
    );
    if args.run.join("residual.safetensors").exists() {
        println!(
            "note: the run's residual network is not used (it was trained on the backbone \
             without the effect); every row scores a backbone"
        );
    }
    println!("[0/{n}] without {}", effect.name());
    let without_dir = args.out.join("without");
    let (before, reused) = score(args, &without_dir, &backbone, &want)
        .context("the run's model without the effect")?;
    let without = ScreenRow {
        mde_cm: mean_of(&before, "mde_cm"),
        deform_l1_m: mean_of(&before, "deform_l1_m"),
        reused,
        ..ScreenRow::unscored(Vec::new(), &without_dir, args.split)
    };
    let mut rows = Vec::new();
    for (k, setting) in settings.iter().enumerate() {
        println!("[{}/{n}] {}", k + 1, setting.label());
        let dir = args.out.join(setting_dir(setting));
        let mut model = backbone.clone();
        model.effects.push(setting.clone());
        let mut row = ScreenRow::unscored(setting.values.clone(), &dir, args.split);
        match score(args, &dir, &model, &want).and_then(|(after, reused)| {
            let c = compare(&before, &after, None, args.block, args.resamples, args.seed)?;
            Ok((after, reused, c))
        }) {
            Ok((after, reused, c)) => {
                row.mde_cm = mean_of(&after, "mde_cm");
                row.deform_l1_m = mean_of(&after, "deform_l1_m");
                row.against_without = c.metrics;
                row.reused = reused;
            }
            Err(e) => {
                eprintln!("warning: {}: {e:#}", setting.label());
                row.error = Some(format!("{e:#}"));
            }
        }
        rows.push(row);
    }
    let lowest_mde = rows
        .iter()
        .enumerate()
        .filter_map(|(i, r)| r.mde_cm.map(|m| (i, m)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i);
    let report = ScreenReport {
        effect: effect.name().into(),
        parameters: effect.parameters().into_iter().map(|p| p.name).collect(),
        run: args.run.display().to_string(),
        model: backbone.label(),
        dataset: want.dataset.clone(),
        split: want.split.clone(),
        protocol: want.protocol.clone(),
        block: args.block,
        resamples: args.resamples,
        seed: args.seed,
        without,
        settings: rows,
        lowest_mde,
        wall_s: t0.elapsed().as_secs_f64(),
    };
    let path = args.out.join("screen.json");
    write_json(&path, &report)?;
    print_table(&report, before.per_episode.as_ref().map_or(0, Vec::len));
    println!("-> {} ({:.1} s)", path.display(), report.wall_s);
    Ok(report)
}

fn print_table(report: &ScreenReport, episodes: usize) {
    let deform = report.without.deform_l1_m.is_some();
    println!(
        "\n{} + {} on {} ({} episodes, blocks of {}); shrinkage = 1 − MDE with / MDE without, \
         95 % bootstrap interval",
        report.model, report.effect, report.split, episodes, report.block
    );
    if report.block == 1 && report.protocol != "deform" {
        // As `compare` says: episodes cut from one recording are not independent samples.
        println!(
            "  (single episodes resampled: if they are cut from fewer, longer recordings, as the \
             reference world's are into 10, the intervals are too narrow: --block 10)"
        );
    }
    let l1 = |v: Option<f64>| {
        if deform {
            v.map_or("       –".into(), |l| format!("  {l:.4}"))
        } else {
            String::new()
        }
    };
    println!(
        "  {:<28} {:>8}  {:<26} {:>9}{}",
        report.parameters.join(":"),
        "MDE cm",
        "shrinkage",
        "lower on",
        if deform { "  l1 (m)" } else { "" }
    );
    println!(
        "  {:<28} {:>8.3}  {:<26} {:>9}{}",
        "(without)",
        report.without.mde_cm.unwrap_or(f64::NAN),
        "",
        "",
        l1(report.without.deform_l1_m)
    );
    for (i, r) in report.settings.iter().enumerate() {
        let values = r
            .values
            .iter()
            .map(|v| v.to_string())
            .collect::<Vec<_>>()
            .join(":");
        let mark = if report.lowest_mde == Some(i) {
            "*"
        } else {
            " "
        };
        match (
            r.mde_cm,
            r.against_without.iter().find(|m| m.metric == "mde_cm"),
        ) {
            (Some(mde), Some(m)) => println!(
                "{mark} {values:<28} {mde:>8.3}  {:<26} {:>9}{}",
                format!(
                    "{:+.1} % [{:+.1}, {:+.1}]",
                    100.0 * m.shrinkage,
                    100.0 * m.ci95[0],
                    100.0 * m.ci95[1]
                ),
                format!("{} / {episodes}", m.lower_after),
                l1(r.deform_l1_m)
            ),
            _ => println!(
                "{mark} {values:<28} {:>8}  {}",
                "–",
                r.error.as_deref().unwrap_or("no scores")
            ),
        }
    }
    if let Some(i) = report.lowest_mde {
        let below = match (report.settings[i].mde_cm, report.without.mde_cm) {
            (Some(with), Some(without)) => with < without,
            _ => false,
        };
        if below {
            println!(
                "  * lowest MDE: its run is {} (score it on another split with `eval --run` \
                 there)",
                report.settings[i].run
            );
        } else {
            println!("  * lowest MDE, but no setting scores below the model without the effect");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cmd_fit::{FIXTURE_ROPE, FitArgs};

    fn args(run: &Path, out: &Path, effect: &str, values: &[&str]) -> ScreenArgs {
        ScreenArgs {
            data: FIXTURE_ROPE.into(),
            run: run.to_path_buf(),
            effect: effect.into(),
            values: values.iter().map(|v| v.to_string()).collect(),
            split: Split::Val,
            protocol: ProtocolArg::Paper,
            out: out.to_path_buf(),
            block: 1,
            resamples: 200,
            seed: 0,
            no_emd: true,
            beyond_range: false,
        }
    }

    #[test]
    fn each_setting_is_a_run_scored_as_eval_scores_it_and_a_second_screen_reads_them() {
        let root = std::env::temp_dir().join(format!("pgrd-screen-{}", std::process::id()));
        let (run, out) = (root.join("run"), root.join("screen"));
        crate::cmd_fit::run(&FitArgs::quick_rope_fixture(run.clone())).unwrap();
        let a = args(&run, &out, "gravity-scale", &["1", "4"]);
        let first = super::run(&a).unwrap();
        // The model without the effect scores as `eval` scores the run itself.
        let own = crate::cmd_eval::run(&EvalArgs {
            data: FIXTURE_ROPE.into(),
            run: run.clone(),
            split: Split::Val,
            protocol: ProtocolArg::Paper,
            json: Some(root.join("own.json")),
            plot: Some(root.join("own.svg")),
            no_emd: true,
            visual: false,
            horizon: None,
            autograd: false,
            save_predictions: None,
        })
        .unwrap();
        assert_eq!(
            first.without.mde_cm,
            Some(own.metrics["mde_cm"]["mean"].as_f64().unwrap())
        );
        // Each setting's run is the run's backbone with the effect appended, at its values.
        let kept = read_backbone(Path::new(&first.settings[1].run)).unwrap();
        assert_eq!(kept.effects.len(), 1);
        assert_eq!(kept.effects[0].effect, Candidate::GravityScale);
        assert_eq!(kept.effects[0].values, vec![4.0]);
        // Gravity as it is leaves the error as it is; four times gravity moves it.
        let mde = |i: usize| first.settings[i].mde_cm.unwrap();
        let without = first.without.mde_cm.unwrap();
        assert!(
            (mde(0) - without).abs() < 1e-9 * without,
            "{} vs {without}",
            mde(0)
        );
        assert!(
            (mde(1) - without).abs() > 1e-2 * without,
            "{} vs {without}",
            mde(1)
        );
        let m = &first.settings[1].against_without[0];
        assert_eq!(m.metric, "mde_cm");
        assert!((m.shrinkage - (1.0 - mde(1) / without)).abs() < 1e-9);
        assert!(m.ci95[0] <= m.shrinkage && m.shrinkage <= m.ci95[1]);
        assert!(first.lowest_mde.is_some());
        assert!(out.join("screen.json").exists());
        // Run again: nothing is scored again, and the numbers are the same.
        let again = super::run(&a).unwrap();
        assert!(again.without.reused && again.settings.iter().all(|r| r.reused));
        assert_eq!(again.settings[1].mde_cm, first.settings[1].mde_cm);
        // Another setting list scores only the new setting.
        let more = super::run(&args(&run, &out, "gravity-scale", &["4", "2"])).unwrap();
        assert!(more.without.reused && more.settings[0].reused && !more.settings[1].reused);
        std::fs::remove_dir_all(&root).ok();
    }

    #[test]
    fn bad_settings_are_refused_with_the_reason_before_anything_is_scored() {
        let root = std::env::temp_dir().join(format!("pgrd-screen-bad-{}", std::process::id()));
        let (run, out) = (root.join("run"), root.join("screen"));
        crate::cmd_fit::run(&FitArgs::quick_rope_fixture(run.clone())).unwrap();
        let cases: [(&str, &[&str], &str); 6] = [
            ("drag", &["100"], "--beyond-range scores"),
            ("drag", &["x"], "not a number"),
            ("nonlinear-elasticity", &["30"], "takes 2 value(s)"),
            ("no-such-effect", &["1"], "one of drag"),
            ("twist", &["0.5"], "needs a `chain` dataset"),
            ("external-field", &["0"], "probe for unknown gaps"),
        ];
        for (effect, values, why) in cases {
            let e = super::run(&args(&run, &out, effect, values)).unwrap_err();
            assert!(format!("{e:#}").contains(why), "{effect} {values:?}: {e:#}");
        }
        // An effect the model already has.
        let mut backbone = read_backbone(&run).unwrap();
        backbone
            .effects
            .push(BaseEffect::new(Candidate::Drag, vec![0.1]).unwrap());
        write_json(&backbone_path(&run), &backbone).unwrap();
        let e = super::run(&args(&run, &out, "drag", &["1"])).unwrap_err();
        assert!(format!("{e:#}").contains("already has drag"), "{e:#}");
        // The screen may not write over the run it screens (a run that was a screen's
        // `without`, screened into that screen's directory again).
        let without = root.join("without");
        std::fs::rename(&run, &without).unwrap();
        let e = super::run(&args(&without, &root, "bending", &["0.1"])).unwrap_err();
        assert!(format!("{e:#}").contains("overwrite"), "{e:#}");
        assert!(!out.exists(), "nothing is written for a refused screen");
        // Beyond the search box on request, but a log-scaled strength stays positive.
        let beyond = |effect: &str, v: &str| ScreenArgs {
            beyond_range: true,
            ..args(&without, &out, effect, &[v])
        };
        let e = super::run(&beyond("bending", "0")).unwrap_err();
        assert!(format!("{e:#}").contains("finite and positive"), "{e:#}");
        assert!(!out.exists());
        let report = super::run(&beyond("gravity-scale", "5")).unwrap();
        assert_eq!(report.settings[0].values, vec![5.0]);
        assert!(report.settings[0].mde_cm.is_some());
        std::fs::remove_dir_all(&root).ok();
    }
}
