//! No NaN within the reference bounds, divergence reported as an error, bad input rejected.

mod common;

use glam::Vec3;
use proptest::prelude::*;
use springs::{
    ActionFrame, Actions, Backbone, BackboneOptions, Manipulation, PAPER_BOUNDS, REFERENCE_BOUNDS,
    SimConfig, SimError, SpringParams, State, Substep,
};

/// A gripper moving from `start` with velocity `vel` (m/s) for `frames` frames, closed for the
/// first `closed_frames`.
fn moving_gripper(start: Vec3, vel: Vec3, frames: usize, closed_frames: usize) -> Actions {
    let pos = (0..frames)
        .map(|t| vec![start + vel * (0.1 * t as f32)])
        .collect();
    let closed = (0..frames).map(|t| vec![t < closed_frames]).collect();
    Actions::new(pos, closed).unwrap()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(40))]

    /// Any parameters inside the reference CMA-ES box (or the wider "paper" box), a small random
    /// object dropped on the ground, grasped and dragged (or pushed) by a moving gripper: the
    /// rollout succeeds and every state is finite and above the ground.
    #[test]
    fn finite_within_reference_bounds(seed in any::<u64>(), u in prop::array::uniform5(0f64..=1.0),
                                      n in 5usize..40, vel in prop::array::uniform3(-0.5f32..0.5),
                                      push in any::<bool>(), paper in prop::bool::weighted(0.25)) {
        let params = if paper { PAPER_BOUNDS } else { REFERENCE_BOUNDS }.denormalize(u);
        let mut rng = common::Rng::new(seed);
        let x0 = common::blob(&mut rng, n, 0.02, Vec3::new(0.0, 0.0, 0.025));
        let grip = x0[0];
        let held: Vec<i32> = x0.iter().map(|p| if p.distance(grip) < 0.012 { 0 } else { -1 }).collect();
        let cfg = SimConfig {
            manipulation: if push { Manipulation::Push } else { Manipulation::Grasp },
            gripper_radius: 0.015,
            ..SimConfig::default()
        };
        let bb = Backbone::new(&x0, &held, params, cfg).unwrap();
        let actions = moving_gripper(grip, Vec3::from(vel), 7, 4);
        let out = bb.rollout(&State::at_rest(x0.clone()), &actions);
        prop_assert!(out.is_ok(), "{:?} with {:?}", out.err(), params);
        let out = out.unwrap();
        for (x, v) in out.positions.iter().zip(&out.velocities) {
            prop_assert!(x.iter().chain(v).all(|p| p.is_finite()));
        }
        // Free particles are clamped to the ground at every step.
        for (p, h) in out.positions[6].iter().zip(&held) {
            prop_assert!(push || *h >= 0 || p.z >= 0.0);
        }
    }
}

#[test]
fn default_substep_is_stable_for_paper_bounds_extremes() {
    // The stiffest corner of the wider "paper" box: 5e5 N/m, 500 springs, 1e4 N s/m.
    let params = PAPER_BOUNDS.denormalize([1.0, 1.0, 1.0, 1.0, 1.0]);
    let mut rng = common::Rng::new(7);
    let x0 = common::blob(&mut rng, 120, 0.03, Vec3::new(0.0, 0.0, 0.04));
    let bb = Backbone::new(&x0, &[], params, SimConfig::default()).unwrap();
    let mut init = State::at_rest(x0.clone());
    init.x.iter_mut().for_each(|p| *p += rng.vec3(0.002));
    let out = bb.rollout(&init, &Actions::without_grippers(4)).unwrap();
    assert!(out.positions[3].iter().all(|p| p.is_finite() && p.z >= 0.0));
}

#[test]
fn too_large_fixed_substep_is_an_error_not_nan() {
    // 5e4 N/m springs at a 0.01 s substep are far beyond the bound (~2e-3 s): the state blows up
    // and the rollout must say so.
    let x0 = common::lattice(3, 3, 3, 0.01, Vec3::new(0.0, 0.0, 0.05));
    let params = SpringParams {
        stiffness: 5e4,
        damping: 0.0,
        threshold: 0.015,
        ..SpringParams::reference_rope()
    };
    let cfg = SimConfig {
        substep: Substep::Fixed { dt: 0.01 },
        ground_z: None,
        ..SimConfig::default()
    };
    let bb = Backbone::new(&x0, &[], params, cfg).unwrap();
    assert!(bb.substep_dt() > 2.0 * bb.stable_dt());
    let mut init = State::at_rest(x0.clone());
    init.x[0].x += 0.003;
    let err = bb
        .rollout(&init, &Actions::without_grippers(200))
        .unwrap_err();
    assert!(matches!(err, SimError::Diverged { .. }), "{err}");
}

