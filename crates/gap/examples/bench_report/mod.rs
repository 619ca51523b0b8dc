//! What the bench examples share: reading a `diagnose-bench --json` report, and the rule by
//! which the bench counts a case toward the goals.

use anyhow::{Context, bail};
use serde_json::Value;

/// The share of its effect-attributable gap a right verdict must recover (the goal).
pub const RECOVERED_GOAL: f64 = 0.7;

/// Reads a bench report, refusing a file without a `cases` array.
pub fn read_report(path: &str) -> anyhow::Result<Value> {
    let text = std::fs::read_to_string(path).with_context(|| path.to_string())?;
    let report: Value = serde_json::from_str(&text).with_context(|| format!("parsing {path}"))?;
    if report.get("cases").and_then(Value::as_array).is_none() {
        bail!("{path}: no `cases` array (not a `diagnose-bench --json` report)");
    }
    Ok(report)
}

/// Whether the goals count `case`: an in-library case only when its effect reached the
/// target raise, `none` and out-of-library cases always, in-base cases never (their effect is
/// in the object's base model).
pub fn counted(case: &Value) -> bool {
    let reached = case.get("target_reached").and_then(Value::as_bool) == Some(true);
    match case.get("class").and_then(Value::as_str) {
        Some("in-library") => reached,
        Some("none" | "out-of-library") => true,
        _ => false,
    }
}
