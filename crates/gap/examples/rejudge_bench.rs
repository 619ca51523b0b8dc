//! How a `diagnose-bench` run's verdicts depend on the verdict rule, without refitting: every
//! stored case report is re-judged ([`gap::Diagnosis::rejudge`]) under each rule and the bench's
//! counts are printed per class. A rule is a floor (`--min-shrinkage`), optionally followed by
//! `/` and a probe margin ([`gap::VerdictRule::probe_margin`]; without it, the stored rule's).
//!
//! ```sh
//! cargo run --release -p pgrd-gap --example rejudge_bench -- <bench.json> <work-dir> 0.05,0.07
//! cargo run --release -p pgrd-gap --example rejudge_bench -- <bench.json> <work-dir> 0.05/0.1,0.05/0.05
//! # the tie-break's least cosine as a third part (`gap::VerdictRule::tie_break_min_cosine`)
//! cargo run --release -p pgrd-gap --example rejudge_bench -- <bench.json> <work-dir> 0.1/0.1/0,0.1/0.1/0.2
//! ```
//!
//! Exact for a case as long as its object's base search (the no-effect diagnoses that chose the
//! base effects every case is judged against) reaches the same verdicts under that rule; objects
//! where it does not are marked `?`, since a real run under that rule would diagnose their cases
//! against another base model. A bench run with `--second-round` is replayed with its second
//! rounds (`report-round2`, judged under the same rule) where the re-judged first round names
//! the effect the stored second round added; where it names another effect, or one where the
//! stored first round named none, the answer is the first round's, marked `²?`.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use anyhow::{Context, bail};
use gap::{Diagnosis, VerdictRule};

fn read(path: &Path) -> anyhow::Result<Diagnosis> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

/// A rule given on the command line: a floor and, optionally, a probe margin and the
/// tie-break's least cosine.
#[derive(Clone, Copy)]
struct RuleSpec {
    floor: f64,
    probe_margin: Option<f64>,
    min_cosine: Option<f64>,
}

impl RuleSpec {
    fn parse(text: &str) -> anyhow::Result<Self> {
        let mut parts = text.trim().splitn(3, '/');
        let floor = parts.next().unwrap_or_default();
        let (margin, cosine) = (parts.next(), parts.next());
        Ok(RuleSpec {
            min_cosine: cosine
                .map(|c| {
                    c.parse()
                        .with_context(|| format!("tie-break cosine of {text:?}"))
                })
                .transpose()?,
            floor: floor
                .parse()
                .with_context(|| format!("floor of {text:?}"))?,
            probe_margin: margin
                .map(|m| {
                    m.parse()
                        .with_context(|| format!("probe margin of {text:?}"))
                })
                .transpose()?,
        })
    }

    fn rule(&self, d: &Diagnosis) -> VerdictRule {
        VerdictRule {
            min_shrinkage: self.floor,
            probe_margin: self.probe_margin.unwrap_or(d.config.rule.probe_margin),
            tie_break_min_cosine: self
                .min_cosine
                .unwrap_or(d.config.rule.tie_break_min_cosine),
            ..d.config.rule
        }
    }
}

impl std::fmt::Display for RuleSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (self.probe_margin, self.min_cosine) {
            (Some(m), Some(c)) => write!(f, "{}/{m}/{c}", self.floor),
            (Some(m), None) => write!(f, "{}/{m}", self.floor),
            (None, _) => write!(f, "{}", self.floor),
        }
    }
}

/// The bench's answer for a case under a rule, and whether the stored reports replay it
/// exactly: the first round's verdict `first` (already re-judged), unless the bench ran a second
/// round and that round, judged under the same rule, says `unknown`. The stored second round
/// was diagnosed with the stored first round's effect added, so it replays the bench only when
/// the re-judged first round names that same effect; a first round that newly names an effect
/// (or another one) would have had a second round no report holds.
fn bench_answer(
    round1: &Diagnosis,
    round2: Option<&Diagnosis>,
    first: String,
    rule: &RuleSpec,
    second_round: bool,
) -> anyhow::Result<(String, bool)> {
    let names_effect = first != "none" && first != "unknown";
    if !second_round || !names_effect {
        return Ok((first, true));
    }
    match round2 {
        Some(d2) if first == round1.verdict => {
            let v2 = d2.rejudge(rule.rule(d2))?.verdict;
            Ok((if v2 == "unknown" { v2 } else { first }, true))
        }
        _ => Ok((first, false)),
    }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [bench, work, floors] = args.as_slice() else {
        bail!(
            "usage: rejudge_bench <bench.json> <work-dir> <floor>[/<probe margin>[/<tie-break cosine>]][,...]"
        );
    };
    let floors: Vec<RuleSpec> = floors
        .split(',')
        .map(RuleSpec::parse)
        .collect::<Result<_, _>>()?;
    let work = Path::new(work);
    let text = std::fs::read_to_string(bench).with_context(|| bench.clone())?;
    let json: serde_json::Value = serde_json::from_str(&text)?;
    // A finished bench writes a summary with `cases`; one still running or interrupted, the
    // pair (objects, cases).
    let cases = json["cases"]
        .as_array()
        .or_else(|| json[1].as_array())
        .context("no cases in the bench file")?;

    // Whether the bench ran `--second-round` (it records both rounds' verdicts).
    let second_round = cases.iter().any(|c| c["rounds"].is_array());

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
                let v = d.rejudge(f.rule(&d))?.verdict;
                if v != d.verdict {
                    println!(
                        "{object}: base search step {step} {} -> {v} under rule {f}",
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
        let d = read(&work.join(&dir).join("report/report.json"))?;
        // With `--second-round` the bench diagnosed again, with the first round's effect
        // added, every case whose first round named an effect.
        let round2_path = work.join(&dir).join("report-round2/report.json");
        let round2 = if round2_path.exists() {
            Some(read(&round2_path)?)
        } else {
            None
        };
        let mut class = s("class");
        if class == "in-library" && !reached {
            class.push_str(" (target not reached)");
        }
        let row = tally
            .entry(class)
            .or_insert_with(|| vec![(0, 0); floors.len()]);
        let mut line = format!(
            "{object:<6} {truth:<24} expected {expected:<24} stored {:<24}",
            s("verdict")
        );
        for (k, f) in floors.iter().enumerate() {
            let first = d.rejudge(f.rule(&d))?.verdict;
            let (v, replay) = bench_answer(&d, round2.as_ref(), first, f, second_round)?;
            let mut mark = String::new();
            if inexact.contains(&(object.clone(), k)) {
                mark.push('?');
            }
            if !replay {
                mark.push_str("²?");
            }
            line.push_str(&format!(" {f}: {v}{mark}"));
            row[k].0 += usize::from(v == expected);
            row[k].1 += 1;
        }
        println!("{line}");
    }
    println!(
        "\nright / counted per class, rule by rule (floor[/probe margin[/tie-break cosine]]: {})",
        floors
            .iter()
            .map(RuleSpec::to_string)
            .collect::<Vec<_>>()
            .join(", ")
    );
    for (class, row) in tally {
        let cells: Vec<String> = row.iter().map(|(r, n)| format!("{r} / {n}")).collect();
        println!("{class:<36} {}", cells.join("   "));
    }
    Ok(())
}
