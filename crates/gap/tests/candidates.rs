//! Each candidate effect changes a rollout at its starting strength and leaves it unchanged at
//! its neutral parameters; the report serialises with the documented keys.

use std::sync::Arc;

use gap::{Candidate, MaterialFrame};
use glam::Vec3;
use springs::{Actions, Backbone, BackboneOptions, SimConfig, SpringParams, State};

/// A 12 x 3 strip 2 cm above the ground, its first column held by gripper 0, which drags it
/// sideways and lifts it, so ground contact, stretching and grasping all occur.
fn scene() -> (Vec<Vec3>, Vec<i32>, Actions, State) {
    let mut x = Vec::new();
    let mut held = Vec::new();
    for i in 0..12 {
        for j in 0..3 {
            x.push(Vec3::new(0.02 * i as f32, 0.02 * j as f32, 0.004));
            held.push(if i == 0 { 0 } else { -1 });
        }
    }
    let frames: Vec<Vec<Vec3>> = (0..16)
        .map(|t| {
            let t = t as f32;
            vec![Vec3::new(
                0.0 - 0.03 * t,
                0.02 + 0.01 * t,
                0.004 + 0.015 * t,
            )]
        })
        .collect();
    let actions = Actions::new(frames, vec![vec![true]; 16]).unwrap();
    let state = State {
        x: x.clone(),
        v: vec![Vec3::new(0.3, 0.0, 0.0); x.len()],
    };
    (x, held, actions, state)
}

fn params() -> SpringParams {
    SpringParams {
        stiffness: 2000.0,
        damping: 5.0,
        threshold: 0.03,
        max_springs: 12,
        ground_friction: 0.4,
    }
}

fn frame(x: &[Vec3]) -> MaterialFrame {
    let f = MaterialFrame::new(x, Vec3::new(0.1, 0.02, 0.05)).unwrap();
    // `stiffness-lag` needs a grasp lag; the axis coordinate stands in for one here.
    let lag = f.coordinate.to_vec();
    f.with_lag(Some(lag))
}

fn roll(effect: Option<(Candidate, Vec<f64>)>) -> Vec<Vec<Vec3>> {
    let (x, held, actions, state) = scene();
    let f = frame(&x);
    // `bending-damping` acts along a chain only: the strip's middle row. `twist` needs both
    // ends of its chain held: out along the middle row and back along the edge row, a U whose
    // two ends the gripper holds.
    let chain = effect.as_ref().and_then(|(c, _)| match c {
        Candidate::BendingDamping => Some((0..12u32).map(|i| 3 * i + 1).collect::<Arc<[u32]>>()),
        Candidate::Twist => Some(
            (0..12u32)
                .map(|i| 3 * i + 1)
                .chain((0..12u32).rev().map(|i| 3 * i + 2))
                .collect(),
        ),
        _ => None,
    });
    let effects = effect
        .map(|(c, v)| vec![c.effect(&v, &f)])
        .unwrap_or_default();
    let bb = Backbone::with_options(
        &x,
        &held,
        params(),
        SimConfig::default(),
        BackboneOptions {
            masses: None,
            effects,
            chain,
            ..Default::default()
        },
    )
    .unwrap();
    bb.rollout(&state, &actions).unwrap().positions
}

fn max_diff(a: &[Vec<Vec3>], b: &[Vec<Vec3>]) -> f32 {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(p, q)| p.distance(*q))
        .fold(0.0, f32::max)
}

#[test]
fn every_candidate_changes_the_rollout_and_vanishes_at_neutral() {
    let plain = roll(None);
    for c in Candidate::LIBRARY
        .into_iter()
        .chain(Candidate::EXTRA)
        .chain([Candidate::ExternalField])
    {
        let on = roll(Some((c, c.start())));
        let off = roll(Some((c, c.neutral())));
        let changed = max_diff(&plain, &on);
        let neutral = max_diff(&plain, &off);
        // The strip's U-shaped chain barely twists as it is dragged (about 10 µm at the
        // start strength); `tests/twist.rs` checks the torsion on a swinging loop.
        let min_change = if c == Candidate::Twist { 1e-6 } else { 1e-4 };
        assert!(
            changed > min_change,
            "{}: start changes the rollout by only {changed} m",
            c.name()
        );
        // Grasp slip's neutral is a very stiff grasp, which only approaches the kinematic one.
        let tol = if c == Candidate::GraspSlip {
            5e-3
        } else {
            1e-6
        };
        assert!(
            neutral <= tol,
            "{}: neutral differs by {neutral} m",
            c.name()
        );
        assert_eq!(c.start().len(), c.parameters().len());
        assert_eq!(c.neutral().len(), c.parameters().len());
        assert_eq!(Candidate::parse(c.name()).unwrap(), c);
    }
    assert!(Candidate::parse("magnet").is_err());
    assert!(Candidate::parse("rotating-frame").is_err());
}

