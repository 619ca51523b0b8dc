//! Gaussians on particles: construction and step-by-step deformation.

// Index loops over parallel arrays read more plainly here than zipped iterators.
#![allow(clippy::needless_range_loop)]

use glam::{Mat3, Quat, Vec3};
use gsplat::{Error, GaussianRig, Gaussians, RigOptions};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed};

/// A 6 x 5 x 2 grid with `h` metre spacing.
fn grid(h: f32) -> Vec<Vec3> {
    let mut p = Vec::new();
    for k in 0..2 {
        for j in 0..5 {
            for i in 0..6 {
                p.push(Vec3::new(i as f32, j as f32, k as f32) * h);
            }
        }
    }
    p
}

fn colors(n: usize) -> Vec<[f32; 3]> {
    (0..n)
        .map(|i| [i as f32 / n as f32, 0.5, 1.0 - i as f32 / n as f32])
        .collect()
}

#[test]
fn scale_comes_from_neighbour_spacing() {
    // On a regular grid every particle's 3 nearest neighbours are at the spacing h.
    let h = 0.02;
    let pts = grid(h);
    let opts = RigOptions {
        scale_factor: 0.5,
        opacity: 0.8,
        ..RigOptions::default()
    };
    let rig = GaussianRig::from_particles(&pts, &colors(pts.len()), &opts).unwrap();
    let g = rig.gaussians();
    assert_eq!(g.len(), pts.len());
    for i in 0..g.len() {
        assert!((g.scales[i] - Vec3::splat(0.5 * h)).abs().max_element() < 1e-6);
        assert_eq!(g.means[i], pts[i]);
        assert_eq!(g.opacities[i], 0.8);
    }
    assert_eq!(g.colors, colors(pts.len()));
    // A stray far particle gets at most twice the median spacing.
    let mut stray = pts.clone();
    stray.push(Vec3::new(5.0, 5.0, 5.0));
    let rig = GaussianRig::from_particles(&stray, &colors(stray.len()), &opts).unwrap();
    assert!((rig.gaussians().scales[pts.len()].x - 0.5 * 2.0 * h).abs() < 1e-6);
}

/// A rigid motion: rotation about an axis through `centre`, then a translation.
fn rigid(rot: Quat, shift: Vec3) -> impl Fn(Vec3) -> Vec3 {
    let centre = Vec3::new(0.05, 0.04, 0.01);
    move |p| rot * (p - centre) + centre + shift
}

#[test]
fn rigid_motion_moves_means_and_rotates_covariances() {
    let pts = grid(0.02);
    let mut rig =
        GaussianRig::from_particles(&pts, &colors(pts.len()), &RigOptions::default()).unwrap();
    // Give the Gaussians anisotropic shapes and orientations so covariance rotation shows.
    let mut g0 = rig.gaussians().clone();
    for i in 0..g0.len() {
        g0.scales[i] = Vec3::new(0.02, 0.005, 0.001);
        g0.rotations[i] = Quat::from_rotation_y(0.1 * i as f32);
        // Gaussians off the particles too: halfway to the next one.
        g0.means[i] += Vec3::new(0.01, 0.0, 0.0);
    }
    rig = GaussianRig::new(g0.clone(), &pts, &RigOptions::default()).unwrap();
    // Ten steps of 6° about a tilted axis plus a drift: the composition is rigid.
    let step = Quat::from_axis_angle(Vec3::new(0.3, -0.5, 0.8).normalize(), 6f32.to_radians());
    let mut total = Quat::IDENTITY;
    let mut shift = Vec3::ZERO;
    for _ in 0..10 {
        total = step * total;
        shift += Vec3::new(0.003, -0.002, 0.004);
        let f = rigid(total, shift);
        let moved: Vec<Vec3> = pts.iter().map(|p| f(*p)).collect();
        rig.deform(&moved).unwrap();
    }
    let f = rigid(total, shift);
    let r = Mat3::from_quat(total);
    let g = rig.gaussians();
    for i in 0..g.len() {
        assert!(
            (g.means[i] - f(g0.means[i])).length() < 2e-5,
            "mean {i}: {} vs {}",
            g.means[i],
            f(g0.means[i])
        );
        let want = r * g0.covariance(i) * r.transpose();
        let got = g.covariance(i);
        let err = (got - want)
            .to_cols_array()
            .iter()
            .fold(0f32, |m, v| m.max(v.abs()));
        assert!(
            err < 1e-4 * 0.02 * 0.02 + 1e-9,
            "covariance {i} off by {err}"
        );
        assert_eq!(g.scales[i], g0.scales[i]);
        assert_eq!(g.opacities[i], g0.opacities[i]);
        assert_eq!(g.colors[i], g0.colors[i]);
    }
}

#[test]
fn identity_step_changes_nothing() {
    let pts = grid(0.01);
    let mut rig =
        GaussianRig::from_particles(&pts, &colors(pts.len()), &RigOptions::default()).unwrap();
    let before = rig.gaussians().clone();
    let after = rig.deform(&pts).unwrap();
    for i in 0..before.len() {
        assert!((after.means[i] - before.means[i]).length() < 1e-7);
        assert!(after.rotations[i].dot(before.rotations[i]).abs() > 1.0 - 1e-6);
    }
}

