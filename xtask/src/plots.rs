//! A run's own progress as pictures: how a fit's CMA-ES search converged (`fit.svg`), how
//! `refine` descended (`refine.svg`), how a network trained (`train.svg`), how two evaluations
//! compare (`compare --plot`), what each round of a diagnosis chain bought (`chain.svg`), and
//! `eval`'s and `plan`'s curves. Drawn from the numbers the JSON files beside
//! them record, written (atomically) whenever those are, so a long run can be watched in a
//! browser and a finished one read at a glance.

use std::path::Path;

use anyhow::Context;
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

type Area<'a> = DrawingArea<SVGBackend<'a>, Shift>;

/// Line colours in order (matplotlib's first six, which readers of the field know).
const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];
const BLUE: RGBColor = PALETTE[0];
const RED: RGBColor = PALETTE[1];
const GREEN: RGBColor = PALETTE[2];
const GREY: RGBColor = RGBColor(127, 127, 127);

/// Reports a picture that could not be drawn as a warning: the run's numbers are written
/// already, and a long training must not stop for its plot.
pub fn or_warn(drawn: anyhow::Result<()>, what: &str) {
    if let Err(e) = drawn {
        eprintln!("warning: could not draw {what}: {e:#}");
    }
}

/// The mean of the finite values among the last `window` entries up to each index (`NaN` where
/// there is none). Training losses are one batch each, too noisy to read step by step; the
/// backbone's yardstick is scored only every few steps, `NaN` between.
pub fn trailing_mean(values: &[f64], window: usize) -> Vec<f64> {
    let window = window.max(1);
    let (mut sum, mut count) = (0.0, 0usize);
    let mut out = Vec::with_capacity(values.len());
    for (i, &v) in values.iter().enumerate() {
        if v.is_finite() {
            sum += v;
            count += 1;
        }
        if i >= window {
            let old = values[i - window];
            if old.is_finite() {
                sum -= old;
                count -= 1;
            }
        }
        // Summing a running window drifts by rounding; recomputing when the window empties
        // keeps a long run's curve from carrying that drift.
        if count == 0 {
            sum = 0.0;
        }
        out.push(if count > 0 {
            sum / count as f64
        } else {
            f64::NAN
        });
    }
    out
}

/// Ends of a logarithmic axis holding every positive finite value, at whole decades: the
/// axis labels powers of ten and the steps between, so a range inside one decade would show
/// one label or none.
fn log_range(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    let (lo, hi) = values
        .filter(|v| v.is_finite() && *v > 0.0)
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    (hi > 0.0).then(|| {
        let low = lo.log10().floor();
        let high = hi.log10().ceil().max(low + 1.0);
        // A hair below the decade, so that rounding in the axis's own logarithm keeps its label.
        (10f64.powf(low) * 0.999, 10f64.powf(high))
    })
}

/// Upper end of a linear axis from 0 that holds every finite value.
fn linear_top(values: impl Iterator<Item = f64>) -> f64 {
    let top = values.filter(|v| v.is_finite()).fold(0.0f64, f64::max);
    if top > 0.0 { top * 1.1 } else { 1.0 }
}

