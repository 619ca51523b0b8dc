//! A small orthographic point renderer for looking at plans: three panels (top x–y, side x–z,
//! side y–z) with the obstacles, the target cloud, the object and the gripper. Pure: returns
//! RGB pixels; writing images is the caller's business.

use glam::Vec3;
use springs::BoxObstacle;

const PANEL: u32 = 240;
const GAP: u32 = 6;
const BACKGROUND: [u8; 3] = [248, 248, 245];
const FRAME: [u8; 3] = [200, 200, 200];
const BLOCK: [u8; 3] = [150, 150, 160];
const TARGET: [u8; 3] = [120, 170, 230];
const OBJECT: [u8; 3] = [200, 50, 40];
const GRIPPER: [u8; 3] = [20, 20, 20];

/// What one frame shows, m.
#[derive(Clone, Copy, Debug)]
pub struct Frame<'a> {
    /// The object's points.
    pub points: &'a [Vec3],
    /// The target cloud.
    pub target: &'a [Vec3],
    /// Gripper positions.
    pub grippers: &'a [Vec3],
    /// Box obstacles.
    pub obstacles: &'a [BoxObstacle],
}

/// An RGB image, rows top to bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width, px.
    pub width: u32,
    /// Height, px.
    pub height: u32,
    /// `width · height · 3` bytes.
    pub rgb: Vec<u8>,
}

impl Image {
    fn put(&mut self, x: i64, y: i64, c: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as u32) < self.width && (y as u32) < self.height {
            let i = (y as usize * self.width as usize + x as usize) * 3;
            self.rgb[i..i + 3].copy_from_slice(&c);
        }
    }
}

/// The cube `[lo, hi]` (m) that every panel shows: the bounding box of all points, grippers and
/// the parts of obstacles near them, padded by 5 cm and made cubic so all panels share a scale.
pub fn view_bounds(frames: &[Frame<'_>]) -> (Vec3, Vec3) {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for f in frames {
        for p in f.points.iter().chain(f.target).chain(f.grippers) {
            lo = lo.min(*p);
            hi = hi.max(*p);
        }
    }
    if !lo.is_finite() {
        return (Vec3::splat(-0.5), Vec3::splat(0.5));
    }
    lo.z = lo.z.min(0.0);
    let centre = (lo + hi) / 2.0;
    let half = ((hi - lo).max_element() / 2.0 + 0.05).max(0.1);
    (centre - Vec3::splat(half), centre + Vec3::splat(half))
}

/// Renders `frame` in three panels (top x–y, side x–z, side y–z) of the cube `bounds`.
pub fn render(frame: &Frame<'_>, bounds: (Vec3, Vec3)) -> Image {
    let width = 3 * PANEL + 4 * GAP;
    let height = PANEL + 2 * GAP;
    let mut img = Image {
        width,
        height,
        rgb: BACKGROUND.repeat((width * height) as usize),
    };
    let (lo, hi) = bounds;
    let span = (hi - lo).max(Vec3::splat(1e-6));
    for (k, (a, b)) in [(0usize, 1usize), (0, 2), (1, 2)].into_iter().enumerate() {
        let x0 = (GAP + k as u32 * (PANEL + GAP)) as i64;
        let y0 = GAP as i64;
        let px = |p: Vec3| -> (i64, i64) {
            let u = (p[a] - lo[a]) / span[a];
            let v = (p[b] - lo[b]) / span[b];
            (
                x0 + (u * (PANEL - 1) as f32).round() as i64,
                y0 + ((1.0 - v) * (PANEL - 1) as f32).round() as i64,
            )
        };
        for i in 0..PANEL as i64 {
            for (x, y) in [(i, 0), (i, PANEL as i64 - 1), (0, i), (PANEL as i64 - 1, i)] {
                img.put(x0 + x, y0 + y, FRAME);
            }
        }
        let clip = |v: i64, lo: i64| v.clamp(lo, lo + PANEL as i64 - 1);
        for o in frame.obstacles {
            let (ua, vb) = px(o.min);
            let (ub, va) = px(o.max);
            for y in clip(va, y0)..=clip(vb, y0) {
                for x in clip(ua, x0)..=clip(ub, x0) {
                    img.put(x, y, BLOCK);
                }
            }
        }
        let dot = |img: &mut Image, p: Vec3, r: i64, c: [u8; 3]| {
            let (x, y) = px(p);
            for dy in -r..=r {
                for dx in -r..=r {
                    if dx * dx + dy * dy <= r * r {
                        img.put(x + dx, y + dy, c);
                    }
                }
            }
        };
        for p in frame.target {
            dot(&mut img, *p, 2, TARGET);
        }
        for p in frame.points {
            dot(&mut img, *p, 2, OBJECT);
        }
        for g in frame.grippers {
            let (x, y) = px(*g);
            for t in 0..32 {
                let th = t as f32 / 32.0 * std::f32::consts::TAU;
                img.put(
                    x + (5.0 * th.cos()).round() as i64,
                    y + (5.0 * th.sin()).round() as i64,
                    GRIPPER,
                );
            }
        }
    }
    img
}
