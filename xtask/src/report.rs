//! Small writers shared by the pipelines: PLY point clouds (with edges) and JSON files, written
//! atomically. Plots are `plots.rs`'.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context;
use glam::Vec3;

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
