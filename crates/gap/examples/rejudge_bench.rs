//! How a `diagnose-bench` run's verdicts depend on the verdict rule's floor, without refitting:
//! every stored case report is re-judged ([`gap::Diagnosis::rejudge`]) at each floor and the
//! bench's counts are printed per class.
//!
//! ```sh
//! cargo run --release -p pgrd-gap --example rejudge_bench -- <bench.json> <work-dir> 0.05,0.07
//! ```
//!
//! Exact for a case as long as its object's base search (the no-effect diagnoses that chose the
//! base effects every case is judged against) reaches the same verdicts at that floor; objects
//! where it does not are marked, since a real run at that floor would diagnose their cases
//! against another base model.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use anyhow::{Context, bail};
use gap::{Diagnosis, VerdictRule};

fn read(path: &Path) -> anyhow::Result<Diagnosis> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

fn floor_rule(d: &Diagnosis, floor: f64) -> VerdictRule {
    VerdictRule {
        min_shrinkage: floor,
        ..d.config.rule
    }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [bench, work, floors] = args.as_slice() else {
        bail!("usage: rejudge_bench <bench.json> <work-dir> <floor>[,<floor>...]");
    };
    let floors: Vec<f64> = floors
        .split(',')
        .map(|f| f.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .context("floors")?;
    let work = Path::new(work);
    let text = std::fs::read_to_string(bench).with_context(|| bench.clone())?;
    let json: serde_json::Value = serde_json::from_str(&text)?;
    // A finished bench writes a summary with `cases`; one still running or interrupted, the
    // pair (objects, cases).
    let cases = json["cases"]
        .as_array()
        .or_else(|| json[1].as_array())
        .context("no cases in the bench file")?;

    // Objects whose base search changes with the floor: their cases are not exact.
    let mut inexact: BTreeSet<(String, usize)> = BTreeSet::new();
    let objects: Vec<String> = cases
        .iter()
        .filter_map(|c| c["object"].as_str().map(String::from))
        .collect();
    for object in objects.iter().collect::<BTreeSet<_>>() {
        for step in 0.. {
            let p = work.join(format!("{object}-none/report-base{step}/report.json"));
            if !p.exists() {
                break;
            }
            let d = read(&p)?;
            for (k, f) in floors.iter().enumerate() {
                let v = d.rejudge(floor_rule(&d, *f))?.verdict;
                if v != d.verdict {
                    println!(
                        "{object}: base search step {step} {} -> {v} at floor {f}",
                        d.verdict
                    );
                    inexact.insert((object.clone(), k));
                }
            }
        }
    }

    // class -> per floor (right, counted)
    let mut tally: BTreeMap<String, Vec<(usize, usize)>> = BTreeMap::new();
    for c in cases {
        let s = |k: &str| c[k].as_str().unwrap_or("?").to_string();
        let (object, truth, expected) = (s("object"), s("truth"), s("expected"));
        let reached = c["target_reached"].as_bool().unwrap_or(false);
        let dir = if truth == "none" {
            format!("{object}-none-replicate")
        } else {
            let scale = c["scale"].as_f64().context("case without a scale")?;
            format!("{object}-{truth}-x{scale}")
        };
        let d = read(&work.join(dir).join("report/report.json"))?;
        let mut class = s("class");
        if class == "in-library" && !reached {
            class.push_str(" (target not reached)");
        }
        let row = tally
            .entry(class)
            .or_insert_with(|| vec![(0, 0); floors.len()]);
        let mut line = format!(
            "{object:<6} {truth:<24} expected {expected:<24} stored {:<24}",
            d.verdict
        );
        for (k, f) in floors.iter().enumerate() {
            let v = d.rejudge(floor_rule(&d, *f))?.verdict;
            let mark = if inexact.contains(&(object.clone(), k)) {
                "?"
            } else {
                ""
            };
            line.push_str(&format!(" {f}: {v}{mark}"));
            row[k].0 += usize::from(v == expected);
            row[k].1 += 1;
        }
        println!("{line}");
    }
    println!(
        "\nright / counted per class, floor by floor ({})",
        floors
            .iter()
            .map(f64::to_string)
            .collect::<Vec<_>>()
            .join(", ")
    );
    for (class, row) in tally {
        let cells: Vec<String> = row.iter().map(|(r, n)| format!("{r} / {n}")).collect();
        println!("{class:<36} {}", cells.join("   "));
    }
    Ok(())
}