/// Draws one picture of `size` pixels with `draw` and writes it to `path` as SVG, atomically.
fn svg_to(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&Area<'_>) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE)?;
        draw(&root)?;
        root.present()?;
    }
    dataset::write_atomic(path, svg.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

/// `fit.svg`: per CMA-ES generation the best loss so far, the generation's best and its
/// median candidate, in m² on a logarithmic axis (the values `backbone.json`'s `fit.history`
/// holds; a candidate that diverged scores the fit's penalty and lifts the median to it).
pub fn fit_svg(path: &Path, object: &str, history: &[fit::Generation]) -> anyhow::Result<()> {
    svg_to(path, (760, 460), |root| {
        let series = [
            (
                "best so far",
                BLUE,
                history.iter().map(|g| g.best_so_far).collect::<Vec<_>>(),
            ),
            (
                "the generation's best",
                GREEN,
                history.iter().map(|g| g.best_loss).collect(),
            ),
            (
                "the generation's median",
                GREY,
                history.iter().map(|g| g.median_loss).collect(),
            ),
        ];
        let Some((lo, hi)) = log_range(series.iter().flat_map(|s| s.2.iter().copied())) else {
            root.draw(&Text::new(
                "no finite loss recorded",
                (40, 40),
                ("sans-serif", 16),
            ))?;
            return Ok(());
        };
        let last = history.len().max(2) as f64;
        let mut chart = ChartBuilder::on(root)
            .caption(format!("fit: {object}, CMA-ES"), ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(72)
            .build_cartesian_2d(1.0..last, (lo..hi).log_scale())?;
        chart
            .configure_mesh()
            .x_desc("generation")
            .y_desc("loss, m²")
            .x_label_formatter(&|v| format!("{v:.0}"))
            // Enough for plotters to label 2, 3, ... 9 within each decade, not only its powers.
            .y_labels(40)
            .y_label_formatter(&|v| format!("{v:.1e}"))
            .light_line_style(WHITE.mix(0.0))
            .draw()?;
        for (label, color, y) in series {
            let points = y
                .into_iter()
                .enumerate()
                .filter(|(_, v)| v.is_finite() && *v > 0.0)
                .map(|(i, v)| (i as f64 + 1.0, v))
                .collect::<Vec<_>>();
            chart
                .draw_series(LineSeries::new(
                    points.iter().copied(),
                    color.stroke_width(2),
                ))?
                .label(label)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color));
            chart.draw_series(points.iter().map(|&p| Circle::new(p, 3, color.filled())))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .position(SeriesLabelPosition::UpperRight)
            .draw()?;
        Ok(())
    })
}

/// The held-out checks of a training run's network selection, for [`train_svg`].
pub struct Checks<'a> {
    /// Optimiser steps checked.
    pub steps: &'a [usize],
    /// Held-out rollout MDE at those steps, cm (`None`: a rollout diverged).
    pub mde_cm: &'a [Option<f64>],
    /// The backbone alone on the same episodes, cm.
    pub backbone_mde_cm: f64,
    /// The step whose network the run keeps.
    pub best_step: usize,
}

/// What [`train_svg`] draws.
pub struct TrainCurves<'a> {
    /// Object and variant, for the title.
    pub title: String,
    /// Training loss per optimiser step, in `unit`.
    pub loss: &'a [f64],
    /// The backbone alone on the same segments, per step (`NaN` where not scored).
    pub backbone_loss: &'a [f64],
    /// `cm²` or `cm`.
    pub unit: &'a str,
    /// The selection's checks, when the run holds episodes out.
    pub checks: Option<Checks<'a>>,
}

/// Steps averaged for the training-loss curve: about a twentieth of the run, 1 to 100.
pub fn smoothing_window(steps: usize) -> usize {
    (steps / 20).clamp(1, 100)
}

/// Over the last `window` steps up to each index, the network's summed loss over the
/// backbone's, on the steps where both were scored (`NaN` where none was): the same segments
/// in numerator and denominator, so what changes from batch to batch cancels.
pub fn trailing_ratio(loss: &[f64], backbone: &[f64], window: usize) -> Vec<f64> {
    let both = |j: usize| {
        let (l, b) = (loss[j], backbone.get(j).copied().unwrap_or(f64::NAN));
        (l.is_finite() && b.is_finite() && b > 0.0).then_some((l, b))
    };
    (0..loss.len())
        .map(|i| {
            let (l, b) = (i + 1 - window.max(1).min(i + 1)..=i)
                .filter_map(both)
                .fold((0.0, 0.0), |(sl, sb), (l, b)| (sl + l, sb + b));
            if b > 0.0 { l / b } else { f64::NAN }
        })
        .collect()
}

