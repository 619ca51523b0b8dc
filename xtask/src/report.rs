//! Small writers shared by the pipelines: PLY point clouds, SVG curve plots, JSON files. All
//! outputs are written atomically.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context;
use glam::Vec3;
use plotters::prelude::*;

/// Writes `value` as pretty JSON, atomically.
pub fn write_json(path: &Path, value: &impl serde::Serialize) -> anyhow::Result<()> {
    let text = serde_json::to_string_pretty(value)?;
    dataset::write_atomic(path, text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

/// Writes an ASCII PLY point cloud (vertices with optional 8-bit colours), atomically.
pub fn write_ply(path: &Path, points: &[Vec3], colors: Option<&[[f32; 3]]>) -> anyhow::Result<()> {
    write_ply_edges(path, points, colors, &[])
}

/// [`write_ply`] with edges between vertex pairs (an `edge` element, which MeshLab,
/// CloudCompare and Blender draw as lines), atomically.
pub fn write_ply_edges(
    path: &Path,
    points: &[Vec3],
    colors: Option<&[[f32; 3]]>,
    edges: &[[u32; 2]],
) -> anyhow::Result<()> {
    let mut s = String::new();
    writeln!(s, "ply\nformat ascii 1.0\nelement vertex {}", points.len())?;
    s.push_str("property float x\nproperty float y\nproperty float z\n");
    if colors.is_some() {
        s.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
    }
    if !edges.is_empty() {
        writeln!(s, "element edge {}", edges.len())?;
        s.push_str("property int vertex1\nproperty int vertex2\n");
    }
    s.push_str("end_header\n");
    for (i, p) in points.iter().enumerate() {
        write!(s, "{} {} {}", p.x, p.y, p.z)?;
        if let Some(c) = colors {
            let b = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
            write!(s, " {} {} {}", b(c[i][0]), b(c[i][1]), b(c[i][2]))?;
        }
        s.push('\n');
    }
    for [a, b] in edges {
        writeln!(s, "{a} {b}")?;
    }
    dataset::write_atomic(path, s.as_bytes()).with_context(|| format!("writing {}", path.display()))
}

/// One named curve of a plot; `y[i]` is plotted at `x = x0 + i`.
pub struct Curve<'a> {
    /// Legend label.
    pub label: String,
    /// Values.
    pub y: &'a [f64],
}

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

/// Plots curves against a step index into an SVG file (written atomically).
pub fn plot_curves(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    x0: f64,
    curves: &[Curve<'_>],
) -> anyhow::Result<()> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (720, 420)).into_drawing_area();
        root.fill(&WHITE)?;
        let n = curves.iter().map(|c| c.y.len()).max().unwrap_or(1).max(2);
        let y_max = curves
            .iter()
            .flat_map(|c| c.y.iter().copied())
            .filter(|v| v.is_finite())
            .fold(0.0f64, f64::max);
        let y_max = if y_max > 0.0 { y_max * 1.1 } else { 1.0 };
        let mut chart = ChartBuilder::on(&root)
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
        root.present()?;
    }
    dataset::write_atomic(path, svg.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}
