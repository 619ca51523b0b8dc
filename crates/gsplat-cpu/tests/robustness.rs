//! Odd inputs give an image or a clear error, never a panic; results do not depend on the
//! thread count.

// Index loops over parallel arrays read more plainly here than zipped iterators.
#![allow(clippy::needless_range_loop)]

use glam::{Mat3, Quat, Vec3};
use gsplat::{Camera, Error, Gaussians, MASK_THRESHOLD, render};

fn camera(w: usize, h: usize) -> Camera {
    Camera::look_at(
        Vec3::new(0.0, -1.0, 0.0),
        Vec3::ZERO,
        Vec3::Z,
        60f32.to_radians(),
        w,
        h,
    )
    .unwrap()
}

fn one(mean: Vec3, scale: Vec3, opacity: f32) -> Gaussians {
    Gaussians {
        means: vec![mean],
        rotations: vec![Quat::IDENTITY],
        scales: vec![scale],
        opacities: vec![opacity],
        colors: vec![[1.0, 0.0, 0.0]],
    }
}

fn is_background(img: &gsplat::Image, bg: [f32; 3]) -> bool {
    img.alpha.iter().all(|a| *a == 0.0)
        && img.depth.iter().all(|d| *d == 0.0)
        && img.rgb.chunks(3).all(|p| p == bg)
}

#[test]
fn empty_scene_is_the_background() {
    let bg = [0.25, 0.5, 0.75];
    let img = render(&Gaussians::default(), &camera(37, 21), bg).unwrap();
    assert_eq!(
        (img.width, img.height, img.rgb.len()),
        (37, 21, 37 * 21 * 3)
    );
    assert!(is_background(&img, bg));
    assert!(img.mask(MASK_THRESHOLD).iter().all(|m| !m));
}

#[test]
fn gaussians_behind_or_at_the_camera_are_culled() {
    let bg = [0.0, 0.0, 0.0];
    // Camera at y = -1 looking along +y: y = -2 is behind, y = -1 is the eye itself, and
    // y = -0.995 is in front but closer than the 1 cm near plane.
    for y in [-2.0, -1.0, -0.995] {
        let img = render(
            &one(Vec3::new(0.0, y, 0.0), Vec3::splat(0.5), 1.0),
            &camera(32, 32),
            bg,
        )
        .unwrap();
        assert!(is_background(&img, bg), "y = {y}");
    }
    // Just beyond the near plane a big Gaussian covers the whole image.
    let img = render(
        &one(Vec3::new(0.0, -0.98, 0.0), Vec3::splat(0.5), 1.0),
        &camera(32, 32),
        bg,
    )
    .unwrap();
    assert!(img.alpha.iter().all(|a| *a > 0.9));
}

#[test]
fn negligible_opacity_draws_nothing() {
    let img = render(
        &one(Vec3::ZERO, Vec3::splat(0.1), 1.0 / 256.0),
        &camera(16, 16),
        [0.0; 3],
    )
    .unwrap();
    assert!(is_background(&img, [0.0; 3]));
}

#[test]
fn degenerate_covariances_render() {
    let bg = [1.0; 3];
    // All-zero and flat scales: the low-pass keeps a footprint of about a pixel.
    let img = render(&one(Vec3::ZERO, Vec3::ZERO, 1.0), &camera(33, 33), bg).unwrap();
    let lit = img.alpha.iter().filter(|a| **a > MASK_THRESHOLD).count();
    assert!((1..=9).contains(&lit), "{lit} pixels for a point Gaussian");
    let img = render(
        &one(Vec3::ZERO, Vec3::new(0.1, 0.0, 0.1), 1.0),
        &camera(33, 33),
        bg,
    )
    .unwrap();
    // Seen edge-on (zero std along the view) it is still a full disc; seen from the side its
    // zero axis would be a line.
    assert!(img.alpha.iter().filter(|a| **a > 0.5).count() > 20);
    // Huge scales: overflowing covariances are culled, large ones cover the image; all finite.
    for s in [1e3f32, 1e18, f32::MAX] {
        let img = render(&one(Vec3::ZERO, Vec3::splat(s), 0.5), &camera(20, 20), bg).unwrap();
        assert!(
            img.rgb
                .iter()
                .chain(&img.alpha)
                .chain(&img.depth)
                .all(|v| v.is_finite()),
            "scale {s}"
        );
    }
    // Far off-screen and very far away.
    for m in [
        Vec3::new(1e6, 1.0, 0.0),
        Vec3::new(0.0, 1e30, 0.0),
        Vec3::new(0.0, 1.0, -1e7),
    ] {
        let img = render(&one(m, Vec3::splat(0.1), 1.0), &camera(20, 20), bg).unwrap();
        assert!(img.rgb.iter().all(|v| v.is_finite()));
    }
}

