//! Grasping, pushing, ground contact and the dashpot against closed-form solutions.

mod common;

use glam::Vec3;
use springs::{
    ActionFrame, Actions, Backbone, Dashpot, Manipulation, SimConfig, SpringParams, State, Substep,
};

fn rope_with_held_end() -> (Vec<Vec3>, Vec<i32>) {
    let x = common::rope(200, 0.4, 0.004, 0.01);
    let held = x.iter().map(|p| if p.x < 0.01 { 0 } else { -1 }).collect();
    (x, held)
}

#[test]
fn held_particles_follow_their_gripper_exactly() {
    let (x, held) = rope_with_held_end();
    let bb = Backbone::new(
        &x,
        &held,
        SpringParams::reference_rope(),
        SimConfig::default(),
    )
    .unwrap();
    // Lift, swing sideways, then open at frame 5.
    let path = [
        Vec3::ZERO,
        Vec3::new(0.0, 0.0, 0.05),
        Vec3::new(0.0, 0.04, 0.1),
        Vec3::new(0.03, 0.08, 0.12),
    ];
    let frames: Vec<Vec<Vec3>> = (0..8).map(|t| vec![path[t.min(3)]]).collect();
    let closed: Vec<Vec<bool>> = (0..8).map(|t| vec![t < 5]).collect();
    let out = bb
        .rollout(
            &State::at_rest(x.clone()),
            &Actions::new(frames.clone(), closed).unwrap(),
        )
        .unwrap();
    let ids: Vec<usize> = (0..x.len()).filter(|&i| held[i] == 0).collect();
    assert!(ids.len() >= 3);
    for t in 1..=5 {
        for &i in &ids {
            let expected = x[i] + (frames[t][0] - frames[0][0]);
            assert!(
                (out.positions[t][i] - expected).length() < 1e-5,
                "frame {t} particle {i}"
            );
            let vg = (frames[t][0] - frames[t - 1][0]) / 0.1;
            assert!((out.velocities[t][i] - vg).length() < 1e-4);
        }
    }
    // Released at frame 5: the end now falls instead of staying at the gripper.
    for &i in &ids {
        assert!(out.positions[7][i].z < out.positions[5][i].z - 0.01);
    }
    // The rest of the rope is pulled along.
    assert!(out.positions[5].iter().filter(|p| p.z > 0.05).count() > 10);
}

#[test]
fn step_by_step_equals_rollout() {
    let (x, held) = rope_with_held_end();
    let bb = Backbone::new(
        &x,
        &held,
        SpringParams::reference_rope(),
        SimConfig::default(),
    )
    .unwrap();
    let frames: Vec<Vec<Vec3>> = (0..4)
        .map(|t| vec![Vec3::new(0.0, 0.0, 0.04 * t as f32)])
        .collect();
    let actions = Actions::new(frames, vec![vec![true]; 4]).unwrap();
    let out = bb.rollout(&State::at_rest(x.clone()), &actions).unwrap();
    let mut st = State::at_rest(x);
    let mut sc = bb.scratch();
    for t in 0..3 {
        bb.step(
            &mut st,
            actions.frame(t).unwrap(),
            actions.frame(t + 1).unwrap(),
            &mut sc,
        )
        .unwrap();
        assert_eq!(st.x, out.positions[t + 1]);
        assert_eq!(st.v, out.velocities[t + 1]);
    }
}

#[test]
fn push_keeps_particles_outside_the_gripper_sphere() {
    // A block resting on the ground; a sphere of radius 1.5 cm sweeps through it at 0.2 m/s.
    let x = common::lattice(6, 6, 3, 0.01, Vec3::new(0.0, 0.0, 0.0));
    let r = 0.015;
    let cfg = SimConfig {
        manipulation: Manipulation::Push,
        gripper_radius: r,
        ..SimConfig::default()
    };
    let params = SpringParams {
        threshold: 0.015,
        ..SpringParams::reference_rope()
    };
    let bb = Backbone::new(&x, &[], params, cfg).unwrap();
    let start = Vec3::new(-0.03, 0.025, 0.015);
    let frames: Vec<Vec<Vec3>> = (0..6)
        .map(|t| vec![start + Vec3::new(0.02 * t as f32, 0.0, 0.0)])
        .collect();
    let out = bb
        .rollout(
            &State::at_rest(x.clone()),
            &Actions::new(frames.clone(), vec![vec![true]; 6]).unwrap(),
        )
        .unwrap();
    for (t, (f, ps)) in frames.iter().zip(&out.positions).enumerate().skip(1) {
        let c = f[0];
        for p in ps {
            assert!(
                p.distance(c) >= r - 1e-4,
                "frame {t}: particle {p} inside sphere at {c}"
            );
        }
    }
    // The sphere ploughs through the block, dragging it along +x (by about 4 mm).
    let mean = |ps: &[Vec3]| ps.iter().sum::<Vec3>() / ps.len() as f32;
    assert!(mean(&out.positions[5]).x > mean(&x).x + 0.002);
    // An inactive (open) gripper does nothing: same result as no gripper at all.
    let open = bb
        .rollout(
            &State::at_rest(x.clone()),
            &Actions::new(frames, vec![vec![false]; 6]).unwrap(),
        )
        .unwrap();
    let none = bb
        .rollout(&State::at_rest(x.clone()), &Actions::without_grippers(6))
        .unwrap();
    assert_eq!(open, none);
}