/// One panel of curves (colour, points) against a step count, titled by `caption`, the y axis
/// from `y.0` to `y.1`.
fn panel<'a, 'b>(
    area: &'a Area<'b>,
    caption: &str,
    x_desc: &str,
    y_desc: &str,
    x_right: f64,
    y: (f64, f64),
    curves: &[(RGBColor, Vec<(f64, f64)>)],
) -> anyhow::Result<ChartContext<'a, SVGBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>> {
    let mut chart = ChartBuilder::on(area)
        .caption(caption, ("sans-serif", 15))
        .margin(8)
        .x_label_area_size(28)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..x_right, y.0..y.1)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .x_label_formatter(&|v| format!("{v:.0}"))
        // Losses in m² are thousandths: two decimals would print them all as 0.00.
        .y_label_formatter(&|v| {
            if y.1.abs() < 0.1 {
                format!("{v:.1e}")
            } else {
                format!("{v:.2}")
            }
        })
        .light_line_style(WHITE.mix(0.0))
        .draw()?;
    for (color, points) in curves {
        chart.draw_series(LineSeries::new(
            points.iter().copied(),
            color.stroke_width(2),
        ))?;
    }
    Ok(chart)
}

/// The finite values of `y`, as points at steps 1, 2, ...
fn by_step(y: &[f64]) -> Vec<(f64, f64)> {
    y.iter()
        .enumerate()
        .filter(|(_, v)| v.is_finite())
        .map(|(i, v)| (i as f64 + 1.0, *v))
        .collect()
}

/// An axis spanning `values` with some room: held-out errors and loss ratios differ by a few
/// per cent to tens of per cent, which an axis from 0 would flatten.
fn span(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * 0.15).max(hi.abs() * 0.02).max(1e-3);
    ((lo - pad).max(0.0), hi + pad)
}

/// `train.svg`, up to three panels over the optimiser steps: the training loss (a trailing
/// mean, [`smoothing_window`]); the network's loss over the backbone's on the same segments
/// ([`trailing_ratio`], below 1 where the network improves on the backbone; when the run
/// scored the backbone); and with a selection the held-out rollout MDE at each check against
/// the backbone's, the kept step circled.
pub fn train_svg(path: &Path, c: &TrainCurves<'_>) -> anyhow::Result<()> {
    let w = smoothing_window(c.loss.len());
    let loss = trailing_mean(c.loss, w);
    // The yardstick is scored every few steps: a window holding several of them.
    let ratio = trailing_ratio(c.loss, c.backbone_loss, w.max(50));
    let has_ratio = ratio.iter().any(|r| r.is_finite());
    let panels = 1 + usize::from(has_ratio) + usize::from(c.checks.is_some());
    let right = (c.loss.len().max(1) as f64).max(
        c.checks
            .as_ref()
            .and_then(|k| k.steps.iter().max())
            .copied()
            .unwrap_or(0) as f64,
    );
    svg_to(path, (760, 40 + 210 * panels as u32), |root| {
        let root = root.titled(&format!("train: {}", c.title), ("sans-serif", 18))?;
        let areas = root.split_evenly((panels, 1));
        let mut areas = areas.iter();
        let Some(area) = areas.next() else {
            anyhow::bail!("no panel to draw in");
        };
        panel(
            area,
            &format!("training rollout loss (mean of the last {w} steps)"),
            "optimiser step",
            c.unit,
            right,
            (0.0, linear_top(loss.iter().copied())),
            &[(BLUE, by_step(&loss))],
        )?;
        if has_ratio && let Some(area) = areas.next() {
            let (lo, hi) = span(ratio.iter().copied().chain([1.0]));
            panel(
                area,
                "network / backbone loss, same segments (grey: 1, the backbone)",
                "optimiser step",
                "ratio",
                right,
                (lo, hi),
                &[
                    (GREY, vec![(0.0, 1.0), (right, 1.0)]),
                    (BLUE, by_step(&ratio)),
                ],
            )?;
        }
        if let (Some(k), Some(area)) = (&c.checks, areas.next()) {
            let checked = k
                .steps
                .iter()
                .zip(k.mde_cm)
                .filter_map(|(&s, m)| m.filter(|v| v.is_finite()).map(|v| (s as f64, v)))
                .collect::<Vec<_>>();
            let kept = checked
                .iter()
                .find(|(s, _)| *s == k.best_step as f64)
                .copied();
            let caption = format!(
                "held-out rollout MDE at each check (grey: backbone alone, {:.3} cm){}",
                k.backbone_mde_cm,
                kept.map_or(String::new(), |(_, v)| format!(
                    "; kept: step {}, {v:.3} cm",
                    k.best_step
                ))
            );
            let y = span(checked.iter().map(|p| p.1).chain([k.backbone_mde_cm]));
            let line = vec![(0.0, k.backbone_mde_cm), (right, k.backbone_mde_cm)];
            let mut chart = panel(
                area,
                &caption,
                "optimiser step",
                "cm",
                right,
                y,
                &[(GREY, line), (RED, checked.clone())],
            )?;
            chart.draw_series(checked.iter().map(|&p| Circle::new(p, 3, RED.filled())))?;
            if let Some(p) = kept {
                chart.draw_series(std::iter::once(Circle::new(p, 7, GREEN.stroke_width(3))))?;
            }
        }
        Ok(())
    })
}