#[test]
fn bad_inputs_are_errors() {
    let pts = grid(0.01);
    let c = colors(pts.len());
    let opts = RigOptions::default();
    assert!(matches!(
        GaussianRig::from_particles(&pts[..1], &c[..1], &opts),
        Err(Error::Particles(_))
    ));
    assert!(matches!(
        GaussianRig::from_particles(&pts, &c[..3], &opts),
        Err(Error::Particles(_))
    ));
    assert!(matches!(
        GaussianRig::from_particles(&vec![Vec3::ONE; 40], &colors(40), &opts),
        Err(Error::Particles(_))
    ));
    let mut nan = pts.clone();
    nan[3].y = f32::NAN;
    assert!(matches!(
        GaussianRig::from_particles(&nan, &c, &opts),
        Err(Error::Particles(_))
    ));
    let mut nan_colour = c.clone();
    nan_colour[2][1] = f32::NAN;
    assert!(GaussianRig::from_particles(&pts, &nan_colour, &opts).is_err());
    for bad in [
        RigOptions {
            bones_per_gaussian: 0,
            ..opts
        },
        RigOptions {
            fit_neighbours: 0,
            ..opts
        },
        RigOptions {
            scale_factor: -1.0,
            ..opts
        },
        RigOptions {
            opacity: 1.5,
            ..opts
        },
        RigOptions {
            opacity: f32::NAN,
            ..opts
        },
    ] {
        assert!(matches!(
            GaussianRig::from_particles(&pts, &c, &bad),
            Err(Error::Options(_))
        ));
    }
    assert!(GaussianRig::new(Gaussians::default(), &[], &opts).is_err());
    let mut rig = GaussianRig::from_particles(&pts, &c, &opts).unwrap();
    let before = rig.gaussians().clone();
    assert!(rig.deform(&pts[1..]).is_err());
    assert!(rig.deform(&nan).is_err());
    assert_eq!(
        rig.gaussians(),
        &before,
        "a failed step leaves the rig unchanged"
    );
    assert_eq!(rig.bones(), &pts[..]);
}

#[test]
fn degenerate_particle_sets_work() {
    let c = colors(30);
    // Collinear (a straight rope): the twist is undetermined and stays put.
    let line: Vec<Vec3> = (0..30)
        .map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.0))
        .collect();
    let mut rig = GaussianRig::from_particles(&line, &c, &RigOptions::default()).unwrap();
    let shifted: Vec<Vec3> = line.iter().map(|p| *p + Vec3::Z * 0.1).collect();
    let g = rig.deform(&shifted).unwrap();
    for i in 0..30 {
        assert!((g.means[i] - shifted[i]).length() < 1e-6);
        assert!(g.rotations[i].dot(Quat::IDENTITY).abs() > 1.0 - 1e-6);
    }
    // Every particle collapsing onto one point, then a few duplicates: no panic.
    let collapsed = vec![Vec3::new(0.1, 0.2, 0.3); 30];
    assert!(
        rig.deform(&collapsed)
            .unwrap()
            .means
            .iter()
            .all(|m| m.is_finite())
    );
    let mut dup = line.clone();
    dup[5] = dup[6];
    dup[7] = dup[6];
    assert!(GaussianRig::from_particles(&dup, &c, &RigOptions::default()).is_ok());
    // Options asking for more neighbours than exist.
    let many = RigOptions {
        bones_per_gaussian: 100,
        fit_neighbours: 100,
        spacing_neighbours: 100,
        ..RigOptions::default()
    };
    let mut rig = GaussianRig::from_particles(&line[..2], &c[..2], &many).unwrap();
    assert!(rig.deform(&shifted[..2]).is_ok());
}

#[test]
fn deformation_does_not_depend_on_thread_count() {
    let pts = grid(0.02);
    let bent: Vec<Vec3> = pts
        .iter()
        .map(|p| Quat::from_rotation_y(2.0 * p.x) * *p + Vec3::new(0.0, 0.1 * p.x * p.x, 0.0))
        .collect();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut rig =
                GaussianRig::from_particles(&pts, &colors(pts.len()), &RigOptions::default())
                    .unwrap();
            rig.deform(&bent).unwrap().clone()
        })
    };
    assert_eq!(run(1), run(3));
}

proptest! {
    #![proptest_config(Config { cases: 32, rng_seed: RngSeed::Fixed(0x0b0e5), ..Config::default() })]

    /// Gaussians built on particles stay on their particles through arbitrary smooth
    /// deformations (their own bone dominates the inverse-distance weights).
    #[test]
    fn gaussians_follow_their_particles(
        steps in prop::collection::vec((-0.3f32..0.3, -0.3f32..0.3, -0.02f32..0.02), 1..6)
    ) {
        let pts = grid(0.02);
        let mut rig = GaussianRig::from_particles(&pts, &colors(pts.len()), &RigOptions::default()).unwrap();
        let mut cur = pts.clone();
        for (bend, twist, lift) in steps {
            cur = cur
                .iter()
                .map(|p| Quat::from_rotation_z(bend * p.x) * Quat::from_rotation_x(twist * p.y) * *p + Vec3::Z * lift)
                .collect();
            let g = rig.deform(&cur).unwrap();
            for i in 0..cur.len() {
                prop_assert!((g.means[i] - cur[i]).length() < 1e-5);
                prop_assert!((g.rotations[i].length() - 1.0).abs() < 1e-5);
            }
        }
    }
}
