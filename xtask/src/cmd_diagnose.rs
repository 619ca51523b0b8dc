//! `cargo xtask diagnose` (where / which / how far for one dataset and fitted run) and
//! `cargo xtask diagnose-bench` (the diagnosis scored on reference-world data whose effect was
//! withheld from the model). Method: `docs/gap.md`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use dataset::{Dataset, Split};
use fit::{BackboneFamily, FitConfig};
use gap::{Candidate, DiagnoseConfig, Diagnosis};
use scene::{Protocol, Scene, SceneConfig};
use serde::Serialize;

use crate::common::{ProtocolArg, load_scenes, read_backbone};
use crate::report::write_json;

/// Arguments of `diagnose`.
#[derive(clap::Args)]
pub struct DiagnoseArgs {
    /// Dataset directory (train split for refits, val split held out).
    #[arg(long)]
    pub data: PathBuf,
    /// Run directory holding backbone.json (from `cargo xtask fit`).
    #[arg(long)]
    pub run: PathBuf,
    /// Report directory (created): report.json and report.html.
    #[arg(long)]
    pub out: PathBuf,
    /// CMA-ES candidates per generation of each refit.
    #[arg(long, default_value_t = 8)]
    pub population: usize,
    /// Generations of each refit.
    #[arg(long, default_value_t = 10)]
    pub generations: usize,
    /// Training episodes sampled per generation.
    #[arg(long, default_value_t = 8)]
    pub samples: usize,
    /// Seed of the refits and the bootstrap.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Bootstrap resamples over held-out episodes.
    #[arg(long, default_value_t = 2000)]
    pub resamples: usize,
    /// Window of each episode.
    #[arg(long, value_enum, default_value_t = ProtocolArg::Paper)]
    pub protocol: ProtocolArg,
    /// Comma-separated candidate effects (default: all nine).
    #[arg(long)]
    pub candidates: Option<String>,
    /// Skip the generic external-field probe (the verdict can then not be `unknown`).
    #[arg(long)]
    pub no_probe: bool,
    /// Print only the verdict line.
    #[arg(long)]
    pub quiet: bool,
}

fn config_from(args: &DiagnoseArgs) -> anyhow::Result<DiagnoseConfig> {
    let candidates = match &args.candidates {
        Some(list) => list
            .split(',')
            .map(|s| Candidate::parse(s.trim()))
            .collect::<Result<Vec<_>, _>>()?,
        None => Candidate::LIBRARY.to_vec(),
    };
    Ok(DiagnoseConfig {
        population: args.population,
        generations: args.generations,
        samples: args.samples,
        seed: args.seed,
        resamples: args.resamples,
        candidates,
        probe: !args.no_probe,
        ..DiagnoseConfig::default()
    })
}

fn scenes(data: &Dataset, split: Split, protocol: Protocol) -> anyhow::Result<Vec<Scene>> {
    Ok(load_scenes(data, split, protocol, &SceneConfig::default())?
        .into_iter()
        .map(|(_, s)| s)
        .collect())
}

/// Writes `<out>/report.json` and `<out>/report.html`.
pub fn write_report(out: &Path, diagnosis: &Diagnosis, title: &str) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    write_json(&out.join("report.json"), diagnosis)?;
    let html = gap::render_html(diagnosis, title);
    dataset::write_atomic(&out.join("report.html"), html.as_bytes())
        .with_context(|| format!("writing {}", out.join("report.html").display()))
}

/// Runs `diagnose`.
pub fn run(args: &DiagnoseArgs) -> anyhow::Result<Diagnosis> {
    let t0 = Instant::now();
    let data = Dataset::open(&args.data)?;
    let backbone = read_backbone(&args.run)?;
    let protocol: Protocol = args.protocol.into();
    let train = scenes(&data, Split::Train, protocol)?;
    let val = scenes(&data, Split::Val, protocol)?;
    let config = config_from(args)?;
    let quiet = args.quiet;
    let d = gap::diagnose(&train, &val, &backbone.params, &config, &mut |line| {
        if !quiet {
            println!("  {line}");
        }
    })?;
    let title = format!("{} ({})", data.meta.object, args.data.display());
    write_report(&args.out, &d, &title)?;
    let how = d.how_far.as_ref().map_or(String::new(), |h| {
        format!(
            "; adding {}: held-out MDE {:.3} -> {:.3} cm ({:.1}% shrinkage)",
            h.effect,
            h.before.mde_cm,
            h.after.mde_cm,
            100.0 * h.shrinkage_mde
        )
    });
    println!(
        "diagnosis of {}: verdict {}{} ({:.1} s) -> {}",
        data.meta.object,
        d.verdict,
        how,
        t0.elapsed().as_secs_f64(),
        args.out.join("report.html").display()
    );
    Ok(d)
}

