//! `out/demo/index.html`: one page that shows what `cargo xtask demo` wrote, each object's
//! fit, error curve and point clouds, then the tour's training curves, comparison, rendered
//! frames, diagnosis and planning trial. It links the files where they lie (relative paths),
//! so it opens offline from the output directory; a file the run did not write is left out.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context;

/// One object's row of the demo's table: name, then val MDE, two-sided Chamfer and EMD, cm.
pub type Row = (String, f64, f64, f64);

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// A picture (`<img>`) or a link for each of `files` (relative to `out`) that exists, with its
/// caption.
fn figures(out: &Path, files: &[(&str, &str)]) -> String {
    let mut html = String::new();
    for (file, caption) in files {
        if !out.join(file).is_file() {
            continue;
        }
        let (file, caption) = (escape(file), escape(caption));
        let is_picture = [".svg", ".png", ".gif"].iter().any(|e| file.ends_with(e));
        if is_picture {
            let _ = writeln!(
                html,
                "<figure><a href=\"{file}\"><img src=\"{file}\" alt=\"{caption}\"></a>\
                 <figcaption>{caption}</figcaption></figure>"
            );
        } else {
            let _ = writeln!(html, "<p><a href=\"{file}\">{file}</a>: {caption}</p>");
        }
    }
    html
}

/// Writes `<out>/index.html` for the demo's `rows` and, when this run made it (`toured`), its
/// tour (`<out>/tour`).
pub fn write(out: &Path, rows: &[Row], toured: bool) -> anyhow::Result<()> {
    let mut html = String::from(
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>pgrd demo</title><style>\
         body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}\
         table{border-collapse:collapse}td,th{padding:.2em .8em;border-bottom:1px solid #ccc;\
         text-align:right}td:first-child,th:first-child{text-align:left}\
         figure{display:inline-block;margin:.5em;vertical-align:top}\
         img{max-width:520px;border:1px solid #ddd}figcaption{font-size:90%;color:#555}\
         </style></head><body>\n<h1>pgrd demo</h1>\n\
         <p>The spring-mass backbone fitted (CMA-ES) on each bundled fixture's training episodes \
         and rolled out on its validation episodes from their first frames. Errors in cm, the \
         mean over episodes at each step, then over steps (<code>docs/pipelines.md</code>).</p>\n\
         <table><tr><th>object</th><th>MDE</th><th>Chamfer (two-sided)</th><th>EMD</th></tr>\n",
    );
    for (name, mde, chamfer, emd) in rows {
        let _ = writeln!(
            html,
            "<tr><td><a href=\"#{0}\">{0}</a></td><td>{mde:.3}</td><td>{chamfer:.3}</td>\
             <td>{emd:.3}</td></tr>",
            escape(name)
        );
    }
    html.push_str("</table>\n");
    for (name, ..) in rows {
        let _ = writeln!(html, "<h2 id=\"{0}\">{0}</h2>", escape(name));
        let file = |f: &str| format!("{name}/{f}");
        let (fit, eval, graph, springs, pred, truth) = (
            file("fit.svg"),
            file("eval_val.svg"),
            file("springs.svg"),
            file("springs.ply"),
            file("final_predicted.ply"),
            file("final_truth.ply"),
        );
        html.push_str(&figures(
            out,
            &[
                (&fit, "the CMA-ES search: loss per generation"),
                (
                    &eval,
                    "the fitted backbone's error per step on the val episodes",
                ),
                (
                    &graph,
                    "the fitted spring graph on the first training episode (held particles \
                     blue, loose ones red)",
                ),
                (&springs, "the same graph in 3D (MeshLab, Blender)"),
                (
                    &pred,
                    "the last predicted step of the first val episode (point cloud)",
                ),
                (&truth, "its recorded truth"),
            ],
        ));
    }
    if toured {
        html.push_str(
            "<h2 id=\"tour\">The tour, on the rope</h2>\n<p>Each stage ran its own command \
             (printed by the demo). On a fixture's three training episodes the network has \
             too little to learn from; <code>docs/RESULTS.md</code> has every stage on 100 \
             episodes.</p>\n",
        );
        html.push_str(&figures(
            out,
            &[
                ("tour/run/train.svg", "training the residual network"),
                (
                    "tour/compare.svg",
                    "spring-mass against pgrd: error per step and per episode",
                ),
                (
                    "tour/render/strip.png",
                    "rendered: truth, prediction, masks (red: missed, cyan: extra)",
                ),
                ("tour/render/compare.gif", "prediction | truth, real time"),
                (
                    "tour/report/report.html",
                    "the gap diagnosis: where the error lies, which effect, how far it shrinks",
                ),
                (
                    "tour/plan/rope-lift.svg",
                    "planning the rope lift: Chamfer distance per step",
                ),
                (
                    "tour/plan/rope-lift_spring-mass.gif",
                    "the lift planned with spring-mass",
                ),
                ("tour/plan/rope-lift_pgrd.gif", "the lift planned with pgrd"),
            ],
        ));
    }
    html.push_str("</body></html>\n");
    let path = out.join("index.html");
    dataset::write_atomic(&path, html.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_index_shows_what_was_written_and_only_that() {
        let out = std::env::temp_dir().join(format!("pgrd-demo-index-{}", std::process::id()));
        std::fs::create_dir_all(out.join("rope")).unwrap();
        std::fs::create_dir_all(out.join("tour/run")).unwrap();
        std::fs::write(out.join("rope/fit.svg"), "<svg/>").unwrap();
        std::fs::write(out.join("rope/springs.ply"), "ply").unwrap();
        std::fs::write(out.join("tour/run/train.svg"), "<svg/>").unwrap();
        let rows = vec![
            ("rope".to_string(), 2.0, 2.5, 1.9),
            ("a<b".to_string(), 1.0, 1.0, 1.0),
        ];
        write(&out, &rows, true).unwrap();
        let html = std::fs::read_to_string(out.join("index.html")).unwrap();
        assert!(html.contains("<img src=\"rope/fit.svg\""), "{html}");
        assert!(html.contains("<a href=\"rope/springs.ply\">"));
        assert!(html.contains("<img src=\"tour/run/train.svg\""));
        assert!(
            !html.contains("eval_val.svg"),
            "a file not written is left out"
        );
        assert!(!html.contains("tour/compare.svg"));
        assert!(html.contains("<td>2.000</td><td>2.500</td>"));
        assert!(html.contains("a&lt;b") && !html.contains("a<b"));
        // A run without the tour does not show an earlier run's.
        write(&out, &rows, false).unwrap();
        let html = std::fs::read_to_string(out.join("index.html")).unwrap();
        assert!(!html.contains("tour/run/train.svg") && html.contains("rope/fit.svg"));
        std::fs::remove_dir_all(&out).unwrap();
    }
}
