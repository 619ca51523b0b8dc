//! `report.html`: one self-contained page (inline SVG, no scripts, no external files).

use std::fmt::Write;

use glam::Vec3;

use crate::candidates::principal_axis;
use crate::diagnose::Diagnosis;

/// A mean error in cm, or a dash where a bin has no samples (the mean is NaN then, e.g. the
/// ground-contact phase of a cable that never touches the ground).
fn cm_or_dash(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.3}")
    } else {
        "–".to_string()
    }
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// Blue → yellow → red for t in [0, 1].
fn colour(t: f64) -> String {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let (r, g, b) = if t < 0.5 {
        let s = t * 2.0;
        (40.0 + 215.0 * s, 90.0 + 150.0 * s, 200.0 - 150.0 * s)
    } else {
        let s = (t - 0.5) * 2.0;
        (255.0, 240.0 - 190.0 * s, 50.0 - 20.0 * s)
    };
    format!("rgb({:.0},{:.0},{:.0})", r, g, b)
}

fn heat_map(d: &Diagnosis) -> String {
    let w = &d.r#where;
    let pts: Vec<Vec3> = w
        .reference_shape
        .iter()
        .map(|p| Vec3::from_array(*p))
        .collect();
    if pts.is_empty() {
        return "<p>No particles.</p>".into();
    }
    let a1 = principal_axis(&pts);
    // Second axis: the principal axis of the points with the first direction removed.
    let flat: Vec<Vec3> = pts.iter().map(|p| *p - a1 * p.dot(a1)).collect();
    let mut a2 = principal_axis(&flat);
    if a2.dot(a1).abs() > 0.9 {
        a2 = a1.any_orthonormal_vector();
    }
    let uv: Vec<(f32, f32)> = pts.iter().map(|p| (p.dot(a1), p.dot(a2))).collect();
    let (umin, umax) = uv
        .iter()
        .fold((f32::MAX, f32::MIN), |m, p| (m.0.min(p.0), m.1.max(p.0)));
    let (vmin, vmax) = uv
        .iter()
        .fold((f32::MAX, f32::MIN), |m, p| (m.0.min(p.1), m.1.max(p.1)));
    let span = (umax - umin).max(vmax - vmin).max(1e-6);
    let emax = w
        .per_particle_cm
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max)
        .max(1e-9);
    let (sw, sh) = (560.0, 300.0);
    let scale = ((sw - 40.0) / span).min((sh - 40.0) / ((vmax - vmin).max(span * 0.05)));
    let mut s = format!(
        "<svg width='{sw}' height='{}' xmlns='http://www.w3.org/2000/svg'>",
        sh + 30.0
    );
    for ((u, v), e) in uv.iter().zip(&w.per_particle_cm) {
        let x = 20.0 + (u - umin) * scale;
        let y = 20.0 + (vmax - v) * scale;
        let _ = write!(
            s,
            "<circle cx='{x:.1}' cy='{y:.1}' r='5' fill='{}'><title>{e:.2} cm</title></circle>",
            colour(e / emax)
        );
    }
    for k in 0..=10 {
        let t = f64::from(k) / 10.0;
        let _ = write!(
            s,
            "<rect x='{}' y='{}' width='20' height='10' fill='{}'/>",
            20 + k * 20,
            sh + 10.0,
            colour(t)
        );
    }
    let _ = write!(
        s,
        "<text x='250' y='{}' font-size='12'>0 … {emax:.2} cm (mean error per particle; principal-axis view)</text></svg>",
        sh + 19.0
    );
    s
}