#[test]
fn tiny_and_odd_image_sizes() {
    for (w, h) in [(1, 1), (1, 40), (17, 1), (15, 17), (33, 16)] {
        let img = render(
            &one(Vec3::ZERO, Vec3::splat(0.2), 0.9),
            &camera(w, h),
            [0.0; 3],
        )
        .unwrap();
        assert_eq!(img.alpha.len(), w * h);
        assert!(img.alpha.iter().any(|a| *a > 0.5), "{w} x {h}");
    }
}

#[test]
fn non_finite_and_out_of_range_inputs_are_errors() {
    let cam = camera(8, 8);
    let good = one(Vec3::ZERO, Vec3::splat(0.1), 0.5);
    let cases: Vec<(Gaussians, &str)> = vec![
        (one(Vec3::new(f32::NAN, 0.0, 0.0), Vec3::ONE, 0.5), "mean"),
        (
            one(Vec3::new(0.0, f32::INFINITY, 0.0), Vec3::ONE, 0.5),
            "mean",
        ),
        (one(Vec3::ZERO, Vec3::new(0.1, f32::NAN, 0.1), 0.5), "scale"),
        (one(Vec3::ZERO, Vec3::new(0.1, -0.1, 0.1), 0.5), "scale"),
        (one(Vec3::ZERO, Vec3::ONE, f32::NAN), "opacity"),
        (one(Vec3::ZERO, Vec3::ONE, 1.5), "opacity"),
        (one(Vec3::ZERO, Vec3::ONE, -0.1), "opacity"),
        (
            Gaussians {
                colors: vec![[0.0, f32::NAN, 0.0]],
                ..good.clone()
            },
            "colour",
        ),
        (
            Gaussians {
                rotations: vec![Quat::from_xyzw(0.0, 0.0, 0.0, 0.0)],
                ..good.clone()
            },
            "rotation",
        ),
        (
            Gaussians {
                rotations: vec![Quat::from_xyzw(f32::NAN, 0.0, 0.0, 1.0)],
                ..good.clone()
            },
            "rotation",
        ),
    ];
    for (g, what) in cases {
        match render(&g, &cam, [0.0; 3]) {
            Err(Error::Gaussian {
                index: 0,
                what: msg,
            }) => assert!(msg.contains(what), "{msg} should mention {what}"),
            other => panic!("{what}: expected a Gaussian error, got {other:?}"),
        }
    }
    let short = Gaussians {
        opacities: vec![],
        ..good.clone()
    };
    assert!(matches!(
        render(&short, &cam, [0.0; 3]),
        Err(Error::Length(_))
    ));
    assert!(render(&good, &cam, [f32::NAN, 0.0, 0.0]).is_err());
    // Non-unit but valid quaternions are normalised, not rejected.
    let scaled = Gaussians {
        rotations: vec![Quat::from_xyzw(0.0, 0.0, 1e-9, 1e-9)],
        ..good
    };
    assert!(render(&scaled, &cam, [0.0; 3]).is_ok());
}

#[test]
fn bad_cameras_are_errors() {
    let g = one(Vec3::ZERO, Vec3::splat(0.1), 0.5);
    let base = camera(8, 8);
    let bad = [
        Camera { width: 0, ..base },
        Camera {
            fx: f32::NAN,
            ..base
        },
        Camera { fy: -1.0, ..base },
        Camera { near: 0.0, ..base },
        Camera {
            cx: f32::INFINITY,
            ..base
        },
        Camera {
            rotation: Mat3::from_diagonal(Vec3::new(1.0, 1.0, 2.0)),
            ..base
        },
        Camera {
            rotation: Mat3::from_diagonal(Vec3::new(1.0, 1.0, -1.0)),
            ..base
        },
        Camera {
            translation: Vec3::NAN,
            ..base
        },
    ];
    for cam in bad {
        assert!(
            matches!(render(&g, &cam, [0.0; 3]), Err(Error::Camera(_))),
            "{cam:?}"
        );
    }
    let fov = 1.0;
    assert!(Camera::look_at(Vec3::ONE, Vec3::ONE, Vec3::Z, fov, 8, 8).is_err());
    assert!(Camera::look_at(Vec3::Z, Vec3::ZERO, Vec3::Z, fov, 8, 8).is_err());
    assert!(Camera::look_at(Vec3::X, Vec3::ZERO, Vec3::ZERO, fov, 8, 8).is_err());
    assert!(Camera::look_at(Vec3::X, Vec3::ZERO, Vec3::Z, 0.0, 8, 8).is_err());
    assert!(Camera::look_at(Vec3::X, Vec3::ZERO, Vec3::Z, 3.2, 8, 8).is_err());
    assert!(Camera::look_at(Vec3::X, Vec3::ZERO, Vec3::Z, fov, 8, 0).is_err());
    assert!(Camera::look_at(Vec3::NAN, Vec3::ZERO, Vec3::Z, fov, 8, 8).is_err());
}

