//! The bench's summary: the confusion matrix, the right verdicts with and without the
//! diagnosis's caution, and the share right per class of case.

use gap::Candidate;

use super::DiagnoseBenchArgs;
use super::records::{BenchCase, BenchSummary, ObjectModel, SkippedCase};

/// Scores the finished cases, prints the confusion matrix and the accuracies, and returns the
/// summary `--json` keeps. `cases` are the bench's case names in the order of the matrix's rows.
pub(super) fn summarise(
    args: &DiagnoseBenchArgs,
    settings: serde_json::Value,
    cases: &[String],
    objects: Vec<ObjectModel>,
    out: Vec<BenchCase>,
    skipped: Vec<SkippedCase>,
    wall_s: f64,
) -> BenchSummary {
    let pick = |f: &dyn Fn(&BenchCase) -> bool| out.iter().filter(|c| f(c)).collect::<Vec<_>>();
    let lib_reached = pick(&|c| c.class == "in-library" && c.target_reached);
    let lib_all = pick(&|c| c.class == "in-library");
    let mut recovered: Vec<f64> = lib_reached.iter().filter_map(|c| c.recovered).collect();
    recovered.sort_by(f64::total_cmp);
    let verdicts: Vec<String> = std::iter::once("none".to_string())
        .chain(Candidate::LIBRARY.iter().map(|c| c.name().to_string()))
        .chain(std::iter::once("unknown".to_string()))
        .collect();
    let confusion: Vec<(String, Vec<(String, usize)>)> = cases
        .iter()
        .map(|t| {
            let row = verdicts
                .iter()
                .map(|l| {
                    let n = out
                        .iter()
                        .filter(|c| &c.truth == t && &c.verdict == l)
                        .count();
                    (l.clone(), n)
                })
                .collect();
            (t.clone(), row)
        })
        .collect();
    println!("\nconfusion matrix (rows: effect in the data; columns: verdict)");
    let short = |s: &str| s.chars().take(7).collect::<String>();
    print!("{:<24}", "");
    for l in &verdicts {
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
    // How the verdicts fare where the diagnosis cautions (docs/gap-log.md, "When the control
    // refit does not carry over").
    let right = |cases: &[&BenchCase], caution: bool| {
        let kept: Vec<_> = cases.iter().filter(|c| c.caution == caution).collect();
        let n = kept.iter().filter(|c| c.verdict == c.expected).count();
        format!("{n} / {}", kept.len())
    };
    let nones = pick(&|c| c.class == "none");
    println!(
        "right with the caution / without: in-library (target reached) {} / {}, none {} / {}",
        right(&lib_reached, true),
        right(&lib_reached, false),
        right(&nones, true),
        right(&nones, false),
    );
    let summary = BenchSummary {
        settings,
        bounds: args.bounds.name().to_string(),
        episodes_per_recording: args.episodes_per_recording,
        in_library_accuracy: share(&lib_reached),
        in_library_accuracy_all: share(&lib_all),
        in_library_cases: [lib_reached.len(), lib_all.len()],
        none_accuracy: share(&pick(&|c| c.class == "none")),
        unknown_accuracy: share(&pick(&|c| c.class == "out-of-library")),
        in_base_accuracy: share(&pick(&|c| c.class == "in-base")),
        median_recovered: recovered
            .get(recovered.len() / 2)
            .copied()
            .unwrap_or(f64::NAN),
        recovered_70_share: if recovered.is_empty() {
            f64::NAN
        } else {
            recovered.iter().filter(|r| **r >= 0.7).count() as f64 / recovered.len() as f64
        },
        confusion,
        objects,
        cases: out,
        skipped,
        wall_s,
    };
    println!(
        "in-library accuracy {} of {} (target reached; {} of all {}), none {}, unknown {}, in-base {}, median recovered gap {} ({} of cases >= 70%) ({:.0} s)",
        percent(summary.in_library_accuracy),
        summary.in_library_cases[0],
        percent(summary.in_library_accuracy_all),
        summary.in_library_cases[1],
        percent(summary.none_accuracy),
        percent(summary.unknown_accuracy),
        percent(summary.in_base_accuracy),
        percent(summary.median_recovered),
        percent(summary.recovered_70_share),
        summary.wall_s
    );
    summary
}

/// A share as a whole percentage, or "–" for a class with no cases (NaN).
pub(super) fn percent(share: f64) -> String {
    if share.is_finite() {
        format!("{:.0}%", 100.0 * share)
    } else {
        "–".to_string()
    }
}

fn share(cases: &[&BenchCase]) -> f64 {
    if cases.is_empty() {
        return f64::NAN;
    }
    cases.iter().filter(|c| c.verdict == c.expected).count() as f64 / cases.len() as f64
}