/// What [`compare_svg`] draws.
pub struct CompareCurves<'a> {
    /// Object, split and protocol, for the title.
    pub title: String,
    /// The reference model's label, then the compared one's.
    pub labels: [String; 2],
    /// Each report's MDE per step over its episodes, cm (`None`: not drawn, e.g. when only
    /// some episodes are compared).
    pub per_step: Option<[&'a [f64]; 2]>,
    /// Per paired episode, its MDE under the reference and under the compared model, cm.
    pub pairs: &'a [(f64, f64)],
}

/// `compare.svg`: the two models' MDE per step (when given), and per episode the compared
/// model's MDE against the reference's, one dot each: below the diagonal the compared model
/// errs less on that episode.
pub fn compare_svg(path: &Path, c: &CompareCurves<'_>) -> anyhow::Result<()> {
    let panels = 1 + usize::from(c.per_step.is_some());
    svg_to(path, (760, 40 + 300 * panels as u32), |root| {
        let root = root.titled(&format!("compare: {}", c.title), ("sans-serif", 18))?;
        let areas = root.split_evenly((panels, 1));
        let mut areas = areas.iter();
        // Only a drawn curve takes a panel.
        if let Some([before, after]) = c.per_step
            && let Some(area) = areas.next()
        {
            let steps = before.len().max(after.len()).max(2) as f64;
            let top = linear_top(before.iter().chain(after).copied());
            panel(
                area,
                &format!(
                    "MDE per step, cm: {} (grey), {} (blue)",
                    c.labels[0], c.labels[1]
                ),
                "prediction step",
                "cm",
                steps,
                (0.0, top),
                &[(GREY, by_step(before)), (BLUE, by_step(after))],
            )?;
        }
        if let Some(area) = areas.next() {
            let top = linear_top(c.pairs.iter().flat_map(|&(b, a)| [b, a]));
            let lower = c.pairs.iter().filter(|(b, a)| a < b).count();
            let mut chart = ChartBuilder::on(area)
                .caption(
                    format!(
                        "MDE per episode, cm: {} lower on {lower} of {} (below the line)",
                        c.labels[1],
                        c.pairs.len()
                    ),
                    ("sans-serif", 15),
                )
                .margin(8)
                .x_label_area_size(36)
                .y_label_area_size(60)
                .build_cartesian_2d(0.0..top, 0.0..top)?;
            chart
                .configure_mesh()
                .x_desc(c.labels[0].as_str())
                .y_desc(c.labels[1].as_str())
                .x_label_formatter(&|v| format!("{v:.2}"))
                .y_label_formatter(&|v| format!("{v:.2}"))
                .light_line_style(WHITE.mix(0.0))
                .draw()?;
            chart.draw_series(LineSeries::new(
                [(0.0, 0.0), (top, top)],
                GREY.stroke_width(1),
            ))?;
            chart.draw_series(
                c.pairs
                    .iter()
                    .filter(|(b, a)| b.is_finite() && a.is_finite())
                    .map(|&p| Circle::new(p, 4, BLUE.filled())),
            )?;
        }
        Ok(())
    })
}

