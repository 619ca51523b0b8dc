//! The `twist` extra candidate (a cable's torsion between its clamped ends): a hanging loop
//! swung out of its plane swings less with it, motion in the loop's plane does not twist it,
//! nothing becomes NaN within the searched range, and an unclamped end releases it.

use std::sync::Arc;

use gap::forces::{BendingSprings, Twist};
use glam::Vec3;
use proptest::prelude::*;
use springs::{
    Actions, Backbone, BackboneOptions, Effect, SimConfig, SpringParams, State, Substep,
};

const N: usize = 31;
const MID: usize = N / 2;

/// A loop of `N` particles hanging up to 0.3 m below its two ends, 0.4 m apart, in the x–z
/// plane: it leaves its first end level, along the chord, and meets its last end nearly
/// vertically (z = 0.6 − 2.025 s² (1 − s) m at x = −0.2 + 0.4 s m). Swinging such a loop about
/// its chord twists it by about (1 − 0.2) times the angle (a loop whose end tangents are
/// equally inclined to the chord, e.g. a symmetric U, would not twist: the ends' twists
/// cancel). Particles 0, 1 are held by gripper 0, the last two by gripper 1.
fn hanging_loop() -> (Vec<Vec3>, Vec<i32>, Arc<[u32]>) {
    let x = (0..N)
        .map(|i| {
            let s = i as f32 / (N - 1) as f32;
            Vec3::new(-0.2 + 0.4 * s, 0.0, 0.6 - 2.025 * s * s * (1.0 - s))
        })
        .collect();
    let held = (0..N)
        .map(|i| match i {
            0 | 1 => 0,
            i if i >= N - 2 => 1,
            _ => -1,
        })
        .collect();
    (x, held, (0..N as u32).collect())
}

/// Springs to each particle's nearest neighbours: consecutive particles lie 1.4–6.4 cm apart
/// (closest where the loop is flattest), so the threshold reaches past the widest gap. Stiff
/// enough for the 10 g particles of [`swing`].
fn params() -> SpringParams {
    SpringParams {
        stiffness: 20000.0,
        damping: 0.01,
        threshold: 0.07,
        max_springs: 4,
        ground_friction: 0.4,
    }
}

/// The largest distance between the same particle in the same frame of two rollouts, m.
fn largest_distance(a: &[Vec<Vec3>], b: &[Vec<Vec3>]) -> f32 {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(p, q)| p.distance(*q))
        .fold(0.0, f32::max)
}

/// The loop with `effects`, rolled out for 3 s from rest with free particles moving at
/// `velocity` scaled by their depth below the chord (a swing), both grippers still and closed
/// unless `open_second`. Returns each frame's positions.
fn swing(effects: Vec<Box<dyn Effect>>, velocity: Vec3, open_second: bool) -> Vec<Vec<Vec3>> {
    let (x, held, chain) = hanging_loop();
    let params = params();
    // 10 g per particle, a 0.3 kg cable: its weight is then comparable to the bending and
    // torsion of relative stiffness 0.1–1 (GJ/L = κ_t k l̄³/L ≈ 0.4 κ_t N·m).
    let options = BackboneOptions {
        masses: Some(vec![0.01; N]),
        effects,
        chain: Some(chain),
        ..Default::default()
    };
    // One fixed substep for every model compared: the automatic one shortens with the
    // torsion's stability bound, and a different integration would differ on its own.
    let config = SimConfig {
        substep: Substep::Fixed { dt: 1e-4 },
        ..SimConfig::default()
    };
    let bb = Backbone::with_options(&x, &held, params, config, options).unwrap();
    let mut state = State::at_rest(x.clone());
    for (i, v) in state.v.iter_mut().enumerate() {
        if held[i] < 0 {
            *v = velocity * ((0.6 - x[i].z) / 0.3);
        }
    }
    let grippers = vec![(x[0] + x[1]) / 2.0, (x[N - 2] + x[N - 1]) / 2.0];
    let frames = 31;
    let actions = Actions::new(
        vec![grippers; frames],
        vec![vec![true, !open_second]; frames],
    )
    .unwrap();
    bb.rollout(&state, &actions).unwrap().positions
}

fn with_twist(kappa_t: f32) -> Vec<Box<dyn Effect>> {
    vec![
        Box::new(BendingSprings::new(0.2)),
        Box::new(Twist::new(kappa_t)),
    ]
}

/// The largest sideways (y) excursion of the loop's lowest particle.
fn sideways(frames: &[Vec<Vec3>]) -> f32 {
    frames.iter().map(|x| x[MID].y.abs()).fold(0.0, f32::max)
}

#[test]
fn the_loop_swings_less_out_of_its_plane_with_twist() {
    let push = Vec3::new(0.0, 0.5, 0.0);
    let free = sideways(&swing(with_twist(0.0), push, false));
    let stiff = sideways(&swing(with_twist(1.0), push, false));
    // Measured: 4.4 cm free, 3.1 cm with κ_t = 1 (GJ/L ≈ 0.5 N·m against the loop's 2.9 N
    // weight); at κ_t = 0.05 the largest excursion moves by a few per cent either way.
    assert!(free > 0.02, "the push should swing the loop: {free} m");
    assert!(stiff < 0.9 * free, "{free} / {stiff} m");
}

#[test]
fn motion_in_the_loop_s_plane_does_not_twist() {
    // Pushed along the chord: the loop stays in the x–z plane, a planar curve has no twist.
    let push = Vec3::new(0.4, 0.0, 0.3);
    let plain = swing(with_twist(0.0), push, false);
    let twisted = swing(with_twist(1.0), push, false);
    let diff = largest_distance(&plain, &twisted);
    assert!(diff < 1e-5, "{diff} m");
    assert!(sideways(&twisted) < 1e-5);
}

#[test]
fn an_open_gripper_releases_the_twist() {
    // With the far end free, the same push gives the same motion with and without twist.
    let push = Vec3::new(0.0, 0.5, 0.0);
    let plain = swing(with_twist(0.0), push, true);
    let twisted = swing(with_twist(1.0), push, true);
    let diff = largest_distance(&plain, &twisted);
    assert!(diff < 1e-6, "{diff} m");
}

#[test]
fn a_model_without_a_chain_is_an_error() {
    let (x, held, _) = hanging_loop();
    let params = params();
    let options = BackboneOptions {
        effects: vec![Box::new(Twist::new(0.1))],
        ..Default::default()
    };
    let err = Backbone::with_options(&x, &held, params, SimConfig::default(), options)
        .unwrap_err()
        .to_string();
    assert!(err.contains("chain"), "{err}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(16))]

    /// Anywhere in the searched range and for any push, the rollout stays finite.
    #[test]
    fn nothing_becomes_nan_in_range(
        log_kappa in (1e-3f32).ln()..0.0f32,
        vy in -2.0f32..2.0,
        vz in -1.0f32..1.0,
    ) {
        let frames = swing(with_twist(log_kappa.exp()), Vec3::new(0.2, vy, vz), false);
        prop_assert!(frames.iter().flatten().all(|p| p.is_finite()));
    }
}
