//! The six objects: geometry, materials, fields, colours, grasp region and per-recording
//! placement. Numbers are nominal material values (documented in `docs/world.md`).

use glam::{Quat, Vec3};
use rand::Rng;

use super::shapes::{SheetSpec, TubeSpec, add_lattice, add_sheet, add_tube, tube_stencils};
use super::{Blueprint, DragShape, Resolution, jitter, smooth_field};
use crate::ObjectKind;
use crate::rng::{stream, tag};

/// Builds the fine model of `kind` at `resolution`; `seed` fixes its random fields and texture.
pub(crate) fn blueprint(kind: ObjectKind, resolution: Resolution, seed: u64) -> Blueprint {
    let mut rng = stream(seed, &[tag::OBJECT, kind as u64]);
    let f = resolution.spacing_factor();
    let full = resolution == Resolution::Full;
    let mut bp = match kind {
        ObjectKind::Rope => rope(f, full, &mut rng),
        ObjectKind::Paper => paper(f, &mut rng),
        ObjectKind::Flag => flag(f, &mut rng),
        ObjectKind::Sloth => sloth(f, &mut rng),
        ObjectKind::Duster => duster(f, full, &mut rng),
        ObjectKind::Teddy => teddy(f, &mut rng),
    };
    if !full {
        bp.substeps /= 2;
    }
    bp
}

fn rope(f: f32, full: bool, rng: &mut impl Rng) -> Blueprint {
    let h = 0.0075 * f;
    let length = 0.9;
    let radius = 0.008;
    let ring = if full { 8 } else { 6 };
    let mut bp = Blueprint {
        total_mass: 0.05,
        contact_radius: 0.002,
        base_friction: 0.45,
        damping_time_s: 0.0002,
        substeps: 100,
        spacing: h,
        ..Default::default()
    };
    let spec = TubeSpec {
        origin: Vec3::new(-length / 2.0, 0.0, 0.0),
        axis: Vec3::X,
        nodes: (length / h).round() as usize + 1,
        spacing: h,
        radius,
        ring,
        ea_core: 2000.0,
        ea_section: 50.0,
        // Soft surface links: the plain rope is floppy (base rigidity ≈ 2.6e-4 N·m²).
        ea_surface: 0.5 * 8.0 / ring as f32,
        long_spans: &[],
    };
    let red = [0.75, 0.16, 0.12];
    let cream = [0.93, 0.88, 0.77];
    let mut tex = |node: usize, j: usize| {
        // A two-tone braid: stripes spiralling with a 3 cm pitch.
        let s = node as f32 * h;
        let a = if j == usize::MAX {
            0.0
        } else {
            j as f32 / ring as f32
        };
        let phase = (s / 0.03 + a).fract();
        jitter(if phase < 0.5 { red } else { cream }, 0.08, rng)
    };
    let tube = add_tube(&mut bp, &spec, &mut tex);
    tube_stencils(&mut bp, &tube, h);
    bp.stiff_field = smooth_field(&bp.rest, 0.3, rng);
    bp.mass_field = smooth_field(&bp.rest, 0.4, rng);
    let end = spec.origin.x;
    bp.grasp_point = Vec3::new(end + 0.0125, 0.0, 0.0);
    bp.held = (0..bp.len() as u32)
        .filter(|&i| bp.rest[i as usize].x <= end + 0.025 + 1e-4)
        .collect();
    bp
}