#[test]
fn auto_substep_respects_bound_and_cap() {
    let x0 = common::lattice(4, 4, 4, 0.01, Vec3::ZERO);
    let bb = Backbone::new(
        &x0,
        &[],
        SpringParams::reference_rope(),
        SimConfig::default(),
    )
    .unwrap();
    assert!(bb.substep_dt() <= 0.9 * bb.stable_dt() && bb.substep_dt() <= 2e-3);
    assert!((bb.substep_dt() * bb.substeps() as f32 - 0.1).abs() < 1e-6);
    let reference = SimConfig {
        substep: Substep::Fixed { dt: 2e-5 },
        ..SimConfig::default()
    };
    let bb = Backbone::new(&x0, &[], SpringParams::reference_rope(), reference).unwrap();
    assert_eq!(bb.substeps(), 5000);
}

fn err_of<T: std::fmt::Debug>(r: Result<T, SimError>) -> SimError {
    r.unwrap_err()
}

#[test]
fn bad_input_is_rejected() {
    let x = common::lattice(2, 2, 2, 0.01, Vec3::ZERO);
    let p = SpringParams::reference_rope();
    let c = SimConfig::default();
    let new =
        |x: &[Vec3], held: &[i32], p: SpringParams, c: SimConfig| Backbone::new(x, held, p, c);

    let mut nan = x.clone();
    nan[3].y = f32::NAN;
    assert!(matches!(
        err_of(new(&nan, &[], p, c)),
        SimError::NonFinite { index: 3, .. }
    ));
    assert!(matches!(
        err_of(new(&x, &[0, 1], p, c)),
        SimError::LengthMismatch { what: "held", .. }
    ));
    let mut held = vec![-1; 8];
    held[2] = -2;
    assert!(matches!(
        err_of(new(&x, &held, p, c)),
        SimError::InvalidHeld { index: 2, .. }
    ));
    for bad in [
        SpringParams {
            stiffness: -1.0,
            ..p
        },
        SpringParams {
            damping: f32::NAN,
            ..p
        },
        SpringParams {
            threshold: 0.0,
            ..p
        },
        SpringParams {
            ground_friction: f32::INFINITY,
            ..p
        },
    ] {
        assert!(
            matches!(
                err_of(new(&x, &[], bad, c)),
                SimError::InvalidParameter { .. }
            ),
            "{bad:?}"
        );
    }
    for bad in [
        SimConfig { step_dt: 0.0, ..c },
        SimConfig {
            gravity: Vec3::new(0.0, f32::NAN, 0.0),
            ..c
        },
        SimConfig {
            ground_z: Some(f32::INFINITY),
            ..c
        },
        SimConfig {
            gripper_radius: -0.1,
            ..c
        },
        SimConfig {
            substep: Substep::Auto {
                safety: 0.0,
                max_dt: 1e-3,
            },
            ..c
        },
        SimConfig {
            substep: Substep::Auto {
                safety: 1.5,
                max_dt: 1e-3,
            },
            ..c
        },
        SimConfig {
            substep: Substep::Auto {
                safety: 0.5,
                max_dt: 0.0,
            },
            ..c
        },
        SimConfig {
            substep: Substep::Fixed { dt: -1e-3 },
            ..c
        },
    ] {
        assert!(
            matches!(
                err_of(new(&x, &[], p, bad)),
                SimError::InvalidParameter { .. }
            ),
            "{bad:?}"
        );
    }
    let opts = |m: Vec<f32>| BackboneOptions {
        masses: Some(m),
        effects: Vec::new(),
        ..Default::default()
    };
    let r = Backbone::with_options(&x, &[], p, c, opts(vec![1.0; 3]));
    assert!(matches!(
        err_of(r),
        SimError::LengthMismatch { what: "masses", .. }
    ));
    let mut m = vec![1.0; 8];
    m[5] = 0.0;
    assert!(matches!(
        err_of(Backbone::with_options(&x, &[], p, c, opts(m))),
        SimError::InvalidParameter { .. }
    ));
    // A chain order or anchor list naming a particle twice, or one the model does not have.
    for (bad, name) in [(vec![0, 1, 1], "chain"), (vec![0, 8], "chain")] {
        let chained = BackboneOptions {
            chain: Some(bad.into()),
            ..Default::default()
        };
        let err = err_of(Backbone::with_options(&x, &[], p, c, chained));
        assert!(
            matches!(err, SimError::InvalidParameter { name: n, .. } if n == name),
            "{err}"
        );
    }
    for bad in [vec![2, 2], vec![9]] {
        let anchored = BackboneOptions {
            anchors: Some(springs::AnchorSprings {
                particles: bad.into(),
                radius_m: 0.05,
                max_springs: 4,
            }),
            ..Default::default()
        };
        let err = err_of(Backbone::with_options(&x, &[], p, c, anchored));
        assert!(
            matches!(
                err,
                SimError::InvalidParameter {
                    name: "anchors",
                    ..
                }
            ),
            "{err}"
        );
    }
    let r = Backbone::new(
        &x,
        &[],
        p,
        SimConfig {
            substep: Substep::Fixed { dt: 1e-9 },
            ..c
        },
    );
    assert!(matches!(err_of(r), SimError::TooLarge { .. }));

    // Actions.
    assert!(matches!(
        err_of(Actions::new(vec![vec![Vec3::ZERO]], vec![])),
        SimError::LengthMismatch { .. }
    ));
    let r = Actions::new(
        vec![vec![Vec3::ZERO], vec![Vec3::ZERO, Vec3::ONE]],
        vec![vec![true], vec![true, true]],
    );
    assert!(matches!(err_of(r), SimError::LengthMismatch { .. }));
    let r = Actions::new(vec![vec![Vec3::NAN]], vec![vec![true]]);
    assert!(matches!(err_of(r), SimError::NonFinite { .. }));

    // Rollout and step inputs.
    let mut held = vec![-1; 8];
    held[0] = 1; // gripper 1, but the actions have one gripper only
    let bb = new(&x, &held, p, c).unwrap();
    let one = Actions::new(vec![vec![Vec3::ZERO]; 2], vec![vec![true]; 2]).unwrap();
    assert!(matches!(
        err_of(bb.rollout(&State::at_rest(x.clone()), &one)),
        SimError::InvalidHeld { index: 0, .. }
    ));
    let bb = new(&x, &[], p, c).unwrap();
    assert!(matches!(
        err_of(bb.rollout(&State::at_rest(x[..5].to_vec()), &one)),
        SimError::LengthMismatch { .. }
    ));
    let mut st = State::at_rest(x.clone());
    st.v[1].z = f32::INFINITY;
    assert!(matches!(
        err_of(bb.rollout(&st, &one)),
        SimError::NonFinite {
            what: "state.v",
            index: 1
        }
    ));
    assert!(matches!(
        err_of(bb.rollout(&State::at_rest(x.clone()), &Actions::without_grippers(0))),
        SimError::LengthMismatch { .. }
    ));

    let other = new(&common::lattice(3, 1, 1, 0.01, Vec3::ZERO), &[], p, c).unwrap();
    let mut sc = other.scratch();
    let f = ActionFrame {
        positions: &[],
        closed: &[],
    };
    let mut st = State::at_rest(x.clone());
    assert!(matches!(
        err_of(bb.step(&mut st, f, f, &mut sc)),
        SimError::ScratchMismatch { .. }
    ));
    let mut sc = bb.scratch();
    let g = ActionFrame {
        positions: &[Vec3::ZERO],
        closed: &[],
    };
    assert!(matches!(
        err_of(bb.step(&mut st, g, g, &mut sc)),
        SimError::LengthMismatch { .. }
    ));
    let before = st.clone();
    st.x[0].x = f32::NAN;
    assert!(bb.step(&mut st, f, f, &mut sc).is_err());
    st.x[0] = before.x[0];
    bb.step(&mut st, f, f, &mut sc).unwrap();
}