#[test]
fn look_at_conventions() {
    // Looking along +y from the origin with z up: +x is image right, +z is image up.
    let cam = Camera::look_at(Vec3::ZERO, Vec3::Y, Vec3::Z, 90f32.to_radians(), 100, 100).unwrap();
    let (c, d) = cam.project(Vec3::new(0.0, 2.0, 0.0)).unwrap();
    assert!((c.x - 50.0).abs() < 1e-4 && (c.y - 50.0).abs() < 1e-4 && (d - 2.0).abs() < 1e-6);
    let (r, _) = cam.project(Vec3::new(1.0, 2.0, 0.0)).unwrap();
    assert!(r.x > 50.0 && (r.y - 50.0).abs() < 1e-4);
    let (u, _) = cam.project(Vec3::new(0.0, 2.0, 1.0)).unwrap();
    assert!(u.y < 50.0);
    // 90° vertical field of view: a point at 45° elevation lands on the top edge.
    let (top, _) = cam.project(Vec3::new(0.0, 1.0, 1.0)).unwrap();
    assert!(top.y.abs() < 1e-3);
    assert!(cam.project(Vec3::new(0.0, -1.0, 0.0)).is_none());
    assert!((cam.eye() - Vec3::ZERO).length() < 1e-6);
}

fn busy_scene() -> Gaussians {
    let mut g = Gaussians::default();
    for i in 0..3000u32 {
        let f = |k: u32| {
            ((i.wrapping_mul(2_654_435_761).wrapping_add(k * 40_503)) % 10_007) as f32 / 10_007.0
        };
        g.means
            .push(Vec3::new(f(1) - 0.5, f(2) - 0.5, f(3) - 0.5) * 0.8);
        g.rotations
            .push(Quat::from_xyzw(f(4) - 0.5, f(5) - 0.5, f(6) - 0.5, 1.0));
        g.scales.push(Vec3::new(f(7), f(8), f(9)) * 0.03);
        g.opacities.push(f(10));
        g.colors.push([f(11), f(12), f(13)]);
    }
    g
}

#[test]
fn result_does_not_depend_on_thread_count() {
    let g = busy_scene();
    let cam = camera(150, 110);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| render(&g, &cam, [0.3; 3]).unwrap())
    };
    let one_thread = run(1);
    assert!(one_thread.alpha.iter().filter(|a| **a > 0.5).count() > 1000);
    for threads in [2, 3, 8] {
        assert!(
            run(threads) == one_thread,
            "{threads} threads differ from one"
        );
    }
}

#[test]
fn framing_fits_points_in_view() {
    // A wide flat set (a rope on the table) and a tall one (a hanging cloth).
    let wide: Vec<Vec3> = (0..50)
        .map(|i| Vec3::new(-0.4 + 0.016 * i as f32, 0.05 * (i as f32 * 0.3).sin(), 0.01))
        .collect();
    let tall: Vec<Vec3> = (0..50)
        .map(|i| Vec3::new(0.1 * (i % 5) as f32, 0.0, 0.3 + 0.01 * i as f32))
        .collect();
    for pts in [wide, tall] {
        for dir in [Vec3::new(0.0, 1.0, -0.6), Vec3::new(-1.0, 0.3, -0.2)] {
            let cam =
                Camera::framing(&pts, dir, Vec3::Z, 45f32.to_radians(), 200, 150, 0.8).unwrap();
            let used = pts
                .iter()
                .map(|p| {
                    let (uv, _) = cam.project(*p).expect("in front");
                    ((uv.x - 100.0).abs() / 100.0).max((uv.y - 75.0).abs() / 75.0)
                })
                .fold(0f32, f32::max);
            assert!(
                (0.7..=0.9).contains(&used),
                "points use {used} of the half-image"
            );
        }
    }
    let one = [Vec3::ONE];
    assert!(
        Camera::framing(&one, Vec3::X, Vec3::Z, 1.0, 10, 10, 0.5).is_ok(),
        "a single point"
    );
    assert!(Camera::framing(&[], Vec3::X, Vec3::Z, 1.0, 10, 10, 0.5).is_err());
    assert!(Camera::framing(&one, Vec3::ZERO, Vec3::Z, 1.0, 10, 10, 0.5).is_err());
    assert!(Camera::framing(&one, Vec3::X, Vec3::Z, 1.0, 10, 10, 0.0).is_err());
    assert!(Camera::framing(&[Vec3::NAN], Vec3::X, Vec3::Z, 1.0, 10, 10, 0.5).is_err());
}

#[test]
fn an_image_too_large_to_hold_is_refused_before_anything_is_allocated() {
    let look = |w, h| Camera::look_at(Vec3::new(0.0, -1.0, 0.0), Vec3::ZERO, Vec3::Z, 1.0, w, h);
    // Each side within 2^20, but 10^10 pixels (200 GB of buffers).
    match look(100_000, 100_000) {
        Err(Error::Camera(m)) => assert!(m.contains("too large"), "{m}"),
        other => panic!("{:?}", other.map(|_| ())),
    }
    assert!(look(1 << 21, 1).is_err());
    assert!(look(8192, 8192).is_ok());
    assert!(look(8192, 8193).is_err());
    assert_eq!(gsplat::MAX_PIXELS, 8192 * 8192);
}
