//! A small point-splat rasteriser: a strip of frames of one episode as a PNG, so a reader sees
//! what the data looks like.

use std::path::Path;

use dataset::Episode;
use glam::Vec3;
use image::{ImageEncoder, Rgb, RgbImage};

use crate::Error;

const PANEL_W: u32 = 320;
const PANEL_H: u32 = 300;
const GAP: u32 = 4;
const BACKGROUND: [u8; 3] = [246, 246, 243];

/// Renders `frames` of `episode` side by side and writes a PNG to `path`: an orthographic view
/// from 25° elevation (55° for flat scenes), at the azimuth (of 12) that shows the first frame largest; shadows on the
/// ground plane z = 0; the gripper as a black ring of `gripper_radius` metres; occluded points
/// are left out.
pub fn render_strip(
    episode: &Episode,
    frames: &[usize],
    gripper_radius: f32,
    path: &Path,
) -> Result<(), Error> {
    let bad = |m: String| Error::Config(format!("render: {m}"));
    if frames.is_empty() {
        return Err(bad("no frames to render".into()));
    }
    if let Some(f) = frames.iter().find(|f| **f >= episode.frames()) {
        return Err(bad(format!(
            "frame {f} out of range ({} frames)",
            episode.frames()
        )));
    }
    // One camera for the whole strip, fitted to every rendered point and the gripper.
    let pts: Vec<Vec3> = frames
        .iter()
        .flat_map(|&f| {
            episode
                .frame(f)
                .iter()
                .chain(episode.gripper_frame(f))
                .copied()
        })
        .collect();
    let lo = pts.iter().copied().fold(Vec3::INFINITY, Vec3::min);
    let hi = pts.iter().copied().fold(Vec3::NEG_INFINITY, Vec3::max);
    let centre = (lo + hi) / 2.0;
    // Flat scenes (a rope on the table) are seen from higher up.
    let first = episode.frame(frames[0]);
    let (flo, fhi) = first
        .iter()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(a, b), p| {
            (a.min(*p), b.max(*p))
        });
    let flat = (fhi.z - flo.z) < 0.3 * (fhi.x - flo.x).max(fhi.y - flo.y);
    let el = if flat { 55f32 } else { 25f32 }.to_radians();
    let camera = |az: f32| {
        let view = Vec3::new(-az.cos() * el.cos(), -az.sin() * el.cos(), -el.sin());
        let right = view.cross(Vec3::Z).normalize();
        (view, right, right.cross(view))
    };
    // Pick the azimuth with the largest projected spread of the first frame (a sheet seen
    // face-on rather than edge-on).
    let spread = |az: f32| {
        let (_, right, up) = camera(az);
        let n = first.len() as f32;
        let (mut su, mut sv, mut suu, mut svv, mut suv) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for p in first {
            let (u, v) = (p.dot(right), p.dot(up));
            (su, sv, suu, svv, suv) = (su + u, sv + v, suu + u * u, svv + v * v, suv + u * v);
        }
        let (cu, cv) = (suu / n - (su / n).powi(2), svv / n - (sv / n).powi(2));
        cu * cv - (suv / n - su * sv / (n * n)).powi(2)
    };
    let az = (0..12)
        .map(|k| (15.0 + 30.0 * k as f32).to_radians())
        .max_by(|a, b| spread(*a).total_cmp(&spread(*b)))
        .unwrap_or(0.6);
    let (view, right, up) = camera(az);
    let extent = pts
        .iter()
        .map(|p| {
            let d = *p - centre;
            (d.dot(right).abs() / PANEL_W as f32).max(d.dot(up).abs() / PANEL_H as f32)
        })
        .fold(1e-6, f32::max);
    let scale = 0.42 / extent;
    let project = |p: Vec3| {
        let d = p - centre;
        (
            PANEL_W as f32 / 2.0 + d.dot(right) * scale,
            PANEL_H as f32 / 2.0 - d.dot(up) * scale,
            d.dot(view),
        )
    };
    let width = frames.len() as u32 * PANEL_W + (frames.len() as u32 - 1) * GAP;
    let mut img = RgbImage::from_pixel(width, PANEL_H, Rgb([255, 255, 255]));
    let n = episode.particles();
    let dot = (2.6 * (350.0 / n.max(1) as f32).sqrt()).clamp(1.6, 5.0);
    let grey = [0.55, 0.55, 0.55];
    for (slot, &f) in frames.iter().enumerate() {
        let x0 = slot as u32 * (PANEL_W + GAP);
        let mut panel = Panel { img: &mut img, x0 };
        panel.fill(BACKGROUND);
        // Ground grid (10 cm) around the object, then shadows.
        let g0 = (centre / 0.1).floor() * 0.1;
        for k in -6..=6 {
            for s in 0..=120 {
                let t = -0.6 + s as f32 * 0.01;
                for p in [
                    Vec3::new(g0.x + k as f32 * 0.1, g0.y + t, 0.0),
                    Vec3::new(g0.x + t, g0.y + k as f32 * 0.1, 0.0),
                ] {
                    let (u, v, _) = project(p);
                    panel.blend(u, v, 0.8, [0.8, 0.8, 0.78], 1.0);
                }
            }
        }
        for (i, p) in episode.frame(f).iter().enumerate() {
            if !episode.visible(f, i) {
                continue;
            }
            let (u, v, _) = project(Vec3::new(p.x, p.y, 0.0));
            panel.blend(u, v, dot, [0.6, 0.6, 0.6], 0.25);
        }
        let mut order: Vec<(f32, usize)> = episode
            .frame(f)
            .iter()
            .enumerate()
            .map(|(i, p)| (project(*p).2, i))
            .collect();
        // Painter's order: farthest first.
        order.sort_by(|a, b| b.0.total_cmp(&a.0));
        for (_, i) in order {
            let (u, v, _) = project(episode.frame(f)[i]);
            if !episode.visible(f, i) {
                continue;
            }
            let c = episode.colors().map_or(grey, |c| c[i]);
            panel.blend(u, v, dot + 0.8, [0.15, 0.15, 0.15], 0.6);
            panel.blend(u, v, dot, c, 1.0);
        }
        for g in episode.gripper_frame(f) {
            let (u, v, _) = project(*g);
            let r = (gripper_radius * scale).max(4.0);
            panel.ring(u, v, r, [0.0, 0.0, 0.0]);
        }
        panel.label(&format!("{:.1}s", f as f32 / 10.0));
    }
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(img.as_raw(), width, PANEL_H, image::ExtendedColorType::Rgb8)
        .map_err(|e| Error::Write {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
    dataset::write_atomic(path, &bytes)?;
    Ok(())
}

struct Panel<'a> {
    img: &'a mut RgbImage,
    x0: u32,
}