/// Line chart of several series over steps.
fn line_chart(series: &[(&str, &str, &[f64])], ylabel: &str) -> String {
    let (w, h, l, b) = (560.0, 260.0, 50.0, 30.0);
    let n = series.iter().map(|s| s.2.len()).max().unwrap_or(0).max(2);
    let ymax = series
        .iter()
        .flat_map(|s| s.2.iter())
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max)
        .max(1e-9)
        * 1.1;
    let x = |i: usize| l + (w - l - 10.0) * i as f64 / (n - 1) as f64;
    let y = |v: f64| 10.0 + (h - b - 10.0) * (1.0 - v / ymax);
    let mut s = format!(
        "<svg width='{w}' height='{}' xmlns='http://www.w3.org/2000/svg'>",
        h + 20.0
    );
    let _ = write!(
        s,
        "<line x1='{l}' y1='{}' x2='{}' y2='{}' stroke='#444'/><line x1='{l}' y1='10' x2='{l}' y2='{}' stroke='#444'/>",
        h - b,
        w - 10.0,
        h - b,
        h - b
    );
    for k in 0..=4 {
        let v = ymax * f64::from(k) / 4.0;
        let _ = write!(
            s,
            "<text x='4' y='{:.1}' font-size='11'>{v:.2}</text>",
            y(v) + 4.0
        );
    }
    // Ticks at five evenly spaced steps; index i is the (i + 1)-th predicted step.
    for k in 0..=4usize {
        let i = (k * (n - 1) + 2) / 4;
        let _ = write!(
            s,
            "<line x1='{0:.1}' y1='{1}' x2='{0:.1}' y2='{2}' stroke='#444'/><text x='{0:.1}' y='{3}' font-size='11' text-anchor='middle'>{4}</text>",
            x(i),
            h - b,
            h - b + 4.0,
            h - b + 15.0,
            i + 1
        );
    }
    let _ = write!(
        s,
        "<text x='{}' y='{}' font-size='12'>step</text><text x='4' y='{}' font-size='12'>{}</text>",
        w / 2.0,
        h + 2.0,
        h + 14.0,
        esc(ylabel)
    );
    for (k, (name, col, v)) in series.iter().enumerate() {
        let pts: Vec<String> = v
            .iter()
            .enumerate()
            .filter(|(_, v)| v.is_finite())
            .map(|(i, v)| format!("{:.1},{:.1}", x(i), y(*v)))
            .collect();
        let _ = write!(
            s,
            "<polyline fill='none' stroke='{col}' stroke-width='2' points='{}'/>",
            pts.join(" ")
        );
        let _ = write!(
            s,
            "<rect x='{}' y='{}' width='12' height='4' fill='{col}'/><text x='{}' y='{}' font-size='12'>{}</text>",
            w - 200.0,
            18.0 + 16.0 * k as f64,
            w - 184.0,
            23.0 + 16.0 * k as f64,
            esc(name)
        );
    }
    s + "</svg>"
}

fn ranking_chart(d: &Diagnosis) -> String {
    let mut rows: Vec<_> = d.ranking.iter().collect();
    if let Some(p) = &d.probe {
        rows.push(p);
    }
    let (w, rh) = (560.0, 22.0);
    let lo = rows
        .iter()
        .map(|r| r.ci95[0])
        .fold(-0.1, f64::min)
        .max(-1.0);
    let hi = rows.iter().map(|r| r.ci95[1]).fold(0.1, f64::max).min(1.0);
    let x0 = 190.0;
    let x = |v: f64| x0 + (w - x0 - 20.0) * (v.clamp(lo, hi) - lo) / (hi - lo);
    let h = rh * rows.len() as f64 + 30.0;
    let mut s = format!("<svg width='{w}' height='{h}' xmlns='http://www.w3.org/2000/svg'>");
    let _ = write!(
        s,
        "<line x1='{0:.1}' y1='0' x2='{0:.1}' y2='{1}' stroke='#888' stroke-dasharray='3,3'/>",
        x(0.0),
        h - 20.0
    );
    for (k, r) in rows.iter().enumerate() {
        let yc = 12.0 + rh * k as f64;
        let col = if r.significant { "#1b7f3b" } else { "#999" };
        let _ = write!(
            s,
            "<text x='4' y='{:.1}' font-size='12'>{}</text>",
            yc + 4.0,
            esc(&r.effect)
        );
        let _ = write!(
            s,
            "<line x1='{:.1}' y1='{yc:.1}' x2='{:.1}' y2='{yc:.1}' stroke='{col}' stroke-width='2'/>",
            x(r.ci95[0]),
            x(r.ci95[1])
        );
        let _ = write!(
            s,
            "<circle cx='{:.1}' cy='{yc:.1}' r='4' fill='{col}'><title>{:.3}</title></circle>",
            x(r.shrinkage),
            r.shrinkage
        );
    }
    let _ = write!(
        s,
        "<text x='{x0}' y='{}' font-size='11'>{lo:.2}</text><text x='{}' y='{}' font-size='11'>{hi:.2}</text><text x='{}' y='{}' font-size='11'>shrinkage of held-out MDE (95% CI)</text></svg>",
        h - 4.0,
        w - 50.0,
        h - 4.0,
        x0 + 80.0,
        h - 4.0
    );
    s
}