/// `chain.svg`: the held-out MDE of the model a diagnosis chain starts from (round 0) and of
/// the model each round wrote, each point labelled with what it holds (`steps`: label, cm).
pub fn chain_svg(path: &Path, title: &str, steps: &[(String, f64)]) -> anyhow::Result<()> {
    svg_to(path, (760, 460), |root| {
        let top = linear_top(steps.iter().map(|s| s.1));
        let right = steps.len().saturating_sub(1).max(1) as f64;
        let mut chart = ChartBuilder::on(root)
            .caption(format!("chain: {title}"), ("sans-serif", 18))
            .margin(16)
            .x_label_area_size(36)
            .y_label_area_size(60)
            .build_cartesian_2d(-0.3..right + 0.3, 0.0..top)?;
        chart
            .configure_mesh()
            .x_desc("round (0: the model the chain starts from)")
            .y_desc("held-out MDE, cm")
            .x_labels(steps.len().max(2))
            .x_label_formatter(&|v| {
                if (v - v.round()).abs() < 1e-6 && *v >= 0.0 {
                    format!("{v:.0}")
                } else {
                    String::new()
                }
            })
            .light_line_style(WHITE.mix(0.0))
            .draw()?;
        let points: Vec<(f64, f64)> = steps
            .iter()
            .enumerate()
            .filter(|(_, s)| s.1.is_finite())
            .map(|(k, s)| (k as f64, s.1))
            .collect();
        chart.draw_series(LineSeries::new(
            points.iter().copied(),
            BLUE.stroke_width(2),
        ))?;
        chart.draw_series(points.iter().map(|&p| Circle::new(p, 4, BLUE.filled())))?;
        let style = TextStyle::from(("sans-serif", 13).into_font()).color(&BLACK);
        for (k, (label, cm)) in steps.iter().enumerate() {
            if cm.is_finite() {
                chart.draw_series(std::iter::once(Text::new(
                    format!("{label}: {cm:.3}"),
                    (k as f64 - 0.25, cm + top * 0.04),
                    style.clone(),
                )))?;
            }
        }
        Ok(())
    })
}

/// `refine.svg`: the batch loss of every iteration of `refine` (a trailing mean, as
/// [`smoothing_window`]) against the fitted backbone's loss over every training scene, and
/// the kept field's loss there, at the iteration after which it was checked.
pub fn refine_svg(path: &Path, object: &str, outcome: &fit::RefineOutcome) -> anyhow::Result<()> {
    let batch: Vec<f64> = outcome.history.iter().map(|s| s.batch_loss_m2).collect();
    let w = smoothing_window(batch.len());
    let mean = trailing_mean(&batch, w);
    let steps = batch.len().max(1) as f64;
    let (lo, hi) = span(
        mean.iter()
            .copied()
            .chain([outcome.initial_loss_m2, outcome.best_loss_m2]),
    );
    svg_to(path, (760, 460), |root| {
        let kept = match outcome.best_iteration {
            Some(i) => format!("kept: iteration {i}, {:.3e} m²", outcome.best_loss_m2),
            None => "kept: the fitted backbone (no iteration beat it)".to_string(),
        };
        let caption = format!(
            "refine: {object}; batch loss (mean of the last {w} iterations), grey: the fitted \
             backbone's {:.3e} m²; {kept}",
            outcome.initial_loss_m2
        );
        let line = vec![
            (0.0, outcome.initial_loss_m2),
            (steps, outcome.initial_loss_m2),
        ];
        let mut chart = panel(
            root,
            &caption,
            "iteration",
            "loss, m²",
            steps,
            (lo, hi),
            &[(GREY, line), (BLUE, by_step(&mean))],
        )?;
        if let Some(i) = outcome.best_iteration {
            let p = ((i + 1) as f64, outcome.best_loss_m2);
            chart.draw_series(std::iter::once(Circle::new(p, 7, GREEN.stroke_width(3))))?;
        }
        Ok(())
    })
}

