//! Renders with closed-form answers.

// Index loops over parallel arrays read more plainly here than zipped iterators.
#![allow(clippy::needless_range_loop)]

use glam::{Mat3, Quat, Vec3};
use gsplat::{Camera, Gaussians, render};

/// A camera whose frame is the world frame (x right, y down, z forward), 64 x 48 px.
fn axis_camera(f: f32) -> Camera {
    Camera {
        fx: f,
        fy: 1.25 * f,
        cx: 32.0,
        cy: 24.0,
        width: 64,
        height: 48,
        near: 0.01,
        rotation: Mat3::IDENTITY,
        translation: Vec3::ZERO,
    }
}

/// Analytic alpha of an isotropic Gaussian of std `s` m at camera point (x0, 0, z): the
/// linearised perspective map gives screen variances `(fx s / z)² (1 + (x0/z)²)` along u and
/// `(fy s / z)²` along v (no u-v term because y0 = 0), plus the 0.3 px² low-pass; then the
/// 3DGS alpha rules.
fn analytic_alpha(cam: &Camera, x0: f64, z: f64, s: f64, opacity: f64, px: f64, py: f64) -> f64 {
    let (fx, fy) = (cam.fx as f64, cam.fy as f64);
    let var_u = (fx * s / z).powi(2) * (1.0 + (x0 / z).powi(2)) + 0.3;
    let var_v = (fy * s / z).powi(2) + 0.3;
    let (u0, v0) = (fx * x0 / z + cam.cx as f64, cam.cy as f64);
    let power = -0.5 * ((px - u0).powi(2) / var_u + (py - v0).powi(2) / var_v);
    let alpha = (opacity * power.exp()).min(0.99);
    if alpha < 1.0 / 255.0 { 0.0 } else { alpha }
}

#[test]
fn single_isotropic_gaussian_matches_its_analytic_image() {
    let cam = axis_camera(60.0);
    let bg = [0.1f32, 0.2, 0.3];
    let color = [0.9f32, 0.6, 0.2];
    for &(x0, z, s, opacity) in &[
        (0.0, 1.0, 0.05, 0.8),
        (0.07, 0.8, 0.02, 1.0),
        (-0.2, 1.5, 0.0, 0.6),
        (0.0, 2.0, 0.3, 0.3),
    ] {
        let g = Gaussians::isotropic(
            vec![Vec3::new(x0 as f32, 0.0, z as f32)],
            vec![color],
            s as f32,
            opacity as f32,
        )
        .unwrap();
        let img = render(&g, &cam, bg).unwrap();
        let mut lit = 0;
        for y in 0..cam.height {
            for x in 0..cam.width {
                let a = analytic_alpha(&cam, x0, z, s, opacity, x as f64 + 0.5, y as f64 + 0.5);
                lit += usize::from(a > 0.0);
                let k = img.index(x, y);
                assert!(
                    (img.alpha[k] as f64 - a).abs() < 1e-5,
                    "alpha at ({x}, {y}): {} vs {a}",
                    img.alpha[k]
                );
                let got = img.pixel(x, y);
                for c in 0..3 {
                    let want = a * color[c] as f64 + (1.0 - a) * bg[c] as f64;
                    assert!((got[c] as f64 - want).abs() < 1e-5, "rgb at ({x}, {y})");
                }
                let want_depth = if a > 0.0 { z } else { 0.0 };
                assert!(
                    (img.depth[k] as f64 - want_depth).abs() < 1e-5 * z,
                    "depth at ({x}, {y})"
                );
            }
        }
        assert!(lit > 0, "the Gaussian should cover some pixels");
    }
}