impl Panel<'_> {
    fn fill(&mut self, c: [u8; 3]) {
        for y in 0..PANEL_H {
            for x in 0..PANEL_W {
                self.img.put_pixel(self.x0 + x, y, Rgb(c));
            }
        }
    }

    fn put(&mut self, x: i32, y: i32, c: [f32; 3], alpha: f32) {
        if x < 0 || y < 0 || x >= PANEL_W as i32 || y >= PANEL_H as i32 {
            return;
        }
        let px = self.img.get_pixel_mut(self.x0 + x as u32, y as u32);
        for (channel, target) in px.0.iter_mut().zip(c) {
            let old = *channel as f32 / 255.0;
            *channel = ((old * (1.0 - alpha) + target * alpha) * 255.0).round() as u8;
        }
    }

    /// An anti-aliased disc of radius `r` px.
    fn blend(&mut self, u: f32, v: f32, r: f32, c: [f32; 3], alpha: f32) {
        let (x0, x1) = ((u - r - 1.0).floor() as i32, (u + r + 1.0).ceil() as i32);
        let (y0, y1) = ((v - r - 1.0).floor() as i32, (v + r + 1.0).ceil() as i32);
        for y in y0..=y1 {
            for x in x0..=x1 {
                let d = ((x as f32 + 0.5 - u).powi(2) + (y as f32 + 0.5 - v).powi(2)).sqrt();
                let cover = (r + 0.5 - d).clamp(0.0, 1.0);
                if cover > 0.0 {
                    self.put(x, y, c, alpha * cover);
                }
            }
        }
    }

    fn ring(&mut self, u: f32, v: f32, r: f32, c: [f32; 3]) {
        let steps = (r * 8.0) as usize + 16;
        for s in 0..steps {
            let a = std::f32::consts::TAU * s as f32 / steps as f32;
            self.blend(u + r * a.cos(), v + r * a.sin(), 0.9, c, 1.0);
        }
    }

    /// Draws `text` (digits, '.', 's') in a 3×5 pixel font scaled ×3 at the top-left.
    fn label(&mut self, text: &str) {
        let glyph = |ch: char| -> [u8; 5] {
            match ch {
                '0' => [7, 5, 5, 5, 7],
                '1' => [2, 6, 2, 2, 7],
                '2' => [7, 1, 7, 4, 7],
                '3' => [7, 1, 7, 1, 7],
                '4' => [5, 5, 7, 1, 1],
                '5' => [7, 4, 7, 1, 7],
                '6' => [7, 4, 7, 5, 7],
                '7' => [7, 1, 1, 1, 1],
                '8' => [7, 5, 7, 5, 7],
                '9' => [7, 5, 7, 1, 7],
                '.' => [0, 0, 0, 0, 2],
                's' => [0, 7, 4, 1, 7],
                _ => [0; 5],
            }
        };
        let s = 3;
        for (k, ch) in text.chars().enumerate() {
            let rows = glyph(ch);
            for (ry, row) in rows.iter().enumerate() {
                for rx in 0..3 {
                    if row & (4 >> rx) != 0 {
                        for dy in 0..s {
                            for dx in 0..s {
                                let x = 10 + (k as i32) * 4 * s + rx * s + dx;
                                let y = 10 + ry as i32 * s + dy;
                                self.put(x, y, [0.2, 0.2, 0.2], 1.0);
                            }
                        }
                    }
                }
            }
        }
    }
}