fn paper(f: f32, rng: &mut impl Rng) -> Blueprint {
    let h = 0.007 * f;
    let (w, l) = (0.21, 0.297);
    let mut bp = Blueprint {
        total_mass: 0.005,
        contact_radius: 0.002,
        base_friction: 0.4,
        damping_time_s: 0.0001,
        substeps: 80,
        spacing: h,
        ..Default::default()
    };
    let spec = SheetSpec {
        origin: Vec3::new(-w / 2.0, 0.0, 0.0),
        du: Vec3::X,
        dv: Vec3::NEG_Z,
        nu: (w / h).round() as usize + 1,
        nv: (l / h).round() as usize + 1,
        spacing: h,
        // Copy paper: 2-D stretch modulus E·t ≈ 4 GPa × 0.1 mm = 4e5 N/m.
        ea_struct: 4.0e5 * h,
        ea_shear: 2.0e5 * h,
    };
    let mut tex = |u: usize, v: usize| {
        let (x, y) = (u as f32 * h, v as f32 * h);
        // A printed page: a blue header block and grey lines of "text" inside the margins.
        let header = (0.02..0.12).contains(&x) && (0.02..0.05).contains(&y);
        let text = (0.02..0.19).contains(&x) && y > 0.07 && y < 0.28 && (y / 0.012).fract() < 0.4;
        let c = if header {
            [0.2, 0.35, 0.75]
        } else if text {
            [0.45, 0.45, 0.48]
        } else {
            [0.96, 0.96, 0.94]
        };
        jitter(c, 0.03, rng)
    };
    add_sheet(&mut bp, &spec, &mut tex);
    bp.stiff_field = smooth_field(&bp.rest, 0.2, rng);
    bp.mass_field = smooth_field(&bp.rest, 0.25, rng);
    bp.grasp_point = Vec3::new(0.0, 0.0, -0.008);
    bp.held = within(&bp.rest, bp.grasp_point, 0.025);
    bp
}

fn flag(f: f32, rng: &mut impl Rng) -> Blueprint {
    let h = 0.01 * f;
    let (w, l) = (0.45, 0.30);
    let mut bp = Blueprint {
        total_mass: 0.02,
        contact_radius: 0.002,
        base_friction: 0.4,
        damping_time_s: 0.0001,
        substeps: 80,
        spacing: h,
        ..Default::default()
    };
    let nu = (w / h).round() as usize + 1;
    let nv = (l / h).round() as usize + 1;
    let spec = SheetSpec {
        origin: Vec3::new(-w / 2.0, 0.0, 0.0),
        du: Vec3::X,
        dv: Vec3::NEG_Z,
        nu,
        nv,
        spacing: h,
        // Polyester flag cloth: stretch modulus ≈ 2e3 N/m, shear a quarter of it.
        ea_struct: 2.0e3 * h,
        ea_shear: 5.0e2 * h,
    };
    let mut tex = |u: usize, v: usize| {
        let (x, y) = (u as f32 * h, v as f32 * h);
        let c = if v == 0 {
            [0.45, 0.3, 0.15] // the wooden stick
        } else if (x - w / 2.0).powi(2) + (y - l / 2.0).powi(2) < 0.06f32.powi(2) {
            [0.98, 0.8, 0.15] // an emblem
        } else if x < w / 3.0 {
            [0.1, 0.3, 0.7]
        } else if x < 2.0 * w / 3.0 {
            [0.95, 0.95, 0.95]
        } else {
            [0.8, 0.12, 0.15]
        };
        jitter(c, 0.04, rng)
    };
    let grid = add_sheet(&mut bp, &spec, &mut tex);
    bp.stiff_field = smooth_field(&bp.rest, 0.25, rng);
    // Hems along the free edges are double cloth: heavier.
    let hem = 0.015 + 1e-4;
    bp.mass_field = bp
        .rest
        .iter()
        .map(|p| {
            let (x, y) = (p.x + w / 2.0, -p.z);
            f32::from(x < hem || x > w - hem || y > l - hem)
        })
        .collect();
    bp.held = grid[0].clone();
    bp.grasp_point = Vec3::ZERO;
    bp
}

/// Base link rigidity of the duster, N, for stem and feathers alike (stiffness-heterogeneity
/// makes the stem stiffer and the feathers softer by √contrast each).
const DUSTER_EA: f32 = 10.0;