/// Isolated particles (no springs) resting in ground contact, sliding at 1 m/s: Coulomb friction
/// with `mu = (ground_friction + 0.5) / 2` decelerates them at `mu g`.
#[test]
fn ground_friction_decelerates_at_mu_g() {
    let g = 9.8;
    let params = SpringParams {
        ground_friction: 0.42,
        threshold: 0.002,
        ..SpringParams::reference_rope()
    };
    let mu = params.effective_ground_mu();
    assert!((mu - 0.46).abs() < 1e-6);
    // Rest penetration of a 1 kg particle: m g / k_ground.
    let z = -g / springs::GROUND_STIFFNESS;
    let x: Vec<Vec3> = (0..4).map(|i| Vec3::new(0.0, 0.1 * i as f32, z)).collect();
    let cfg = SimConfig {
        clamp_to_ground: false,
        ..SimConfig::default()
    };
    let bb = Backbone::new(&x, &[], params, cfg).unwrap();
    assert!(bb.springs().is_empty());
    let v0 = 1.0;
    let init = State {
        x: x.clone(),
        v: vec![Vec3::new(v0, 0.0, 0.0); 4],
    };
    let out = bb.rollout(&init, &Actions::without_grippers(6)).unwrap();
    let a = mu * g;
    for t in 1..=2 {
        let expected = v0 - a * 0.1 * t as f32;
        for v in &out.velocities[t] {
            assert!(
                (v.x - expected).abs() < 0.02 * v0,
                "t {t}: {} vs {expected}",
                v.x
            );
        }
    }
    let stop = v0 * v0 / (2.0 * a);
    for (p, q) in out.positions[5].iter().zip(&x) {
        assert!(
            (p.x - q.x - stop).abs() < 0.05 * stop,
            "slid {} vs {stop}",
            p.x - q.x
        );
        assert!(out.velocities[5][0].length() < 1e-6);
    }
}

/// Two 1 kg particles joined by one spring + dashpot: the relative coordinate is a damped
/// oscillator `mu d'' + c d' + k d = 0` with mu = 0.5 kg, solved in closed form.
fn two_body_error(k: f32, c: f32, substep: Substep, dashpot: Dashpot) -> f32 {
    let rest = 0.02;
    let x0 = vec![Vec3::ZERO, Vec3::new(rest, 0.0, 0.0)];
    let params = SpringParams {
        stiffness: k,
        damping: c,
        threshold: 0.03,
        max_springs: 4,
        ground_friction: 0.0,
    };
    let cfg = SimConfig {
        gravity: Vec3::ZERO,
        ground_z: None,
        substep,
        dashpot,
        ..SimConfig::default()
    };
    let bb = Backbone::new(&x0, &[], params, cfg).unwrap();
    let d0 = 0.004f64;
    let init = State {
        x: vec![Vec3::ZERO, Vec3::new(rest + d0 as f32, 0.0, 0.0)],
        v: vec![Vec3::ZERO; 2],
    };
    let out = bb.rollout(&init, &Actions::without_grippers(11)).unwrap();
    let (k, c, mu) = (f64::from(k), f64::from(c), 0.5f64);
    let disc = c * c - 4.0 * k * mu;
    let exact = |t: f64| -> f64 {
        if disc > 0.0 {
            let (s1, s2) = (
                (-c + disc.sqrt()) / (2.0 * mu),
                (-c - disc.sqrt()) / (2.0 * mu),
            );
            d0 * (s2 * (s1 * t).exp() - s1 * (s2 * t).exp()) / (s2 - s1)
        } else {
            let (a, w) = (c / (2.0 * mu), (-disc).sqrt() / (2.0 * mu));
            d0 * (-a * t).exp() * ((w * t).cos() + a / w * (w * t).sin())
        }
    };
    let mut worst = 0.0f64;
    for (t, x) in out.positions.iter().enumerate() {
        let d = f64::from(x[1].x - x[0].x) - f64::from(rest);
        worst = worst.max((d - exact(0.1 * t as f64)).abs() / d0);
    }
    worst as f32
}

#[test]
fn dashpot_matches_closed_form() {
    // Overdamped, the reference rope values (zeta 2.6): the implicit dashpot keeps the slow
    // creep right even though c dt / mu = 0.4 at the automatic substep.
    let e = two_body_error(17059.0, 480.0, Substep::AUTO, Dashpot::Implicit);
    assert!(e < 0.01, "overdamped error {e}");
    // Underdamped (zeta 0.07), slow enough that the substep resolves the oscillation.
    let e = two_body_error(100.0, 1.0, Substep::AUTO, Dashpot::Implicit);
    assert!(e < 0.02, "underdamped error {e}");
    // The reference's own substep converges to the same solution.
    let e = two_body_error(
        17059.0,
        480.0,
        Substep::Fixed { dt: 2e-5 },
        Dashpot::Implicit,
    );
    assert!(e < 1e-3, "reference-substep error {e}");
    // The reference's explicit dashpot at its substep, and at the automatic substep (which
    // the damping shortens), also match.
    let e = two_body_error(
        17059.0,
        480.0,
        Substep::Fixed { dt: 2e-5 },
        Dashpot::Explicit,
    );
    assert!(e < 1e-3, "explicit dashpot, reference substep: error {e}");
    let e = two_body_error(17059.0, 480.0, Substep::AUTO, Dashpot::Explicit);
    assert!(e < 0.01, "explicit dashpot, automatic substep: error {e}");
    let e = two_body_error(100.0, 1.0, Substep::AUTO, Dashpot::Explicit);
    assert!(e < 0.02, "explicit dashpot, underdamped: error {e}");
    let _ = ActionFrame {
        positions: &[],
        closed: &[],
    };
}