#[test]
fn the_probes_window_confines_its_field() {
    // Frame centre (0.1, 0.02, 0.05) m; the strip starts at x in [0, 0.22] m and is dragged
    // towards -x.
    let field = |dx: f64, window: f64| {
        vec![
            0.0, 0.0, 2.0, 0.0, dx, 0.0, 0.0, window, // a0 = +2 m/s² up, no gradient
        ]
    };
    let plain = roll(None);
    let wide = roll(Some((Candidate::ExternalField, field(0.0, 5.0))));
    let near = roll(Some((Candidate::ExternalField, field(0.0, 0.1))));
    let far = roll(Some((Candidate::ExternalField, field(0.5, 0.05))));
    // Centred 0.5 m along +x from the frame centre, at least 0.38 m from the strip, a 5 cm
    // window leaves less than e^-28 of the field there: nothing moves.
    assert!(max_diff(&plain, &far) < 1e-6, "{}", max_diff(&plain, &far));
    // On the strip it acts, and a wide window (the whole strip at full strength) more than a
    // narrow one.
    let (n, w) = (max_diff(&plain, &near), max_diff(&plain, &wide));
    assert!(n > 1e-3, "{n}");
    assert!(w > n, "wide {w} narrow {n}");
}

#[test]
fn the_probe_starts_at_the_residuals_focus_and_the_rest_as_before() {
    let (x, ..) = scene();
    let plain = frame(&x);
    let focus = |point_m: [f32; 3], spread_m: f32, attracting: bool| {
        plain.clone().with_focus(Some(gap::ResidualFocus {
            point_m,
            spread_m,
            attracting,
        }))
    };
    let probe = Candidate::ExternalField;
    // Without a focus, every candidate starts where it always did.
    assert_eq!(probe.start_in(&plain), probe.start());
    // With one: a central field there (offset from the frame centre 0.1, 0.02, 0.05 m), no
    // uniform part, pulling when the residuals point to it, with the lines' spread as window,
    // no velocity term.
    let s = probe.start_in(&focus([0.3, 0.02, 0.0], 0.2, true));
    let want = [0.0, 0.0, 0.0, -2.0, 0.2, 0.0, -0.05, 0.2, 0.0, 0.0, 0.0];
    assert_eq!(s.len(), want.len());
    for (a, b) in s.iter().zip(want) {
        assert!((a - b).abs() < 1e-6, "{s:?}");
    }
    // Pushing when they point away; offset and window held to their ranges.
    let s = probe.start_in(&focus([3.0, -2.0, 0.05], 0.001, false));
    assert_eq!(s[3], 2.0);
    assert!((s[4] - 0.5).abs() < 1e-6 && (s[5] + 0.5).abs() < 1e-6 && s[6].abs() < 1e-6);
    assert_eq!(s[7], gap::PROBE_WINDOW_M[0]);
    // The library candidates ignore the focus.
    let f = focus([0.3, 0.02, 0.0], 0.2, true);
    for c in Candidate::LIBRARY {
        assert_eq!(c.start_in(&f), c.start(), "{}", c.name());
    }
    // The start lies inside the probe's own ranges.
    let ranges = probe.parameters();
    for (v, p) in s.iter().zip(&ranges) {
        assert!(*v >= p.lower && *v <= p.upper, "{} = {v}", p.name);
    }
}