fn duster(f: f32, full: bool, rng: &mut impl Rng) -> Blueprint {
    let h = 0.0125 * f;
    let stem_len = 0.38;
    let mut bp = Blueprint {
        total_mass: 0.065,
        contact_radius: 0.002,
        base_friction: 0.4,
        damping_time_s: 0.0002,
        substeps: 100,
        spacing: h,
        ..Default::default()
    };
    let spec = TubeSpec {
        origin: Vec3::ZERO,
        axis: Vec3::Z,
        nodes: (stem_len / h).round() as usize + 1,
        spacing: h,
        radius: 0.008,
        ring: 4,
        // The same base material as the feathers: stiffness-heterogeneity makes the stem rigid.
        ea_core: DUSTER_EA,
        ea_section: DUSTER_EA,
        ea_surface: DUSTER_EA,
        long_spans: &[2, 4, 8, 16],
    };
    let wood = [0.38, 0.22, 0.1];
    let grip = [0.1, 0.1, 0.1];
    let mut stem_tex = |node: usize, _j: usize| {
        jitter(if node as f32 * h < 0.08 { grip } else { wood }, 0.05, rng)
    };
    let tube = add_tube(&mut bp, &spec, &mut stem_tex);
    tube_stencils(&mut bp, &tube, h);
    let stem_count = bp.len();
    // The stem must be able to act rigid: its links get extra Gauss–Seidel sweeps.
    bp.stiff_links = bp.links.len();
    bp.stiff_iterations = 8;
    let (strands, per, sf) = if full { (90, 7, 0.013) } else { (60, 5, 0.018) };
    let palette = [
        [0.95, 0.45, 0.7],
        [0.3, 0.8, 0.9],
        [0.98, 0.85, 0.3],
        [0.6, 0.4, 0.85],
        [0.95, 0.95, 0.95],
    ];
    let top = tube.centre.len() - 1;
    let head_nodes = ((0.16 / h).round() as usize).max(2);
    for s in 0..strands {
        let node = top - (s * 7919) % head_nodes;
        let azimuth = s as f32 * 2.399_963;
        // Strands near the tip point upward, lower ones spread out and slightly down.
        let rise = 1.0 - (top - node) as f32 / head_nodes as f32;
        let elevation = -0.35 + 1.4 * rise + rng.random_range(-0.2..0.2);
        let dir = Vec3::new(
            elevation.cos() * azimuth.cos(),
            elevation.cos() * azimuth.sin(),
            elevation.sin(),
        );
        let root = tube.centre[node];
        let c = bp.rest[root as usize];
        let color = palette[rng.random_range(0..palette.len())];
        let ids: Vec<u32> = (0..per)
            .map(|m| {
                let p = c + dir * (sf * (m + 1) as f32);
                bp.add(p, true, DragShape::None, jitter(color, 0.1, rng))
            })
            .collect();
        for m in 0..per {
            let prev = if m == 0 { root } else { ids[m - 1] };
            let next = if m + 1 < per { ids[m + 1] } else { ids[m] };
            // A feather plume is ~2.5 cm wide: its drag diameter, not the shaft's.
            bp.drag[ids[m] as usize] = DragShape::Rod {
                a: prev,
                b: next,
                area: 0.025 * sf,
            };
            bp.link(prev, ids[m], DUSTER_EA);
            if m + 1 < per {
                bp.stencil(prev, ids[m], ids[m + 1], sf.powi(3));
            }
        }
        // Clamp the root's direction to the stem with links to the neighbouring stem nodes.
        for nb in [node.saturating_sub(1), (node + 1).min(top)] {
            if nb != node {
                bp.link(tube.centre[nb], ids[0], DUSTER_EA);
            }
        }
        if per > 1 {
            bp.link(root, ids[1], DUSTER_EA);
        }
    }
    let n = bp.len();
    bp.stiff_field = (0..n).map(|i| f32::from(i < stem_count)).collect();
    bp.mass_field = bp.stiff_field.clone();
    bp.grasp_point = Vec3::new(0.0, 0.0, 0.03);
    bp.held = within(&bp.rest[..stem_count], bp.grasp_point, 0.04);
    bp
}

