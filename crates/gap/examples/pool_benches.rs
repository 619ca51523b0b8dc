//! Pools several `diagnose-bench --json` reports (seeds, or an in-library bench with an
//! out-of-library one) into the counts the issue's goals are judged on, and prints their
//! confusion matrix as a Markdown table.
//!
//! ```sh
//! cargo run --release -p pgrd-gap --example pool_benches -- bench_37.json ool_37.json bench_38.json ...
//! cargo run --release -p pgrd-gap --example pool_benches -- --classes in-library,none bench_*.json
//! ```
//!
//! Counted as the bench counts them: an in-library case only when its effect reached the
//! target raise (the goal's cases), `none` and out-of-library cases always, in-base cases
//! never (their effect is in the object's base model). `--classes` keeps only the classes
//! named from every report, e.g. the `none` replicates of one bench and not of another:
//! `--classes in-library,none a.json --classes out-of-library b.json` (a `--classes` applies
//! to the reports after it).
//!
//! Reports written since session 88 carry their bench's `settings`; when the reports pooled
//! under one `--classes` differ in a setting that changes what a case is (the world's link
//! sweeps, the verdict rule's floor, the second round, the dataset's size), a warning names it.
//! Reports under different `--classes` are not compared: an in-library bench at 12 / 8
//! episodes pooled with out-of-library ones at 100 / 20 is the documented use.

mod bench_report;

use std::collections::BTreeMap;

use anyhow::{Context, bail};
use bench_report::{RECOVERED_GOAL, counted, read_report};
use gap::Candidate;
use serde_json::Value;

/// One counted case: what the data held, what was expected, what was answered, and the share
/// of the effect-attributable gap the answer recovered.
struct Case {
    truth: String,
    class: String,
    expected: String,
    verdict: String,
    recovered: Option<f64>,
}

const CLASSES: [&str; 3] = ["in-library", "none", "out-of-library"];

/// Settings that change what a bench's case is: pooling reports that differ in one mixes
/// two benchmarks.
const DEFINING: [&str; 5] = [
    "link_sweeps",
    "min_shrinkage",
    "second_round",
    "episodes",
    "val",
];

/// A report's [`DEFINING`] settings in that order (`None` for a report written before they
/// were recorded).
type Defining = Option<Vec<Value>>;

fn defining_settings(report: &Value) -> Defining {
    let s = report.get("settings")?;
    Some(
        DEFINING
            .iter()
            .map(|k| s.get(*k).cloned().unwrap_or(Value::Null))
            .collect(),
    )
}

fn cases_of(path: &str, report: &Value, classes: &[String]) -> anyhow::Result<Vec<Case>> {
    let Some(cases) = report.get("cases").and_then(Value::as_array) else {
        bail!("{path}: no `cases` array (not a `diagnose-bench --json` report)");
    };
    let field = |c: &Value, k: &str| -> anyhow::Result<String> {
        c.get(k)
            .and_then(Value::as_str)
            .map(str::to_string)
            .with_context(|| format!("{path}: a case without `{k}`"))
    };
    let mut out = Vec::new();
    for c in cases {
        let class = field(c, "class")?;
        if counted(c) && classes.contains(&class) {
            out.push(Case {
                truth: field(c, "truth")?,
                expected: field(c, "expected")?,
                verdict: field(c, "verdict")?,
                recovered: c.get("recovered").and_then(Value::as_f64),
                class,
            });
        }
    }
    Ok(out)
}