/// `springs.svg`: a spring graph seen along the axis on which it is thinnest (a rope from
/// above, a sheet face-on), at one scale on both axes: springs as thin grey lines, particles as
/// dots in `colors` (as `springs.ply` has them).
pub fn springs_svg(
    path: &Path,
    title: &str,
    positions: &[glam::Vec3],
    edges: &[[u32; 2]],
    colors: &[[f32; 3]],
) -> anyhow::Result<()> {
    let (lo, hi) = positions.iter().fold(
        (
            glam::Vec3::splat(f32::INFINITY),
            glam::Vec3::splat(f32::NEG_INFINITY),
        ),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    let extent = (hi - lo).to_array();
    // The two world axes of largest extent, in x, y, z order.
    let thinnest = (0..3)
        .min_by(|&a, &b| extent[a].total_cmp(&extent[b]))
        .unwrap_or(2);
    let (u, v) = match thinnest {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    };
    let names = ["x", "y", "z"];
    let side = f64::from(extent[u].max(extent[v]).max(1e-6)) * 1.05;
    let centre = |k: usize| f64::from(lo[k] + hi[k]) / 2.0;
    let (cu, cv) = (centre(u), centre(v));
    svg_to(path, (640, 680), |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(
                format!(
                    "springs: {title}, {} particles, {} springs",
                    positions.len(),
                    edges.len()
                ),
                ("sans-serif", 16),
            )
            .margin(12)
            .x_label_area_size(32)
            .y_label_area_size(56)
            .build_cartesian_2d(
                cu - side / 2.0..cu + side / 2.0,
                cv - side / 2.0..cv + side / 2.0,
            )?;
        chart
            .configure_mesh()
            .x_desc(format!("{}, m", names[u]))
            .y_desc(format!("{}, m", names[v]))
            .x_label_formatter(&|x| format!("{x:.2}"))
            .y_label_formatter(&|y| format!("{y:.2}"))
            .light_line_style(WHITE.mix(0.0))
            .draw()?;
        let at = |i: u32| {
            let p = positions[i as usize].to_array();
            (f64::from(p[u]), f64::from(p[v]))
        };
        let line = GREY.mix(0.35).stroke_width(1);
        chart.draw_series(
            edges
                .iter()
                .filter(|[a, b]| (*a as usize) < positions.len() && (*b as usize) < positions.len())
                .map(|[a, b]| PathElement::new(vec![at(*a), at(*b)], line)),
        )?;
        chart.draw_series(positions.iter().zip(colors).enumerate().map(|(i, (_, c))| {
            let rgb = |x: f32| (x.clamp(0.0, 1.0) * 255.0).round() as u8;
            let color = RGBColor(rgb(c[0]), rgb(c[1]), rgb(c[2]));
            Circle::new(at(i as u32), 2, color.filled())
        }))?;
        Ok(())
    })
}

/// One named curve of a plot; `y[i]` is plotted at `x = x0 + i`.
pub struct Curve<'a> {
    /// Legend label.
    pub label: String,
    /// Values.
    pub y: &'a [f64],
}