/// Arguments of `diagnose-bench`.
#[derive(clap::Args)]
pub struct DiagnoseBenchArgs {
    /// Write the cases and the summary as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Objects to generate (comma-separated).
    #[arg(long, default_value = "rope,paper,sloth")]
    pub objects: String,
    /// Cases: comma-separated world effect names, `none` and `magnet` (default: all).
    #[arg(long)]
    pub cases: Option<String>,
    /// Training episodes per generated dataset.
    #[arg(long, default_value_t = 16)]
    pub episodes: usize,
    /// Held-out episodes per generated dataset.
    #[arg(long, default_value_t = 8)]
    pub val: usize,
    /// Tracked particles.
    #[arg(long, default_value_t = 60)]
    pub tracked: usize,
    /// Generations of the backbone fit (without the effect).
    #[arg(long, default_value_t = 12)]
    pub fit_generations: usize,
    /// Generations of each diagnosis refit.
    #[arg(long, default_value_t = 8)]
    pub generations: usize,
    /// Training episodes sampled per generation.
    #[arg(long, default_value_t = 6)]
    pub samples: usize,
    /// Seed of the data and of every fit.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Where generated datasets and reports go.
    #[arg(long, default_value = "target/diagnose-bench")]
    pub work: PathBuf,
}

/// One bench case.
#[derive(Serialize, Clone, Debug)]
pub struct BenchCase {
    /// Object.
    pub object: String,
    /// The effect switched on in the data (`none` or `magnet` included).
    pub truth: String,
    /// What the diagnosis should say.
    pub expected: String,
    /// What it said.
    pub verdict: String,
    /// Held-out MDE of the backbone refit without any effect, cm.
    pub mde_before_cm: f64,
    /// Held-out MDE with the true effect's candidate (when in the library), cm.
    pub mde_after_cm: Option<f64>,
    /// Shrinkage of the true effect's candidate.
    pub shrinkage: Option<f64>,
    /// Held-out MDE of the backbone refit on the same data generated without the effect, cm.
    pub mde_without_effect_cm: f64,
    /// `(before − after) / (before − without)`: share of the effect-attributable gap recovered.
    pub recovered: Option<f64>,
    /// Wall time of the diagnosis, s.
    pub diagnose_wall_s: f64,
}

/// Bench summary.
#[derive(Serialize, Debug)]
pub struct BenchSummary {
    /// Share of in-library cases with the right verdict.
    pub in_library_accuracy: f64,
    /// Share of `none` cases answered `none`.
    pub none_accuracy: f64,
    /// Share of out-of-library cases answered `unknown`.
    pub unknown_accuracy: f64,
    /// Median recovered share over in-library cases with a positive attributable gap.
    pub median_recovered: f64,
    /// Confusion matrix rows: truth, then counts per verdict label.
    pub confusion: Vec<(String, Vec<(String, usize)>)>,
    /// All cases.
    pub cases: Vec<BenchCase>,
    /// Wall time, s.
    pub wall_s: f64,
}

fn generate(
    object: world::ObjectKind,
    truth: &str,
    args: &DiagnoseBenchArgs,
    dir: &Path,
) -> anyhow::Result<Dataset> {
    let mut cfg = world::GenConfig::fixture(object);
    cfg.train_episodes = args.episodes;
    cfg.val_episodes = args.val;
    cfg.tracked = args.tracked;
    cfg.seed = args.seed;
    cfg.effects = world::Effects::parse(truth, object)?;
    let data = world::generate(&cfg)?;
    Ok(data.write(dir)?)
}

fn fit_backbone(
    train: &[Scene],
    args: &DiagnoseBenchArgs,
) -> anyhow::Result<springs::SpringParams> {
    let family = BackboneFamily::new(springs::REFERENCE_BOUNDS)?;
    let cfg = FitConfig {
        population: 8,
        generations: args.fit_generations,
        samples: args.samples,
        sigma0: 0.2,
        seed: args.seed,
    };
    let out = fit::fit(train, &family, &cfg, None, &mut |_| {})?;
    Ok(BackboneFamily::params(&out.best))
}

fn diagnose_dataset(data: &Dataset, args: &DiagnoseBenchArgs) -> anyhow::Result<Diagnosis> {
    let train = scenes(data, Split::Train, Protocol::Paper)?;
    let val = scenes(data, Split::Val, Protocol::Paper)?;
    let base = fit_backbone(&train, args)?;
    let cfg = DiagnoseConfig {
        generations: args.generations,
        samples: args.samples,
        seed: args.seed,
        ..DiagnoseConfig::default()
    };
    Ok(gap::diagnose(&train, &val, &base, &cfg, &mut |_| {})?)
}

fn control_mde(d: &Diagnosis) -> f64 {
    d.ranking
        .first()
        .map_or(f64::NAN, |r| r.heldout_mde_before_cm)
}

