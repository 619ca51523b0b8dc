//! Compares two `diagnose-bench --json` reports of the same seed and settings, case by case:
//! the way to judge a change to the diagnosis (a candidate's form, a rule) on paired data.
//!
//! ```sh
//! cargo run --release -p pgrd-gap --example diff_benches -- before.json after.json
//! ```
//!
//! Cases are paired by object, withheld effect and strength. It prints every case whose
//! verdict differs, every object whose base model differs (a different base model makes its
//! cases' verdicts incomparable), then the goal counts of both reports as the bench counts
//! them: in-library cases only where the effect reached the target raise, right verdicts
//! recovering at least 70 % of their gap, `none` and out-of-library cases always. The two
//! reports must come from the same seeds (`settings.seed`, `settings.case_seed`) when both
//! record their settings; other differences in settings are listed, since they are usually
//! what is being compared.

mod bench_report;

use std::collections::BTreeMap;

use anyhow::bail;
use bench_report::{RECOVERED_GOAL, counted, read_report};
use serde_json::Value;

/// A case's key: object, withheld effect, strength.
type Key = (String, String, String);

fn text(c: &Value, k: &str) -> String {
    c.get(k).and_then(Value::as_str).unwrap_or("?").to_string()
}

fn number(c: &Value, k: &str) -> Option<f64> {
    c.get(k).and_then(Value::as_f64)
}

fn cases(report: &Value) -> BTreeMap<Key, &Value> {
    let mut out = BTreeMap::new();
    for c in report["cases"].as_array().into_iter().flatten() {
        let scale = number(c, "scale").map_or("?".into(), |s| format!("x{s}"));
        out.insert((text(c, "object"), text(c, "truth"), scale), c);
    }
    out
}

fn bases(report: &Value) -> BTreeMap<String, String> {
    report["objects"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|o| (text(o, "object"), o["base"].to_string()))
        .collect()
}

/// Goal counts as the bench counts them.
struct Counts {
    in_library: (usize, usize),
    recovered_70: usize,
    none: (usize, usize),
    out_of_library: (usize, usize),
}

fn counts(report: &Value) -> Counts {
    let mut n = Counts {
        in_library: (0, 0),
        recovered_70: 0,
        none: (0, 0),
        out_of_library: (0, 0),
    };
    for c in report["cases"].as_array().into_iter().flatten() {
        if !counted(c) {
            continue;
        }
        let right = text(c, "verdict") == text(c, "expected");
        let tally = |t: &mut (usize, usize)| {
            t.0 += usize::from(right);
            t.1 += 1;
        };
        match text(c, "class").as_str() {
            "in-library" => {
                tally(&mut n.in_library);
                if right && number(c, "recovered").is_some_and(|r| r >= RECOVERED_GOAL) {
                    n.recovered_70 += 1;
                }
            }
            "none" => tally(&mut n.none),
            _ => tally(&mut n.out_of_library),
        }
    }
    n
}

fn describe(c: &Value) -> String {
    let pct = |k: &str| number(c, k).map_or("–".into(), |v| format!("{:.1} %", 100.0 * v));
    format!(
        "{} (shrinkage of the true effect {}, recovered {})",
        text(c, "verdict"),
        pct("shrinkage"),
        pct("recovered")
    )
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [a_path, b_path] = args.as_slice() else {
        bail!("usage: diff_benches <before.json> <after.json>");
    };
    let (a, b) = (read_report(a_path)?, read_report(b_path)?);
    let (sa, sb) = (a.get("settings"), b.get("settings"));
    if sa.is_none() || sb.is_none() {
        println!(
            "warning: a report without `settings` (written before session 88): \
             whether the two are paired cannot be checked"
        );
    }
    if let (Some(sa), Some(sb)) = (sa, sb) {
        for k in ["seed", "case_seed"] {
            if sa.get(k) != sb.get(k) {
                bail!(
                    "the reports are not paired: `{k}` {} against {}",
                    sa[k],
                    sb[k]
                );
            }
        }
        let keys: Vec<&String> = sa
            .as_object()
            .map(|m| m.keys().collect())
            .unwrap_or_default();
        for k in keys {
            if k != "json" && k != "work" && sa.get(k) != sb.get(k) {
                println!("setting `{k}`: {} -> {}", sa[k], sb[k]);
            }
        }
    }
    let (ba, bb) = (bases(&a), bases(&b));
    for (object, base) in &ba {
        match bb.get(object) {
            Some(other) if other != base => println!("base model of {object}: {base} -> {other}"),
            None => println!("{object}: only in {a_path}"),
            _ => {}
        }
    }
    let (ca, cb) = (cases(&a), cases(&b));
    let mut changed = 0;
    for (key, before) in &ca {
        let Some(after) = cb.get(key) else {
            println!("{} {} {}: only in {a_path}", key.0, key.1, key.2);
            continue;
        };
        if text(before, "verdict") != text(after, "verdict") {
            changed += 1;
            println!(
                "{} {} {} ({}, expected {}): {} -> {}",
                key.0,
                key.1,
                key.2,
                text(before, "class"),
                text(before, "expected"),
                describe(before),
                describe(after)
            );
        }
    }
    for key in cb.keys().filter(|k| !ca.contains_key(*k)) {
        println!("{} {} {}: only in {b_path}", key.0, key.1, key.2);
    }
    println!(
        "{changed} of {} paired cases changed their verdict",
        ca.len()
    );
    println!(
        "| report | in-library right | recovering >= 70 % | `none` right | out-of-library right |"
    );
    println!("| --- | --- | --- | --- | --- |");
    for (path, r) in [(a_path, &a), (b_path, &b)] {
        let n = counts(r);
        println!(
            "| {path} | {} / {} | {} | {} / {} | {} / {} |",
            n.in_library.0,
            n.in_library.1,
            n.recovered_70,
            n.none.0,
            n.none.1,
            n.out_of_library.0,
            n.out_of_library.1
        );
    }
    Ok(())
}
