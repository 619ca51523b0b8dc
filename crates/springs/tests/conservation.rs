//! Invariants of the internal dynamics: momentum, energy, rest, rigid-motion invariance.

mod common;

use glam::{Mat3, Vec3};
use proptest::prelude::*;
use springs::{Actions, Backbone, Dashpot, SimConfig, SpringParams, State, Substep};

/// A free object: no gravity, no ground, nothing held.
fn free_config() -> SimConfig {
    SimConfig {
        gravity: Vec3::ZERO,
        ground_z: None,
        ..SimConfig::default()
    }
}

fn params(stiffness: f32, damping: f32) -> SpringParams {
    SpringParams {
        stiffness,
        damping,
        threshold: 0.03,
        max_springs: 30,
        ground_friction: 0.3,
    }
}

/// A random blob at rest positions `x0` and a perturbed initial state.
fn scene(seed: u64, n: usize, pos_noise: f32, vel_noise: f32) -> (Vec<Vec3>, State) {
    let mut rng = common::Rng::new(seed);
    let x0 = common::blob(&mut rng, n, 0.03, Vec3::new(0.0, 0.0, 0.1));
    let x = x0.iter().map(|&p| p + rng.vec3(pos_noise)).collect();
    let v = (0..n).map(|_| rng.vec3(vel_noise)).collect();
    (x0, State { x, v })
}

fn dashpot(explicit: bool) -> Dashpot {
    if explicit {
        Dashpot::Explicit
    } else {
        Dashpot::Implicit
    }
}

fn momentum(v: &[Vec3]) -> glam::DVec3 {
    v.iter().map(|p| p.as_dvec3()).sum()
}

/// Kinetic + elastic energy, J (unit masses).
fn energy(bb: &Backbone, x: &[Vec3], v: &[Vec3]) -> f64 {
    let ke: f64 = v.iter().map(|p| 0.5 * f64::from(p.length_squared())).sum();
    ke + bb.elastic_energy(x).unwrap()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    #[test]
    fn momentum_is_conserved(seed in any::<u64>(), n in 2usize..60, k in 10f32..5e4, c in 0f32..1000.0,
                             explicit in any::<bool>(), partitions in 1u32..4) {
        let (x0, init) = scene(seed, n, 0.003, 0.5);
        let cfg = SimConfig { dashpot: dashpot(explicit), partitions, ..free_config() };
        let bb = Backbone::new(&x0, &[], params(k, c), cfg).unwrap();
        let out = bb.rollout(&init, &Actions::without_grippers(6)).unwrap();
        let p0 = momentum(&init.v);
        let scale: f64 = init.v.iter().map(|v| f64::from(v.length())).sum::<f64>() + 1e-3;
        for v in &out.velocities {
            let dp = (momentum(v) - p0).length();
            prop_assert!(dp <= 1e-4 * scale, "momentum drift {dp} (scale {scale})");
        }
    }

    /// The dashpot only removes energy; the one source is the integrator's own error, which
    /// grows with rotation per substep. Tolerance: each step may gain at most 1e-3 of the
    /// initial energy (docs/physics.md; over 400 random cases of this regime the largest gain
    /// measured was 4e-5).
    #[test]
    fn energy_does_not_increase(seed in any::<u64>(), n in 2usize..60, k in 10f32..5e4, c in 1f32..1000.0,
                                safety in 0.3f32..1.0, explicit in any::<bool>(), partitions in 1u32..4) {
        let (x0, init) = scene(seed, n, 0.003, 0.05);
        let cfg = SimConfig {
            substep: Substep::Auto { safety, max_dt: 2e-3 },
            dashpot: dashpot(explicit),
            partitions,
            ..free_config()
        };
        let bb = Backbone::new(&x0, &[], params(k, c), cfg).unwrap();
        let out = bb.rollout(&init, &Actions::without_grippers(8)).unwrap();
        let e0 = energy(&bb, &init.x, &init.v);
        let mut prev = e0;
        for (x, v) in out.positions.iter().zip(&out.velocities).skip(1) {
            let e = energy(&bb, x, v);
            prop_assert!(e <= prev + 1e-3 * e0, "energy rose from {prev} to {e} (initial {e0})");
            prev = e;
        }
        // And the dashpots do remove energy when there are springs to damp.
        if !bb.springs().is_empty() {
            prop_assert!(prev < e0, "no dissipation: {prev} vs {e0}");
        }
    }

    #[test]
    fn forces_are_invariant_to_rigid_motion(seed in any::<u64>(), n in 2usize..60, k in 10f32..5e4,
                                            c in 0f32..1000.0, axis in prop::array::uniform3(-1f32..1.0),
                                            angle in -3.1f32..3.1, shift in prop::array::uniform3(-2f32..2.0)) {
        let (x0, st) = scene(seed, n, 0.003, 0.3);
        let bb = Backbone::new(&x0, &[], params(k, c), free_config()).unwrap();
        let axis = Vec3::from(axis).try_normalize().unwrap_or(Vec3::Z);
        let rot = Mat3::from_axis_angle(axis, angle);
        let xr: Vec<Vec3> = st.x.iter().map(|&p| rot * p + Vec3::from(shift)).collect();
        let vr: Vec<Vec3> = st.v.iter().map(|&p| rot * p).collect();
        let (mut f, mut fr) = (vec![Vec3::ZERO; n], vec![Vec3::ZERO; n]);
        bb.spring_forces(&st.x, &st.v, &mut f).unwrap();
        bb.spring_forces(&xr, &vr, &mut fr).unwrap();
        let scale = f.iter().map(|p| p.length()).fold(1e-3, f32::max);
        for (a, b) in f.iter().zip(&fr) {
            prop_assert!((rot * *a - *b).length() <= 2e-3 * scale, "{a} rotated != {b}");
        }
        // Equal and opposite pair forces: the total internal force vanishes.
        let total: Vec3 = f.iter().sum();
        prop_assert!(total.length() <= 1e-4 * scale * n as f32);
    }
}

#[test]
fn structure_at_rest_stays_at_rest() {
    for seed in 0..4 {
        let mut rng = common::Rng::new(seed);
        let x0 = common::blob(&mut rng, 80, 0.03, Vec3::new(0.0, 0.0, 0.5));
        // Ground far below: present but never touched.
        let cfg = SimConfig {
            gravity: Vec3::ZERO,
            ..SimConfig::default()
        };
        let bb = Backbone::new(&x0, &[], SpringParams::reference_rope(), cfg).unwrap();
        assert!(bb.springs().len() > 100);
        let out = bb
            .rollout(&State::at_rest(x0.clone()), &Actions::without_grippers(5))
            .unwrap();
        for (x, v) in out.positions.iter().zip(&out.velocities) {
            assert_eq!(x, &x0, "positions moved");
            assert!(v.iter().all(|p| *p == Vec3::ZERO), "velocities not zero");
        }
    }
}

#[test]
fn rest_lengths_give_zero_force() {
    let x = common::lattice(4, 4, 4, 0.013, Vec3::new(0.1, -0.2, 0.3));
    let bb = Backbone::new(&x, &[], SpringParams::reference_rope(), free_config()).unwrap();
    let mut f = vec![Vec3::ONE; x.len()];
    bb.spring_forces(&x, &vec![Vec3::ZERO; x.len()], &mut f)
        .unwrap();
    assert!(f.iter().all(|p| *p == Vec3::ZERO));
    assert_eq!(bb.elastic_energy(&x).unwrap(), 0.0);
}