/// Runs the bench: for each object, data without effects, with each library effect alone and
/// with the out-of-library magnet; fits the backbone without the effect; diagnoses.
pub fn run_bench(args: &DiagnoseBenchArgs) -> anyhow::Result<BenchSummary> {
    let t0 = Instant::now();
    let cases: Vec<String> = match &args.cases {
        Some(c) => c.split(',').map(|s| s.trim().to_string()).collect(),
        None => std::iter::once("none".to_string())
            .chain(Candidate::LIBRARY.iter().map(|c| c.name().to_string()))
            .chain(std::iter::once("magnet".to_string()))
            .collect(),
    };
    let mut out = Vec::new();
    for name in args.objects.split(',') {
        let object: world::ObjectKind = name.trim().parse()?;
        // The no-effect dataset is always needed: it defines the effect-attributable gap.
        let base_dir = args.work.join(format!("{object}-none"));
        let data0 = generate(object, "none", args, &base_dir)?;
        let t = Instant::now();
        let d0 = diagnose_dataset(&data0, args)?;
        let e0 = control_mde(&d0);
        write_report(
            &base_dir.join("report"),
            &d0,
            &format!("{object}, no effect"),
        )?;
        for truth in &cases {
            let (d, wall) = if truth == "none" {
                (d0.clone(), t.elapsed().as_secs_f64())
            } else {
                let dir = args.work.join(format!("{object}-{truth}"));
                let data = generate(object, truth, args, &dir)?;
                let t = Instant::now();
                let d = diagnose_dataset(&data, args)?;
                write_report(&dir.join("report"), &d, &format!("{object}, {truth}"))?;
                (d, t.elapsed().as_secs_f64())
            };
            let expected = match truth.as_str() {
                "none" => "none".to_string(),
                "magnet" => "unknown".to_string(),
                t => t.to_string(),
            };
            let before = control_mde(&d);
            let after = d
                .ranking
                .iter()
                .find(|r| &r.effect == truth)
                .map(|r| r.heldout_mde_after_cm);
            let gap = before - e0;
            let case = BenchCase {
                object: object.to_string(),
                truth: truth.clone(),
                expected,
                verdict: d.verdict.clone(),
                mde_before_cm: before,
                mde_after_cm: after,
                shrinkage: d
                    .ranking
                    .iter()
                    .find(|r| &r.effect == truth)
                    .map(|r| r.shrinkage),
                mde_without_effect_cm: e0,
                recovered: after.filter(|_| gap > 0.0).map(|a| (before - a) / gap),
                diagnose_wall_s: wall,
            };
            println!(
                "{:<6} {:<24} verdict {:<24} MDE {:.3} -> {} cm (without effect {:.3}), recovered {} ({:.0} s)",
                case.object,
                case.truth,
                case.verdict,
                before,
                after.map_or("-".into(), |a| format!("{a:.3}")),
                e0,
                case.recovered
                    .map_or("-".into(), |r| format!("{:.0}%", 100.0 * r)),
                wall
            );
            out.push(case);
            if let Some(path) = &args.json {
                // Partial results survive an interrupted bench.
                write_json(path, &out)?;
            }
        }
    }
    let acc = |pick: &dyn Fn(&BenchCase) -> bool| {
        let sel: Vec<&BenchCase> = out.iter().filter(|c| pick(c)).collect();
        let right = sel.iter().filter(|c| c.verdict == c.expected).count();
        if sel.is_empty() {
            f64::NAN
        } else {
            right as f64 / sel.len() as f64
        }
    };
    let mut recovered: Vec<f64> = out.iter().filter_map(|c| c.recovered).collect();
    recovered.sort_by(f64::total_cmp);
    let labels: Vec<String> = std::iter::once("none".to_string())
        .chain(Candidate::LIBRARY.iter().map(|c| c.name().to_string()))
        .chain(std::iter::once("unknown".to_string()))
        .collect();
    let confusion: Vec<(String, Vec<(String, usize)>)> = cases
        .iter()
        .map(|t| {
            let row = labels
                .iter()
                .map(|l| {
                    (
                        l.clone(),
                        out.iter()
                            .filter(|c| &c.truth == t && &c.verdict == l)
                            .count(),
                    )
                })
                .collect();
            (t.clone(), row)
        })
        .collect();
    println!("\nconfusion matrix (rows: effect in the data; columns: verdict)");
    let short = |s: &str| s.chars().take(7).collect::<String>();
    print!("{:<24}", "");
    for l in &labels {
        print!("{:>8}", short(l));
    }
    println!();
    for (t, row) in &confusion {
        print!("{t:<24}");
        for (_, n) in row {
            print!("{n:>8}");
        }
        println!();
    }
    let summary = BenchSummary {
        in_library_accuracy: acc(&|c| c.truth != "none" && c.truth != "magnet"),
        none_accuracy: acc(&|c| c.truth == "none"),
        unknown_accuracy: acc(&|c| c.truth == "magnet"),
        median_recovered: recovered
            .get(recovered.len() / 2)
            .copied()
            .unwrap_or(f64::NAN),
        confusion,
        cases: out,
        wall_s: t0.elapsed().as_secs_f64(),
    };
    println!(
        "in-library accuracy {:.0}%, none {:.0}%, unknown {:.0}%, median recovered gap {:.0}% ({:.0} s)",
        100.0 * summary.in_library_accuracy,
        100.0 * summary.none_accuracy,
        100.0 * summary.unknown_accuracy,
        100.0 * summary.median_recovered,
        summary.wall_s
    );
    if let Some(path) = &args.json {
        write_json(path, &summary)?;
    }
    Ok(summary)
}