fn table<'a>(head: &[&str], rows: impl Iterator<Item = Vec<String>> + 'a) -> String {
    let mut s = String::from("<table><tr>");
    for h in head {
        let _ = write!(s, "<th>{}</th>", esc(h));
    }
    s.push_str("</tr>");
    for r in rows {
        s.push_str("<tr>");
        for c in r {
            let _ = write!(s, "<td>{}</td>", esc(&c));
        }
        s.push_str("</tr>");
    }
    s + "</table>"
}

/// The substep rule as the command line names it (reports without one used `auto`).
fn substep_name(s: Option<springs::Substep>) -> String {
    match s {
        None | Some(springs::Substep::Auto { .. }) => "auto".into(),
        Some(springs::Substep::Spectral { .. }) => "spectral".into(),
        Some(springs::Substep::Fixed { dt }) => format!("fixed {dt} s"),
    }
}

/// The page for a diagnosis; `title` names the dataset.
pub fn render_html(d: &Diagnosis, title: &str) -> String {
    let w = &d.r#where;
    let mut body = String::new();
    let _ = write!(body, "<h1>Sim-to-real gap diagnosis: {}</h1>", esc(title));
    let _ = write!(
        body,
        "<p class='verdict'>Verdict: <b>{}</b></p><p>{} training / {} held-out episodes; fitted backbone held-out MDE {:.3} cm; substep rule {}; {:.0} s.</p>",
        esc(&d.verdict),
        d.episodes[0],
        d.episodes[1],
        d.backbone_as_given.mde_cm,
        substep_name(d.substep),
        d.wall_s
    );
    if let Some(b) = d.budget.as_ref().filter(|b| !b.options.is_empty()) {
        let _ = write!(
            body,
            "<p>Time budget {:.0} min: estimated {:.0} s as given{}, so the diagnosis ran with \
             <code>{}</code> (estimated {:.0} s). <code>--budget-min 0</code> runs it whole.</p>",
            b.budget_s / 60.0,
            b.full_estimated_s,
            if b.margin > 1.0 {
                format!(
                    ", each estimate counted {:.2} times against the budget (the largest \
                     overrun measured)",
                    b.margin
                )
            } else {
                String::new()
            },
            esc(&b.options),
            b.estimated_s
        );
    }
    let base: Vec<String> = d.control.base.iter().map(|b| b.label()).collect();
    let _ = write!(
        body,
        "<p>Model diagnosed: spring-mass backbone{}. Control refit: held-out MDE {:.3} cm.</p>",
        if base.is_empty() {
            " alone".to_string()
        } else {
            esc(&format!(
                " + base effects {} (refitted with it; values after the control refit)",
                base.join(", ")
            ))
        },
        d.control.heldout_mde_cm
    );
    if let Some(c) = d.carry_over_caution() {
        let _ = write!(body, "<p class='caution'>Caution: {}.</p>", esc(&c));
    }
    if let Some(t) = &d.tie_break {
        let _ = write!(
            body,
            "<p>Tied on held-out error (the best, {}, does not beat the others significantly): {}. \
             Chosen by the signature cosine: <b>{}</b>.</p>",
            esc(&t.by_shrinkage),
            esc(&t.tied.join(", ")),
            esc(&t.chosen)
        );
    }
    if let Some(h) = &d.how_far {
        if h.effect == d.verdict {
            let _ = write!(body, "<h2>How far: adding {}</h2>", esc(&h.effect));
        } else {
            // `none` / `unknown`: the top-ranked candidate, shown for reference only.
            let _ = write!(
                body,
                "<h2>How far: adding {}, the best candidate (not the verdict)</h2>",
                esc(&h.effect)
            );
        }
        body += &table(
            &["metric (held-out, cm)", "before", "after", "shrinkage"],
            [
                ("MDE", h.before.mde_cm, h.after.mde_cm, h.shrinkage_mde),
                (
                    "Chamfer (two-sided)",
                    h.before.chamfer_cm,
                    h.after.chamfer_cm,
                    h.shrinkage_chamfer,
                ),
                ("EMD", h.before.emd_cm, h.after.emd_cm, h.shrinkage_emd),
            ]
            .into_iter()
            .map(|(n, b, a, s)| {
                vec![
                    n.to_string(),
                    format!("{b:.3}"),
                    format!("{a:.3}"),
                    format!("{:.1}%", 100.0 * s),
                ]
            }),
        );
        body += &line_chart(
            &[
                ("before (backbone)", "#c0392b", &h.before.per_step_mde_cm),
                ("after (+effect)", "#1b7f3b", &h.after.per_step_mde_cm),
            ],
            "held-out MDE, cm",
        );
    }
    if let Some(l) = &d.learnable {
        body += "<h2>How much is learnable: the trained residual network</h2>";
        let _ = write!(
            body,
            "<p>Held-out MDE {:.3} cm with the network against {:.3} cm for its backbone{}.</p>",
            l.network_mde_cm,
            l.backbone_mde_cm,
            if l.changed_verdict {
                "; no library effect helps significantly, but the network beats the control by \
                 at least the probe margin, so the verdict is <b>unknown</b>"
            } else {
                ""
            }
        );
        body += &table(
            &["network against", "shrinkage", "95% CI"],
            [
                ("its backbone".to_string(), l.vs_backbone),
                (l.model.clone(), l.vs_model),
            ]
            .into_iter()
            .map(|(name, c)| {
                vec![
                    name,
                    format!("{:+.3}", c.shrinkage),
                    format!("[{:+.3}, {:+.3}]", c.ci95[0], c.ci95[1]),
                ]
            }),
        );
    }
    body += "<h2>Which: candidates ranked</h2>";
    // A race asked for but with nothing to cut (no more candidates than it keeps) ran none.
    if d.ranking.iter().any(|r| r.raced_out) {
        let _ = write!(
            body,
            "<p>Refits raced: every candidate ran half of its {} generations; the best {} by \
             training loss ran the rest. The others (marked &ldquo;raced out&rdquo;) are scored \
             at their halfway parameters.</p>",
            d.config.generations, d.config.race
        );
    }
    body += &ranking_chart(d);
    body += &table(
        &[
            "effect",
            "MDE before",
            "MDE after",
            "shrinkage",
            "95% CI",
            "vs effect off",
            "significant",
            "signature cos",
        ],
        d.ranking.iter().chain(d.probe.iter()).map(|r| {
            vec![
                if r.raced_out {
                    format!("{} (raced out)", r.effect)
                } else {
                    r.effect.clone()
                },
                format!("{:.3}", r.heldout_mde_before_cm),
                format!("{:.3}", r.heldout_mde_after_cm),
                format!("{:+.3}", r.shrinkage),
                format!("[{:+.3}, {:+.3}]", r.ci95[0], r.ci95[1]),
                r.effect_itself.map_or("–".into(), |c| {
                    format!("{:+.3} [{:+.3}, {:+.3}]", c.shrinkage, c.ci95[0], c.ci95[1])
                }),
                if r.significant { "yes" } else { "no" }.to_string(),
                format!("{:+.2}", r.signature_cosine),
            ]
        }),
    );
    if let (Some(st), Some(_)) = (&d.probe_start, &d.probe) {
        let f = &st.focus;
        let [x, y, z] = f.point_m;
        let _ = write!(
            body,
            "<p>The external-field probe (the last row) was refitted from two starts: a field \
             centred where the backbone's residuals on training episodes converge, ({x:.3}, \
             {y:.3}, {z:.3}) m, {}, with a window of {:.3} m (training loss {:.3e} m²), and a \
             broad field about the data's mean (training loss {:.3e} m²){}. The row is the \
             refit from the {} start, the lower training loss{}.</p>",
            if f.attracting {
                "pulling toward it"
            } else {
                "pushing away from it"
            },
            f.window_m(),
            st.focus_train_loss_m2,
            st.broad_train_loss_m2,
            if st.raced {
                ", both after half the generations (the starts were raced)"
            } else {
                ""
            },
            if st.from_focus { "focus" } else { "broad" },
            if st.raced {
                " halfway; only it ran the second half"
            } else {
                ""
            }
        );
    }
    body += "<h2>Where: error on the object</h2>";
    if w.skipped_episodes > 0 {
        let _ = write!(
            body,
            "<p class='caution'>{} held-out episode(s) left out of this section: their \
             tracked count differs from the first episode's.</p>",
            w.skipped_episodes
        );
    }
    body += &heat_map(d);
    body += &table(
        &["region", "range of axis coordinate", "mean error (cm)"],
        w.regions.iter().map(|b| {
            vec![
                b.label.clone(),
                format!("[{:+.2}, {:+.2}]", b.range[0], b.range[1]),
                cm_or_dash(b.mean_error_cm),
            ]
        }),
    );
    body += "<h2>Where: error over time</h2>";
    body += &line_chart(
        &[("fitted backbone", "#2c3e50", &w.per_step_cm)],
        "held-out MDE, cm",
    );
    body += &table(
        &["phase", "share of samples", "mean error (cm)"],
        w.phases.iter().map(|b| {
            vec![
                b.label.clone(),
                format!("{:.1}%", 100.0 * b.share),
                cm_or_dash(b.mean_error_cm),
            ]
        }),
    );
    body += "<h2>Where: error against state</h2>";
    for t in &w.state {
        let _ = write!(
            body,
            "<h3>{} (Spearman {:+.2})</h3>",
            esc(&t.quantity),
            t.spearman
        );
        body += &table(
            &["quintile", "range", "mean error (cm)"],
            t.bins.iter().map(|b| {
                vec![
                    b.label.clone(),
                    format!("[{:.3}, {:.3}]", b.range[0], b.range[1]),
                    cm_or_dash(b.mean_error_cm),
                ]
            }),
        );
    }
    format!(
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>pgrd diagnosis: {}</title><style>body{{font-family:sans-serif;max-width:900px;margin:20px auto;color:#222}}table{{border-collapse:collapse;margin:8px 0}}td,th{{border:1px solid #ccc;padding:3px 8px;font-size:13px}}.verdict{{font-size:22px}}.caution{{background:#fff4d6;border-left:4px solid #e0a000;padding:6px 10px}}svg{{display:block;margin:8px 0;background:#fafafa}}</style></head><body>{}</body></html>\n",
        esc(title),
        body
    )
}

#[cfg(test)]
mod tests {
    use super::{cm_or_dash, line_chart};

    #[test]
    fn empty_bins_show_a_dash_not_nan() {
        assert_eq!(cm_or_dash(f64::NAN), "–");
        assert_eq!(cm_or_dash(1.23456), "1.235");
    }

    #[test]
    fn the_time_axis_is_labelled_from_the_first_to_the_last_step() {
        let v: Vec<f64> = (0..37).map(f64::from).collect();
        let svg = line_chart(&[("backbone", "#000", &v)], "cm");
        let ticks: Vec<&str> = svg
            .split("text-anchor='middle'>")
            .skip(1)
            .map(|t| t.split('<').next().unwrap())
            .collect();
        assert_eq!(ticks, ["1", "10", "19", "28", "37"]);
    }
}
