//! The bench as a page (`<json>.html` beside `--json`): the confusion matrix with each cell
//! shaded by its share of the row, green where its verdicts are right and red where they are
//! not, then every case. Drawn from the summary's JSON, so any stored bench can be drawn again.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context;
use serde_json::Value;

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

fn share(v: &Value) -> String {
    v.as_f64()
        .filter(|s| s.is_finite())
        .map_or("–".to_string(), |s| format!("{:.0} %", 100.0 * s))
}

fn number(v: &Value, digits: usize) -> String {
    v.as_f64()
        .map_or("–".to_string(), |x| format!("{x:.digits$}"))
}

/// Writes the page of a bench summary (`BenchSummary` as JSON) to `path`.
pub fn write(path: &Path, summary: &Value) -> anyhow::Result<()> {
    let cases = summary["cases"].as_array().cloned().unwrap_or_default();
    let mut html = String::from(
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>diagnose-bench</title><style>\
         body{font-family:sans-serif;margin:2em;color:#222}\
         table{border-collapse:collapse;margin:1em 0}\
         td,th{padding:.25em .6em;border:1px solid #ddd;text-align:right}\
         td:first-child,th:first-child{text-align:left}\
         </style></head><body>\n<h1>diagnose-bench</h1>\n",
    );
    let _ = writeln!(
        html,
        "<p>In-library verdicts right: {} of {} cases whose effect reached the target ({} of \
         all {}); <code>none</code> right: {}; <code>unknown</code> right: {}; in-base: {}. \
         Median share of the effect-attributable gap recovered {}, at least 70 % in {} of \
         cases. {} s.</p>",
        share(&summary["in_library_accuracy"]),
        number(&summary["in_library_cases"][0], 0),
        share(&summary["in_library_accuracy_all"]),
        number(&summary["in_library_cases"][1], 0),
        share(&summary["none_accuracy"]),
        share(&summary["unknown_accuracy"]),
        share(&summary["in_base_accuracy"]),
        share(&summary["median_recovered"]),
        share(&summary["recovered_70_share"]),
        number(&summary["wall_s"], 0),
    );
    // The matrix: rows the effect in the data, columns the verdict. A cell is right when every
    // case in it got the verdict it should (an in-base effect should get `none`).
    let rows = summary["confusion"].as_array().cloned().unwrap_or_default();
    let columns: Vec<String> = rows
        .first()
        .and_then(|r| r[1].as_array())
        .map(|c| {
            c.iter()
                .filter_map(|p| p[0].as_str().map(str::to_string))
                .collect()
        })
        .unwrap_or_default();
    html.push_str(
        "<h2>Confusion matrix</h2>\n<p>Rows: the effect in the data; columns: the verdict. \
         Green: right verdicts, red: wrong ones, darker for a larger share of the row; every \
         case counted, reached its target or not.</p>\n<table><tr><th>withheld ↓ / verdict \
         →</th>",
    );
    for c in &columns {
        let _ = write!(html, "<th>{}</th>", escape(c));
    }
    html.push_str("</tr>\n");
    for row in &rows {
        let truth = row[0].as_str().unwrap_or("?");
        let counts: Vec<u64> = row[1]
            .as_array()
            .map(|c| c.iter().map(|p| p[1].as_u64().unwrap_or(0)).collect())
            .unwrap_or_default();
        let total = counts.iter().sum::<u64>().max(1) as f64;
        let _ = write!(html, "<tr><td>{}</td>", escape(truth));
        for (verdict, n) in columns.iter().zip(&counts) {
            if *n == 0 {
                html.push_str("<td style=\"color:#bbb\">·</td>");
                continue;
            }
            let right = cases.iter().any(|c| {
                c["truth"] == truth
                    && c["verdict"] == verdict.as_str()
                    && c["expected"] == c["verdict"]
            });
            let alpha = 0.15 + 0.6 * (*n as f64 / total);
            let color = if right { (44, 160, 44) } else { (214, 39, 40) };
            let _ = write!(
                html,
                "<td style=\"background:rgba({},{},{},{alpha:.2})\">{n}</td>",
                color.0, color.1, color.2
            );
        }
        html.push_str("</tr>\n");
    }
    html.push_str(
        "</table>\n<h2>Cases</h2>\n<table><tr><th>object</th><th>withheld</th><th>class</th>\
         <th>strength</th><th>target reached</th><th>expected</th><th>verdict</th>\
         <th>held-out MDE, cm</th><th>true effect's shrinkage</th><th>gap recovered</th>\
         <th>s</th></tr>\n",
    );
    for c in &cases {
        let right = c["verdict"] == c["expected"];
        let _ = writeln!(
            html,
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>×{}</td><td>{}</td><td>{}</td>\
             <td style=\"color:{}\">{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            escape(c["object"].as_str().unwrap_or("?")),
            escape(c["truth"].as_str().unwrap_or("?")),
            escape(c["class"].as_str().unwrap_or("?")),
            number(&c["scale"], 0),
            if c["target_reached"].as_bool() == Some(true) {
                "yes"
            } else {
                "no"
            },
            escape(c["expected"].as_str().unwrap_or("?")),
            if right { "#2c8a2c" } else { "#c62828" },
            escape(c["verdict"].as_str().unwrap_or("?")),
            number(&c["mde_before_cm"], 3),
            share(&c["shrinkage"]),
            share(&c["recovered"]),
            number(&c["diagnose_wall_s"], 0),
        );
    }
    html.push_str("</table>\n</body></html>\n");
    dataset::write_atomic(path, html.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}