#[test]
fn material_axis_follows_particle_order() {
    let x: Vec<Vec3> = (0..10)
        .map(|i| Vec3::new(-0.1 * i as f32, 0.0, 0.0))
        .collect();
    let f = MaterialFrame::new(&x, Vec3::ZERO).unwrap();
    let u: &Arc<Vec<f32>> = &f.coordinate;
    assert!((u[0] + 1.0).abs() < 1e-5 && (u[9] - 1.0).abs() < 1e-5);
    assert!(u.windows(2).all(|w| w[1] > w[0]));
    assert!(MaterialFrame::new(&x[..1], Vec3::ZERO).is_err());
    // A shape alone: the same coordinate, centred on the shape's mean.
    let own = MaterialFrame::of_shape(&x).unwrap();
    assert_eq!(own.coordinate, f.coordinate);
    assert!((own.centre - Vec3::new(-0.45, 0.0, 0.0)).length() < 1e-6);
    assert!(MaterialFrame::of_shape(&[]).is_err());
}

#[test]
fn bad_effect_parameters_are_errors_not_panics() {
    let (x, held, _, _) = scene();
    let f = frame(&x);
    for (c, v) in [
        (Candidate::Drag, vec![f64::NAN]),
        (Candidate::NonlinearElasticity, vec![10.0, 1.5]),
        (Candidate::GraspSlip, vec![0.0, 1.0]),
        (Candidate::ActuationDelay, vec![-1.0]),
        (
            Candidate::ExternalField,
            vec![0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        ),
    ] {
        let opts = BackboneOptions {
            masses: None,
            effects: vec![c.effect(&v, &f)],
            ..Default::default()
        };
        assert!(
            Backbone::with_options(&x, &held, params(), SimConfig::default(), opts).is_err(),
            "{}",
            c.name()
        );
    }
}

/// A lone free particle (no springs, no ground) starting at 1 m height with velocity `v0`
/// under `candidate` at `values`, `steps` model steps on: its final position and velocity.
/// Particle 0 is held still; the free one, 5 m away, is beyond any spring.
fn lone_particle(
    config: SimConfig,
    candidate: Candidate,
    values: &[f64],
    v0: Vec3,
    steps: usize,
) -> (Vec3, Vec3) {
    let x = vec![Vec3::new(0.0, 0.0, 1.0), Vec3::new(5.0, 0.0, 1.0)];
    let held = vec![0, -1];
    let actions = Actions::new(vec![vec![x[0]]; steps + 1], vec![vec![true]; steps + 1]).unwrap();
    let config = SimConfig {
        ground_z: None,
        ..config
    };
    let bb = Backbone::with_options(
        &x,
        &held,
        params(),
        config,
        BackboneOptions {
            masses: None,
            effects: vec![candidate.effect(values, &frame(&x))],
            ..Default::default()
        },
    )
    .unwrap();
    let state = State {
        x: x.clone(),
        v: vec![Vec3::ZERO, v0],
    };
    // Entry 0 of a rollout is the initial state, so the last entry is `steps` steps later.
    let out = bb.rollout(&state, &actions).unwrap();
    (out.positions[steps][1], out.velocities[steps][1])
}

/// `gravity-scale` at factor s makes a lone free particle (no springs, no ground) fall with
/// acceleration s g: after t seconds from rest it has dropped ½ s g t².
#[test]
fn gravity_scale_multiplies_free_fall() {
    let steps = 10;
    let config = SimConfig::default();
    let g = -config.gravity.z;
    let t = config.step_dt * steps as f32;
    for s in [1.0f32, 1.5] {
        let (end, _) = lone_particle(
            config,
            Candidate::GravityScale,
            &[f64::from(s)],
            Vec3::ZERO,
            steps,
        );
        let drop = 1.0 - end.z;
        let expected = 0.5 * s * g * t * t;
        // Semi-implicit Euler over many substeps: within 2 % of the exact drop.
        assert!(
            (drop - expected).abs() < 0.02 * expected,
            "factor {s}: dropped {drop} m, expected {expected} m"
        );
    }
}

/// The probe's velocity term `v × b` turns a lone free particle's velocity at |b| rad/s about
/// −b̂ and keeps its speed (no gravity, no ground, position field off): after t seconds a
/// particle moving along +x at 1 m/s with b = (0, 0, 2) 1/s moves along (cos 2t, −sin 2t, 0).
#[test]
fn the_probes_velocity_term_turns_without_work() {
    let steps = 5;
    let config = SimConfig {
        gravity: Vec3::ZERO,
        ..SimConfig::default()
    };
    let t = config.step_dt * steps as f32;
    let probe_neutral = Candidate::ExternalField.neutral();
    let mut probe = probe_neutral.clone();
    probe[10] = 2.0;
    let (_, v) = lone_particle(config, Candidate::ExternalField, &probe, Vec3::X, steps);
    let want = Vec3::new((2.0 * t).cos(), -(2.0 * t).sin(), 0.0);
    assert!((v.length() - 1.0).abs() < 1e-4, "speed {}", v.length());
    assert!((v - want).length() < 1e-3, "velocity {v}, expected {want}");
    // Neutral (b = 0): it goes straight on.
    let (_, v) = lone_particle(
        config,
        Candidate::ExternalField,
        &probe_neutral,
        Vec3::X,
        steps,
    );
    assert!((v - Vec3::X).length() < 1e-6, "{v}");
}

/// A 12 x 3 strip hanging straight down from its top row (or lying flat on the ground, 4 mm
/// up, from its first row), which gripper 0 holds still for 6 s (60 frames); returns the held
/// particles' mean height at the end, m.
fn grasp_height(grasp: Option<Vec<f64>>, lying: bool) -> f32 {
    let frames = 60;
    let (mut x, mut held) = (Vec::new(), Vec::new());
    for i in 0..12 {
        for j in 0..3 {
            let along = 0.02 * i as f32;
            x.push(match lying {
                true => Vec3::new(0.02 * j as f32, along, 0.004),
                false => Vec3::new(0.02 * j as f32, 0.0, 0.4 - along),
            });
            held.push(if i == 0 { 0 } else { -1 });
        }
    }
    let grip = vec![vec![Vec3::new(0.02, 0.0, x[0].z)]; frames + 1];
    let actions = Actions::new(grip, vec![vec![true]; frames + 1]).unwrap();
    let effects = grasp
        .map(|v| vec![Candidate::GraspSlip.effect(&v, &frame(&x))])
        .unwrap_or_default();
    let bb = Backbone::with_options(
        &x,
        &held,
        SpringParams {
            damping: 50.0,
            ..params()
        },
        SimConfig::default(),
        BackboneOptions {
            masses: None,
            effects,
            ..Default::default()
        },
    )
    .unwrap();
    let state = State {
        x: x.clone(),
        v: vec![Vec3::ZERO; x.len()],
    };
    let last = bb
        .rollout(&state, &actions)
        .unwrap()
        .positions
        .pop()
        .unwrap();
    (0..3).map(|j| last[j].z).sum::<f32>() / 3.0
}

/// How far the held row ends from where the rigid grasp holds it, mm (see [`grasp_height`]).
fn shift_from_rigid_mm(grasp: Vec<f64>, lying: bool) -> f32 {
    (grasp_height(Some(grasp), lying) - grasp_height(None, lying)) * 1e3
}

/// Rollouts start in the middle of recordings, where a hanging object's compliant grasp is
/// already stretched by its weight: the grasp starts loaded, so the held row stays where it
/// was observed instead of dropping by the stretch (1 cm at relative stiffness 1).
#[test]
fn a_hanging_object_starts_with_its_grasp_loaded() {
    let shift = shift_from_rigid_mm(vec![1.0, 100.0], false);
    assert!(
        shift.abs() < 2.0,
        "the held row settles {shift} mm from the rigid grasp's"
    );
    // A softer grasp (5 cm under the weight) stays there as well, while it never slips.
    let soft = shift_from_rigid_mm(vec![0.2, 100.0], false);
    assert!(soft.abs() < 10.0, "{soft} mm");
}

/// An object lying on the ground rests on it: its grasp starts unloaded, so the held row is
/// not lifted by the stretch a hanging object's grasp would start with (1 cm here).
#[test]
fn a_lying_object_starts_with_its_grasp_unloaded() {
    let shift = shift_from_rigid_mm(vec![1.0, 100.0], true);
    assert!(
        shift.abs() < 2.0,
        "the held row settles {shift} mm from the rigid grasp's"
    );
}