#[test]
fn centred_gaussian_is_symmetric_about_the_image_centre() {
    // Pixel centres at +0.5 and the principal point at the image centre: the image of an
    // on-axis Gaussian is mirror-symmetric in both axes.
    let cam = axis_camera(50.0);
    let g = Gaussians::isotropic(vec![Vec3::new(0.0, 0.0, 1.0)], vec![[1.0; 3]], 0.1, 1.0).unwrap();
    let img = render(&g, &cam, [0.0; 3]).unwrap();
    for y in 0..48 {
        for x in 0..64 {
            let a = img.alpha[img.index(x, y)];
            assert!((a - img.alpha[img.index(63 - x, y)]).abs() < 1e-6);
            assert!((a - img.alpha[img.index(x, 47 - y)]).abs() < 1e-6);
        }
    }
    // Opacity 1 is capped at 0.99 (uncapped, the pixel nearest the centre would be 0.992).
    assert!((img.alpha[img.index(32, 24)] - 0.99).abs() < 1e-6);
    assert!(img.alpha.iter().all(|a| *a <= 0.99 + 1e-6));
}

#[test]
fn two_gaussians_composite_front_to_back() {
    // A red Gaussian in front of a blue one, both on the axis: the centre pixel is
    // a1 red + (1 - a1) a2 blue + (1 - a1)(1 - a2) background, whatever their index order.
    let cam = axis_camera(40.0);
    let front = (Vec3::new(0.0, 0.0, 1.0), [1.0f32, 0.0, 0.0], 0.6f32);
    let back = (Vec3::new(0.0, 0.0, 1.5), [0.0f32, 0.0, 1.0], 0.7f32);
    for order in [[back, front], [front, back]] {
        let g = Gaussians::new(
            order.iter().map(|o| o.0).collect(),
            vec![Quat::IDENTITY; 2],
            vec![Vec3::splat(0.05); 2],
            order.iter().map(|o| o.2).collect(),
            order.iter().map(|o| o.1).collect(),
        )
        .unwrap();
        let img = render(&g, &cam, [0.0, 1.0, 0.0]).unwrap();
        // Pixel (31, 23) has its centre 0.5 px from the axis in u and v.
        let at = |z: f64, o: f64| analytic_alpha(&cam, 0.0, z, 0.05, o, 31.5, 23.5);
        let (a1, a2) = (at(1.0, 0.6), at(1.5, 0.7));
        let p = img.pixel(31, 23);
        assert!((p[0] as f64 - a1).abs() < 1e-5);
        assert!((p[2] as f64 - (1.0 - a1) * a2).abs() < 1e-5);
        assert!((p[1] as f64 - (1.0 - a1) * (1.0 - a2)).abs() < 1e-5);
        let depth = (a1 * 1.0 + (1.0 - a1) * a2 * 1.5) / (a1 + (1.0 - a1) * a2);
        assert!((img.depth[img.index(31, 23)] as f64 - depth).abs() < 1e-5);
    }
}

#[test]
fn anisotropic_gaussian_follows_its_rotation() {
    // A needle (std 10 cm along its axis, 1 mm across) rotated 90° about the viewing axis lies
    // along v instead of u.
    let cam = axis_camera(100.0);
    let make = |q: Quat| {
        Gaussians::new(
            vec![Vec3::new(0.0, 0.0, 1.0)],
            vec![q],
            vec![Vec3::new(0.1, 0.001, 0.001)],
            vec![1.0],
            vec![[1.0; 3]],
        )
        .unwrap()
    };
    let flat = render(&make(Quat::IDENTITY), &cam, [0.0; 3]).unwrap();
    let turned = render(
        &make(Quat::from_rotation_z(std::f32::consts::FRAC_PI_2)),
        &cam,
        [0.0; 3],
    )
    .unwrap();
    // About 10 px from the centre along the needle it is still bright (analytic alpha 0.39 for
    // the flat one, 0.50 for the turned one), across it dark.
    assert!(flat.alpha[flat.index(42, 23)] > 0.3 && flat.alpha[flat.index(31, 33)] < 0.01);
    assert!(turned.alpha[turned.index(31, 33)] > 0.3 && turned.alpha[turned.index(42, 23)] < 0.01);
}