/// Plots curves against a step index into an SVG file (written atomically): `eval`'s error per
/// step, `plan`'s Chamfer distance per planning step.
pub fn plot_curves(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    x0: f64,
    curves: &[Curve<'_>],
) -> anyhow::Result<()> {
    svg_to(path, (720, 420), |root| {
        let n = curves.iter().map(|c| c.y.len()).max().unwrap_or(1).max(2);
        let y_max = linear_top(curves.iter().flat_map(|c| c.y.iter().copied()));
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(52)
            .build_cartesian_2d(x0..x0 + (n - 1) as f64, 0.0..y_max)?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(y_label)
            .light_line_style(WHITE.mix(0.0))
            .draw()?;
        for (k, c) in curves.iter().enumerate() {
            let color = PALETTE[k % PALETTE.len()];
            let points = c.y.iter().enumerate().filter(|(_, v)| v.is_finite());
            chart
                .draw_series(LineSeries::new(
                    points.map(|(i, v)| (x0 + i as f64, *v)),
                    color.stroke_width(2),
                ))?
                .label(c.label.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color));
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .position(SeriesLabelPosition::UpperLeft)
            .draw()?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh directory of this test process for `name`'s pictures.
    fn scratch(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("pgrd-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn the_trailing_mean_skips_what_was_not_scored() {
        let nan = f64::NAN;
        let m = trailing_mean(&[1.0, nan, 3.0, nan, nan, nan, 8.0], 3);
        assert_eq!(m[0], 1.0);
        assert_eq!(m[1], 1.0);
        assert_eq!(m[2], 2.0);
        assert_eq!(m[3], 3.0); // window [nan, 3, nan]
        assert_eq!(m[4], 3.0);
        assert!(m[5].is_nan()); // window [nan, nan, nan]
        assert_eq!(m[6], 8.0);
        assert_eq!(trailing_mean(&[2.0, 4.0, 6.0], 1), vec![2.0, 4.0, 6.0]);
    }

    #[test]
    fn the_ratio_compares_the_same_steps_only() {
        let nan = f64::NAN;
        let loss = [1.0, 2.0, 3.0, 4.0];
        let base = [2.0, nan, 6.0, nan];
        let r = trailing_ratio(&loss, &base, 2);
        assert_eq!(r[0], 0.5);
        assert_eq!(r[1], 0.5); // steps 0-1: only step 0 has both
        assert_eq!(r[2], 0.5); // steps 1-2: 3 / 6
        assert_eq!(r[3], 0.5);
        let r = trailing_ratio(&loss, &base, 4);
        assert_eq!(r[3], 4.0 / 8.0);
        assert!(
            trailing_ratio(&loss, &[nan; 4], 3)
                .iter()
                .all(|r| r.is_nan())
        );
    }

    #[test]
    fn the_comparison_counts_the_episodes_below_the_line() {
        let dir = scratch("compare-svg");
        let path = dir.join("compare.svg");
        let pairs = [(2.0, 1.5), (1.0, 1.2), (3.0, 2.0)];
        let curves = CompareCurves {
            title: "rope (val, paper)".into(),
            labels: ["before: spring-mass".into(), "after: pgrd".into()],
            per_step: Some([&[1.0, 2.0, 3.0], &[1.0, 1.5, 2.5]]),
            pairs: &pairs,
        };
        compare_svg(&path, &curves).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.contains("after: pgrd lower on 2 of 3"), "{svg}");
        assert!(svg.contains("MDE per step"));
        let only_pairs = CompareCurves {
            per_step: None,
            ..curves
        };
        compare_svg(&path, &only_pairs).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(!svg.contains("MDE per step"));
        assert!(svg.contains("after: pgrd lower on 2 of 3"), "{svg}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_chain_picture_labels_every_round() {
        let dir = scratch("chain-svg");
        let path = dir.join("chain.svg");
        let steps = vec![
            ("spring-mass".to_string(), 38.5),
            ("+ bending".to_string(), 29.4),
            ("control refit".to_string(), 15.8),
        ];
        chain_svg(&path, "duster", &steps).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        for label in [
            "spring-mass: 38.500",
            "+ bending: 29.400",
            "control refit: 15.800",
        ] {
            assert!(svg.contains(label), "{label}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_refine_picture_marks_the_kept_iteration_or_says_none_was() {
        let dir = scratch("refine-svg");
        let path = dir.join("refine.svg");
        let step = |iteration, batch_loss_m2| fit::RefineStep {
            iteration,
            batch_loss_m2,
            grad_norm: 1.0,
            failed: 0,
            train_loss_m2: None,
        };
        let mut outcome = fit::RefineOutcome {
            log_factor: vec![0.0; 3],
            best_loss_m2: 1.5e-3,
            initial_loss_m2: 2.0e-3,
            best_iteration: Some(2),
            history: vec![step(0, 2.2e-3), step(1, f64::NAN), step(2, 1.4e-3)],
            config: fit::RefineConfig::default(),
            wall_s: 1.0,
        };
        refine_svg(&path, "rope", &outcome).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.contains("kept: iteration 2, 1.500e-3 m²"), "{svg}");
        assert!(svg.contains("2.000e-3 m²"));
        outcome.best_iteration = None;
        refine_svg(&path, "rope", &outcome).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.contains("no iteration beat it"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_spring_graph_is_seen_across_its_thinnest_axis() {
        let dir = scratch("springs-svg");
        let path = dir.join("springs.svg");
        // A rope lying along x on the table: seen from above (x against y).
        let positions: Vec<glam::Vec3> = (0..10)
            .map(|i| glam::Vec3::new(0.1 * i as f32, 0.01 * (i % 2) as f32, 0.005))
            .collect();
        let edges: Vec<[u32; 2]> = (0..9).map(|i| [i, i + 1]).collect();
        springs_svg(&path, "rope", &positions, &edges, &[[0.3; 3]; 10]).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.contains("10 particles, 9 springs"));
        assert!(svg.contains("x, m") && svg.contains("y, m") && !svg.contains("z, m"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_log_axis_spans_whole_decades() {
        let (lo, hi) = log_range([1.4e-4, 2.3e-3, f64::NAN, -1.0].into_iter()).unwrap();
        assert!(
            (lo - 0.999e-4).abs() < 1e-12 && (hi - 1e-2).abs() < 1e-10,
            "{lo} {hi}"
        );
        let (lo, hi) = log_range([1e-3].into_iter()).unwrap();
        assert!(lo < 1e-3 * 1.0001 && hi > 1e-3, "{lo} {hi}");
        assert!(log_range([f64::NAN, 0.0].into_iter()).is_none());
    }

    fn generation(index: usize, best: f64) -> fit::Generation {
        fit::Generation {
            index,
            best_loss: best,
            median_loss: best * 2.0,
            best_so_far: best,
            diverged: 0,
            wall_s: 0.1,
        }
    }

    #[test]
    fn the_fit_picture_names_its_curves_and_survives_no_finite_loss() {
        let dir = scratch("fit-svg");
        let path = dir.join("fit.svg");
        let history = (0..5)
            .map(|i| generation(i, 1e-3 / (i + 1) as f64))
            .collect::<Vec<_>>();
        fit_svg(&path, "rope", &history).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.starts_with("<svg"), "{}", &svg[..40.min(svg.len())]);
        for label in ["best so far", "the generation&apos;s median", "fit: rope"] {
            assert!(
                svg.contains(label) || svg.contains(&label.replace("&apos;", "'")),
                "{label}"
            );
        }
        fit_svg(&path, "rope", &[generation(0, f64::NAN)]).unwrap();
        assert!(
            std::fs::read_to_string(&path)
                .unwrap()
                .contains("no finite loss")
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_training_picture_marks_the_kept_step() {
        let dir = scratch("train-svg");
        let path = dir.join("train.svg");
        let loss = (0..200)
            .map(|i| 10.0 / (1.0 + i as f64 / 50.0))
            .collect::<Vec<_>>();
        let base = (0..200)
            .map(|i| if i % 10 == 0 { 10.0 } else { f64::NAN })
            .collect::<Vec<_>>();
        let checks = Checks {
            steps: &[0, 100, 200],
            mde_cm: &[Some(2.0), None, Some(1.5)],
            backbone_mde_cm: 2.0,
            best_step: 200,
        };
        let curves = TrainCurves {
            title: "rope (full)".into(),
            loss: &loss,
            backbone_loss: &base,
            unit: "cm²",
            checks: Some(checks),
        };
        train_svg(&path, &curves).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.contains("kept: step 200, 1.500 cm"));
        assert!(svg.contains("backbone alone, 2.000 cm"));
        assert!(svg.contains("mean of the last 10 steps"));
        assert!(svg.contains("network / backbone loss"));
        // Without a selection, one panel, and no check is drawn.
        let curves = TrainCurves {
            checks: None,
            ..curves
        };
        train_svg(&path, &curves).unwrap();
        assert!(
            !std::fs::read_to_string(&path)
                .unwrap()
                .contains("kept: step")
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