fn main() -> anyhow::Result<()> {
    let mut classes: Vec<String> = CLASSES.iter().map(|c| c.to_string()).collect();
    let mut cases = Vec::new();
    let mut reports = 0;
    // The reports' defining settings, one group per `--classes`.
    let mut groups: Vec<Vec<(String, Defining)>> = vec![Vec::new()];
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        if arg == "--classes" {
            let list = args.next().context("--classes needs a list")?;
            classes = list.split(',').map(|c| c.trim().to_string()).collect();
            if groups.last().is_some_and(|g| !g.is_empty()) {
                groups.push(Vec::new());
            }
            if let Some(bad) = classes.iter().find(|c| !CLASSES.contains(&c.as_str())) {
                bail!("unknown class {bad:?} (in-library, none, out-of-library)");
            }
        } else {
            let report = read_report(&arg)?;
            cases.extend(cases_of(&arg, &report, &classes)?);
            if let Some(group) = groups.last_mut() {
                group.push((arg, defining_settings(&report)));
            }
            reports += 1;
        }
    }
    if reports == 0 {
        bail!("usage: pool_benches [--classes a,b] <bench.json>...");
    }
    println!("{reports} reports, {} counted cases", cases.len());
    for group in &groups {
        warn_on_mixed_settings(group);
    }
    for class in CLASSES {
        let of: Vec<&Case> = cases.iter().filter(|c| c.class == class).collect();
        let right: Vec<&&Case> = of.iter().filter(|c| c.verdict == c.expected).collect();
        print!("{class}: {} / {} right", right.len(), of.len());
        if class == "in-library" {
            let recovered = right
                .iter()
                .filter(|c| c.recovered.is_some_and(|r| r >= RECOVERED_GOAL))
                .count();
            print!(", {recovered} of the right recovering >= 70 % of their gap");
        }
        println!();
    }
    // Rows and columns in the library's order, then `none`, then `unknown` and the
    // out-of-library effects (in the order they first appear); only those that occur.
    let rank = |name: &str| {
        let library = Candidate::LIBRARY.iter().position(|c| c.name() == name);
        library.unwrap_or(match name {
            "none" => Candidate::LIBRARY.len(),
            _ => Candidate::LIBRARY.len() + 1,
        })
    };
    let mut rows: Vec<&str> = Vec::new();
    let mut columns: Vec<&str> = Vec::new();
    for c in &cases {
        if !rows.contains(&c.truth.as_str()) {
            rows.push(&c.truth);
        }
        if !columns.contains(&c.verdict.as_str()) {
            columns.push(&c.verdict);
        }
    }
    rows.sort_by_key(|r| rank(r));
    columns.sort_by_key(|v| rank(v));
    let mut counts: BTreeMap<(&str, &str), usize> = BTreeMap::new();
    for c in &cases {
        *counts.entry((&c.truth, &c.verdict)).or_default() += 1;
    }
    println!(
        "\n| withheld ↓ / verdict → | {} | right |",
        columns.join(" | ")
    );
    println!("|{}", " --- |".repeat(columns.len() + 2));
    for r in rows {
        let cells: Vec<String> = columns
            .iter()
            .map(|v| match counts.get(&(r, *v)) {
                Some(n) => n.to_string(),
                None => "·".to_string(),
            })
            .collect();
        let of: Vec<&Case> = cases.iter().filter(|c| c.truth == r).collect();
        let right = of.iter().filter(|c| c.verdict == c.expected).count();
        println!("| {r} | {} | {right} / {} |", cells.join(" | "), of.len());
    }
    Ok(())
}

/// Prints a warning for each defining setting the reports of one `--classes` group disagree
/// on (reports without recorded settings are listed, not compared).
fn warn_on_mixed_settings(settings: &[(String, Defining)]) {
    let recorded: Vec<(&String, &Vec<Value>)> = settings
        .iter()
        .filter_map(|(p, s)| s.as_ref().map(|s| (p, s)))
        .collect();
    let unrecorded: Vec<&str> = settings
        .iter()
        .filter(|(_, s)| s.is_none())
        .map(|(p, _)| p.as_str())
        .collect();
    if !unrecorded.is_empty() && !recorded.is_empty() {
        println!(
            "note: settings not recorded in {} (written before session 88)",
            unrecorded.join(", ")
        );
    }
    for (k, key) in DEFINING.iter().enumerate() {
        let mut values: Vec<&Value> = recorded.iter().map(|(_, s)| &s[k]).collect();
        values.dedup();
        if values.len() > 1 {
            let each: Vec<String> = recorded
                .iter()
                .map(|(p, s)| format!("{p}: {}", s[k]))
                .collect();
            println!(
                "warning: the pooled reports differ in `{key}` ({})",
                each.join(", ")
            );
        }
    }
}
