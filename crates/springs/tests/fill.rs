//! Interior fill of closed and open surfaces.

use glam::Vec3;
use springs::{SimError, fill_interior};

/// `n` points on a sphere of radius `r` (Fibonacci spiral).
fn sphere(n: usize, r: f32) -> Vec<Vec3> {
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let rho = (1.0 - z * z).sqrt();
            let phi = i as f32 * 2.399_963;
            r * Vec3::new(rho * phi.cos(), rho * phi.sin(), z)
        })
        .collect()
}

#[test]
fn sphere_is_filled_inside_only() {
    let r = 0.1;
    let s = 0.02;
    let surface = sphere(2000, r);
    let inside = fill_interior(&surface, s).unwrap();
    // Every fill point is inside the sphere, and none sits on the surface.
    for p in &inside {
        assert!(p.length() < r - 0.2 * s, "{p} is not inside");
    }
    // Every grid centre well inside (more than a cell from the surface) is filled.
    let lo = surface.iter().copied().fold(Vec3::INFINITY, Vec3::min);
    let dims = ((2.0 * r) / s).ceil() as usize;
    let mut deep = 0;
    for k in 0..dims {
        for j in 0..dims {
            for i in 0..dims {
                let c = lo + s * (Vec3::new(i as f32, j as f32, k as f32) + 0.5);
                if c.length() < r - s {
                    deep += 1;
                    assert!(
                        inside.iter().any(|p| p.distance(c) < 1e-5),
                        "deep cell {c} missing"
                    );
                }
            }
        }
    }
    assert!(deep > 200);
    // Deterministic.
    assert_eq!(inside, fill_interior(&surface, s).unwrap());
}

#[test]
fn open_surfaces_are_not_filled() {
    // A tube along z without caps: rays along +-z escape, so its axis region stays empty. Only
    // points within the ray tube's radius (2 x the 5 mm point spacing) of the wall can be
    // blocked in every direction.
    let mut tube = Vec::new();
    for k in 0..40 {
        for a in 0..60 {
            let phi = a as f32 * std::f32::consts::TAU / 60.0;
            tube.push(Vec3::new(
                0.05 * phi.cos(),
                0.05 * phi.sin(),
                0.005 * k as f32,
            ));
        }
    }
    let open = fill_interior(&tube, 0.01).unwrap();
    for p in &open {
        assert!(p.truncate().length() > 0.05 - 0.0105, "{p} is off the wall");
    }
    // Closing it with two caps makes it fillable.
    let mut closed = tube.clone();
    for z in [0.0, 0.195] {
        for i in -10..=10 {
            for j in -10..=10 {
                let p = Vec3::new(0.005 * i as f32, 0.005 * j as f32, z);
                if p.truncate().length() < 0.05 {
                    closed.push(p);
                }
            }
        }
    }
    let filled = fill_interior(&closed, 0.01).unwrap();
    // The tube's volume holds ~1530 grid points of 1 cm; those within 5 mm of the surface
    // are dropped.
    assert!(filled.len() > 900, "{} filled", filled.len());
    assert!(open.len() * 10 < filled.len());
    for p in &filled {
        assert!(
            p.truncate().length() < 0.05 && p.z > 0.0 && p.z < 0.195,
            "{p} outside"
        );
    }
}

#[test]
fn fill_bad_input() {
    let s = sphere(100, 0.1);
    assert!(matches!(
        fill_interior(&s, 0.0),
        Err(SimError::InvalidParameter { .. })
    ));
    assert!(matches!(
        fill_interior(&s, 1e-6),
        Err(SimError::TooLarge { .. })
    ));
    let mut bad = s.clone();
    bad[7] = Vec3::NAN;
    assert!(matches!(
        fill_interior(&bad, 0.01),
        Err(SimError::NonFinite { index: 7, .. })
    ));
    assert!(fill_interior(&s[..3], 0.01).unwrap().is_empty());
}