fn ellipsoid(p: Vec3, c: Vec3, r: Vec3) -> bool {
    ((p - c) / r).length_squared() <= 1.0
}

fn capsule(p: Vec3, a: Vec3, b: Vec3, r: f32) -> bool {
    let ab = b - a;
    let t = ((p - a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0);
    p.distance(a + ab * t) <= r
}

fn sloth(f: f32, rng: &mut impl Rng) -> Blueprint {
    let h = 0.012 * f;
    let mut bp = Blueprint {
        total_mass: 0.25,
        contact_radius: 0.003,
        base_friction: 0.5,
        damping_time_s: 0.0005,
        substeps: 50,
        spacing: h,
        ..Default::default()
    };
    let body_c = Vec3::new(0.0, 0.0, 0.055);
    let body_r = Vec3::new(0.10, 0.065, 0.05);
    let head_c = Vec3::new(0.12, 0.0, 0.07);
    let head_r = 0.045;
    let limb_r = 0.017;
    let limbs = [
        (Vec3::new(0.06, 0.05, 0.05), Vec3::new(0.14, 0.22, 0.02)),
        (Vec3::new(0.06, -0.05, 0.05), Vec3::new(0.14, -0.22, 0.02)),
        (Vec3::new(-0.06, 0.05, 0.05), Vec3::new(-0.15, 0.21, 0.02)),
        (Vec3::new(-0.06, -0.05, 0.05), Vec3::new(-0.15, -0.21, 0.02)),
    ];
    let core = move |p: Vec3| ellipsoid(p, body_c, body_r) || p.distance(head_c) <= head_r;
    let inside = move |p: Vec3| core(p) || limbs.iter().any(|(a, b)| capsule(p, *a, *b, limb_r));
    let mut tex = |p: Vec3| {
        let face = p.distance(head_c) <= head_r && p.x > head_c.x + 0.012;
        let eye = |y: f32| {
            ((p - Vec3::new(head_c.x + 0.03, y, head_c.z + 0.01)) / Vec3::new(0.03, 0.012, 0.01))
                .length_squared()
                < 1.0
        };
        let claw = limbs.iter().any(|(_, b)| p.distance(*b) < 0.025);
        let c = if face && (eye(0.018) || eye(-0.018)) {
            [0.12, 0.09, 0.07]
        } else if face {
            [0.86, 0.76, 0.6]
        } else if claw {
            [0.22, 0.22, 0.22]
        } else if core(p) {
            [0.45, 0.33, 0.22]
        } else {
            [0.34, 0.25, 0.17]
        };
        jitter(c, 0.1, rng)
    };
    // E ≈ 8 kPa plush: EA = E h² per link.
    let ea = 8.0e3 * h * h;
    let lo = Vec3::new(-0.17, -0.25, 0.0);
    let hi = Vec3::new(0.18, 0.25, 0.11);
    add_lattice(&mut bp, lo, hi, h, ea, inside, &mut tex);
    bp.stiff_field = bp.rest.iter().map(|p| f32::from(core(*p))).collect();
    bp.mass_field = bp.stiff_field.clone();
    bp.grasp_point = Vec3::new(0.0, 0.0, 0.10);
    bp.held = within(&bp.rest, bp.grasp_point, 0.03);
    bp
}

fn teddy(f: f32, rng: &mut impl Rng) -> Blueprint {
    let h = 0.014 * f;
    let mut bp = Blueprint {
        total_mass: 0.3,
        contact_radius: 0.003,
        base_friction: 0.5,
        damping_time_s: 0.0005,
        substeps: 80,
        spacing: h,
        ..Default::default()
    };
    // The body is cut flat at the bottom: a sitting teddy rests on a broad base.
    let body = (Vec3::new(0.0, 0.0, 0.065), Vec3::new(0.065, 0.07, 0.075));
    let head = (Vec3::new(0.01, 0.0, 0.185), 0.055);
    let ears = [
        Vec3::new(0.005, 0.045, 0.235),
        Vec3::new(0.005, -0.045, 0.235),
    ];
    let snout = (Vec3::new(0.06, 0.0, 0.175), 0.024);
    let arms = [
        (Vec3::new(0.0, 0.065, 0.12), Vec3::new(0.05, 0.095, 0.07)),
        (Vec3::new(0.0, -0.065, 0.12), Vec3::new(0.05, -0.095, 0.07)),
    ];
    let legs = [
        (Vec3::new(0.02, 0.035, 0.03), Vec3::new(0.10, 0.05, 0.03)),
        (Vec3::new(0.02, -0.035, 0.03), Vec3::new(0.10, -0.05, 0.03)),
    ];
    let inside = move |p: Vec3| {
        (ellipsoid(p, body.0, body.1) && p.z >= 0.0)
            || p.distance(head.0) <= head.1
            || ears.iter().any(|e| p.distance(*e) <= 0.022)
            || p.distance(snout.0) <= snout.1
            || arms.iter().any(|(a, b)| capsule(p, *a, *b, 0.022))
            || legs.iter().any(|(a, b)| capsule(p, *a, *b, 0.026))
    };
    let mut tex = |p: Vec3| {
        let eye = [Vec3::new(0.055, 0.022, 0.2), Vec3::new(0.055, -0.022, 0.2)]
            .iter()
            .any(|e| p.distance(*e) < 0.014);
        let nose = p.distance(snout.0 + Vec3::new(0.022, 0.0, 0.005)) < 0.012;
        let light = p.distance(snout.0) <= snout.1 + 1e-3
            || (ellipsoid(p, body.0, body.1) && p.x > 0.035 && p.z < 0.12);
        let ear = ears.iter().any(|e| p.distance(*e) <= 0.023);
        let c = if eye || nose {
            [0.08, 0.06, 0.05]
        } else if light {
            [0.88, 0.76, 0.58]
        } else if ear {
            [0.5, 0.35, 0.22]
        } else {
            [0.72, 0.55, 0.36]
        };
        jitter(c, 0.08, rng)
    };
    // E ≈ 80 kPa: firmly stuffed.
    let ea = 8.0e4 * h * h;
    let lo = Vec3::new(-0.07, -0.13, 0.0);
    let hi = Vec3::new(0.13, 0.13, 0.27);
    add_lattice(&mut bp, lo, hi, h, ea, inside, &mut tex);
    // Stiffer head, softer body; beans in the bottom.
    bp.stiff_field = bp
        .rest
        .iter()
        .map(|p| ((p.z - 0.1) / 0.08).clamp(0.0, 1.0))
        .collect();
    bp.mass_field = bp
        .rest
        .iter()
        .map(|p| ((0.12 - p.z) / 0.1).clamp(0.0, 1.0))
        .collect();
    bp.grasp_point = centroid(&bp.rest);
    bp
}

/// Indices of `points` within `radius` of `c`.
fn within(points: &[Vec3], c: Vec3, radius: f32) -> Vec<u32> {
    (0..points.len() as u32)
        .filter(|&i| points[i as usize].distance(c) <= radius)
        .collect()
}

pub(crate) fn centroid(points: &[Vec3]) -> Vec3 {
    points.iter().copied().sum::<Vec3>() / points.len().max(1) as f32
}

/// Initial positions and gripper position of one recording: a random pose on the table (rope:
/// also a random smooth planar curve, or a straight line with `straight`) or in the air for held
/// objects.
pub(crate) fn place(
    kind: ObjectKind,
    bp: &Blueprint,
    straight: bool,
    rng: &mut impl Rng,
) -> (Vec<Vec3>, Vec3) {
    let offset = Vec3::new(
        rng.random_range(-0.05..0.05),
        rng.random_range(-0.05..0.05),
        0.0,
    );
    let yaw = Quat::from_rotation_z(rng.random_range(0.0..std::f32::consts::TAU));
    match kind {
        ObjectKind::Rope => place_rope(bp, offset, straight, rng),
        ObjectKind::Paper | ObjectKind::Flag | ObjectKind::Duster => {
            let home = match kind {
                ObjectKind::Paper => 0.45,
                ObjectKind::Flag => 0.55,
                _ => 0.28,
            };
            let g = bp.grasp_point;
            let target = offset + Vec3::Z * home;
            let x = bp.rest.iter().map(|p| target + yaw * (*p - g)).collect();
            (x, target)
        }
        ObjectKind::Sloth | ObjectKind::Teddy => {
            let c = centroid(&bp.rest);
            let lift = bp.contact_radius + 0.001
                - bp.rest.iter().map(|p| p.z).fold(f32::INFINITY, f32::min);
            let map = |p: Vec3| {
                let q = yaw * (p - Vec3::new(c.x, c.y, 0.0)) + offset;
                q + Vec3::Z * lift
            };
            let x = bp.rest.iter().map(|p| map(*p)).collect();
            (x, map(bp.grasp_point))
        }
    }
}

/// Lays the straight rope along a random smooth planar curve (arc length preserved; a straight
/// line with `straight`), resting on the table.
fn place_rope(
    bp: &Blueprint,
    offset: Vec3,
    straight: bool,
    rng: &mut impl Rng,
) -> (Vec<Vec3>, Vec3) {
    let bend = if straight { 0.0 } else { 1.0 };
    let x0 = bp.rest.iter().map(|p| p.x).fold(f32::INFINITY, f32::min);
    let length = bp
        .rest
        .iter()
        .map(|p| p.x)
        .fold(f32::NEG_INFINITY, f32::max)
        - x0;
    let heading0 = rng.random_range(0.0..std::f32::consts::TAU);
    let waves: Vec<(f32, f32, f32)> = (0..2)
        .map(|_| {
            (
                bend * rng.random_range(0.0..0.7),
                rng.random_range(0.5..1.5),
                rng.random_range(0.0..std::f32::consts::TAU),
            )
        })
        .collect();
    let heading = |s: f32| {
        heading0
            + waves
                .iter()
                .map(|(a, l, ph)| a * (std::f32::consts::TAU * s / l + ph).sin())
                .sum::<f32>()
    };
    // Integrate the centre line with 1 mm steps.
    let ds = 0.001;
    let steps = (length / ds).ceil() as usize + 1;
    let mut line = Vec::with_capacity(steps + 1);
    let mut c = glam::Vec2::ZERO;
    line.push(c);
    for k in 0..steps {
        let th = heading((k as f32 + 0.5) * ds);
        c += glam::Vec2::new(th.cos(), th.sin()) * ds;
        line.push(c);
    }
    let mid = line[line.len() / 2];
    let rest_radius = bp
        .rest
        .iter()
        .map(|p| p.y.hypot(p.z))
        .fold(0.0f32, f32::max);
    let lift = rest_radius + bp.contact_radius;
    let map = |p: Vec3| {
        let s = (p.x - x0).clamp(0.0, length);
        let k = ((s / ds) as usize).min(line.len() - 2);
        let t = s / ds - k as f32;
        let q = line[k].lerp(line[k + 1], t) - mid;
        let th = heading(s);
        let normal = glam::Vec2::new(-th.sin(), th.cos());
        let xy = q + normal * p.y;
        Vec3::new(xy.x, xy.y, p.z + lift) + offset
    };
    let x = bp.rest.iter().map(|p| map(*p)).collect();
    (x, map(bp.grasp_point))
}
