//! The `bending-damping` extra candidate (a chain's internal bending damping, applied
//! implicitly): its velocities solve `(M + dt C) v' = M v` with `C` built here from the
//! dissipation `½ c |d/dt curvature|²`; it conserves momentum, never adds kinetic energy, keeps
//! held particles' velocities, and takes the energy out of a bending vibration.

use std::sync::Arc;

use gap::forces::{BendingDamping, BendingSprings};
use glam::{Vec3, Vec3A};
use proptest::prelude::*;
use springs::{Backbone, BackboneOptions, Effect, ModelSetup, SimConfig, SpringParams, State};

fn params(stiffness: f32) -> SpringParams {
    SpringParams {
        stiffness,
        damping: 0.0,
        threshold: 0.025,
        max_springs: 8,
        ground_friction: 0.4,
    }
}

/// A chain of `n` particles with segments of about 2 cm, bent by `bend` (rad per joint), in
/// a shuffled index order so that the chain order, not the index order, has to be followed.
fn chain(n: usize, bend: &[f32]) -> (Vec<Vec3>, Arc<[u32]>) {
    let gcd = |mut a: usize, mut b: usize| {
        while b != 0 {
            (a, b) = (b, a % b);
        }
        a
    };
    let step = [7, 5, 11, 13]
        .into_iter()
        .find(|s| gcd(*s, n) == 1)
        .unwrap_or(1);
    let order: Vec<u32> = (0..n).map(|i| ((i * step + 3) % n) as u32).collect();
    let mut x = vec![Vec3::ZERO; n];
    let (mut p, mut angle) = (Vec3::new(0.0, 0.0, 0.5), 0.0f32);
    for (k, &i) in order.iter().enumerate() {
        x[i as usize] = p;
        angle += bend.get(k).copied().unwrap_or(0.0);
        p += 0.02 * (1.0 + 0.1 * (k % 3) as f32) * Vec3::new(angle.cos(), 0.0, angle.sin());
    }
    (x, order.into())
}

/// The damping of time `tau` set up on `rest` along `order` with masses `masses`.
fn set_up(rest: &[Vec3], order: &Arc<[u32]>, masses: &mut [f32], tau: f32) -> BendingDamping {
    let held = vec![-1; rest.len()];
    let p = params(1000.0);
    let mut rest_lengths = Vec::new();
    let mut stiffness = Vec::new();
    let mut damping = Vec::new();
    let mut effect = BendingDamping::new(tau);
    effect
        .setup(&mut ModelSetup {
            rest_positions: rest,
            held: &held,
            params: &p,
            springs: &[],
            rest_lengths: &mut rest_lengths,
            stiffness: &mut stiffness,
            damping: &mut damping,
            masses,
            chain: Some(order),
        })
        .unwrap();
    effect
}

/// `C v` for the dissipation `½ c Σ |s·v|²` over consecutive triplets of `order`, written
/// from the formula: s = (1/l₁, −1/l₁ − 1/l₂, 1/l₂), c = τ k l̄² (k = 1000 N/m).
fn damping_times(rest: &[Vec3], order: &[u32], tau: f32, v: &[Vec3A]) -> Vec<Vec3A> {
    let len = |a: u32, b: u32| f64::from(rest[a as usize].distance(rest[b as usize]));
    let mean = order.windows(2).map(|w| len(w[0], w[1])).sum::<f64>() / (order.len() - 1) as f64;
    let c = f64::from(tau) * 1000.0 * mean * mean;
    let mut out = vec![Vec3A::ZERO; v.len()];
    for w in order.windows(3) {
        let (i1, i2) = (1.0 / len(w[0], w[1]), 1.0 / len(w[1], w[2]));
        let s = [i1, -(i1 + i2), i2];
        let rate: Vec3A = (0..3).map(|k| v[w[k] as usize] * s[k] as f32).sum();
        for k in 0..3 {
            out[w[k] as usize] += rate * (c * s[k]) as f32;
        }
    }
    out
}

fn momentum(m: &[f32], v: &[Vec3A]) -> Vec3A {
    m.iter().zip(v).map(|(m, v)| *v * *m).sum()
}

fn kinetic(m: &[f32], v: &[Vec3A]) -> f32 {
    m.iter()
        .zip(v)
        .map(|(m, v)| 0.5 * m * v.length_squared())
        .sum()
}

#[test]
fn the_velocities_solve_the_implicit_system() {
    let n = 15;
    let bend: Vec<f32> = (0..n).map(|k| 0.3 * (k as f32 * 0.7).sin()).collect();
    let (rest, order) = chain(n, &bend);
    let mut masses: Vec<f32> = (0..n).map(|i| 0.5 + 0.1 * i as f32).collect();
    let tau = 0.02;
    let effect = set_up(&rest, &order, &mut masses, tau);
    let inv: Vec<f32> = masses.iter().map(|m| 1.0 / m).collect();
    let v0: Vec<Vec3A> = (0..n)
        .map(|i| {
            Vec3A::new(
                (i as f32).sin(),
                (i as f32 * 1.3).cos(),
                0.2 * i as f32 - 1.0,
            )
        })
        .collect();
    let dt = 1e-3;
    let mut v = v0.clone();
    effect.damp_velocities(dt, &inv, &mut v);
    let cv = damping_times(&rest, &order, tau, &v);
    for i in 0..n {
        let residual = (v[i] - v0[i]) * masses[i] + cv[i] * dt;
        assert!(
            residual.length() < 1e-4,
            "particle {i}: residual {residual}"
        );
    }
    // It did damp something: the system is not the identity here.
    assert!(kinetic(&masses, &v) < 0.99 * kinetic(&masses, &v0));
}

#[test]
fn held_particles_keep_their_velocities_and_bound_the_rest() {
    let n = 10;
    let (rest, order) = chain(n, &[0.2; 10]);
    let mut masses = vec![1.0; n];
    let tau = 0.05;
    let effect = set_up(&rest, &order, &mut masses, tau);
    let held = [order[0] as usize, order[1] as usize, order[n - 1] as usize];
    let inv: Vec<f32> = (0..n)
        .map(|i| if held.contains(&i) { 0.0 } else { 1.0 })
        .collect();
    let v0: Vec<Vec3A> = (0..n)
        .map(|i| Vec3A::new(0.3 * i as f32, -0.1, (i as f32).cos()))
        .collect();
    let mut v = v0.clone();
    effect.damp_velocities(1e-3, &inv, &mut v);
    let cv = damping_times(&rest, &order, tau, &v);
    for i in 0..n {
        if held.contains(&i) {
            assert_eq!(v[i], v0[i]);
        } else {
            let residual = v[i] - v0[i] + cv[i] * 1e-3;
            assert!(
                residual.length() < 1e-4,
                "particle {i}: residual {residual}"
            );
        }
    }
}

/// The factored system is kept between calls: every call must still solve its own system,
/// whether the held particles, the substep or the chain change between calls.
#[test]
fn repeated_calls_solve_their_own_systems() {
    let (rest_a, order_a) = chain(12, &[0.3; 12]);
    let (rest_b, order_b) = chain(9, &[-0.5; 9]);
    let mut masses_a: Vec<f32> = (0..12).map(|i| 1.0 + 0.05 * i as f32).collect();
    let mut masses_b = vec![2.0; 9];
    let (tau_a, tau_b) = (0.03, 0.01);
    let a = set_up(&rest_a, &order_a, &mut masses_a, tau_a);
    let b = set_up(&rest_b, &order_b, &mut masses_b, tau_b);
    for round in 0..6 {
        let (effect, rest, order, masses, tau) = if round % 3 == 2 {
            (&b, &rest_b, &order_b, &masses_b, tau_b)
        } else {
            (&a, &rest_a, &order_a, &masses_a, tau_a)
        };
        let n = masses.len();
        // Rounds 0 and 1 differ only in the held particle, 3 and 4 only in the substep.
        let held = order[if round == 1 { 2 } else { 0 }] as usize;
        let dt = if round == 4 { 2e-3 } else { 1e-3 };
        let inv: Vec<f32> = (0..n)
            .map(|i| if i == held { 0.0 } else { 1.0 / masses[i] })
            .collect();
        let v0: Vec<Vec3A> = (0..n)
            .map(|i| Vec3A::new((i + round) as f32 * 0.1, -0.2, (i as f32).sin()))
            .collect();
        let mut v = v0.clone();
        effect.damp_velocities(dt, &inv, &mut v);
        let cv = damping_times(rest, order, tau, &v);
        for i in 0..n {
            if i == held {
                assert_eq!(v[i], v0[i], "round {round}");
            } else {
                let residual = (v[i] - v0[i]) * masses[i] + cv[i] * dt;
                assert!(
                    residual.length() < 1e-4,
                    "round {round}, particle {i}: {residual}"
                );
            }
        }
    }
}

#[test]
fn a_model_without_a_chain_is_an_error() {
    let rest = vec![Vec3::ZERO, Vec3::X * 0.02, Vec3::X * 0.04];
    let held = vec![-1; 3];
    let options = BackboneOptions {
        effects: vec![Box::new(BendingDamping::new(0.01))],
        ..Default::default()
    };
    let err = Backbone::with_options(&rest, &held, params(1000.0), SimConfig::default(), options)
        .unwrap_err();
    assert!(err.to_string().contains("chain"), "{err}");
}

/// The largest transverse kinetic energy over the second half second of a straight chain
/// (bending κ = 0.5, both ends held, no gravity) started in its first bending mode, with
/// bending damping of time `tau`.
fn late_vibration_energy(tau: f32) -> f32 {
    let n = 16;
    let (rest, order) = chain(n, &[]);
    let mut held = vec![-1; n];
    held[order[0] as usize] = 0;
    held[order[n - 1] as usize] = 1;
    let config = SimConfig {
        gravity: Vec3::ZERO,
        step_dt: 0.01,
        ..SimConfig::default()
    };
    let options = BackboneOptions {
        effects: vec![
            Box::new(BendingSprings::new(0.5)),
            Box::new(BendingDamping::new(tau)),
        ],
        chain: Some(order.clone()),
        ..Default::default()
    };
    let bb = Backbone::with_options(&rest, &held, params(1e5), config, options).unwrap();
    let mut state = State::at_rest(rest.clone());
    for (k, &i) in order.iter().enumerate() {
        let s = (std::f32::consts::PI * k as f32 / (n - 1) as f32).sin();
        state.v[i as usize] = Vec3::Z * 0.1 * s;
    }
    let grippers = [rest[order[0] as usize], rest[order[n - 1] as usize]];
    let frame = springs::ActionFrame {
        positions: &grippers,
        closed: &[true, true],
    };
    let mut scratch = bb.scratch();
    let mut late = 0.0f32;
    for step in 0..100 {
        bb.step(&mut state, frame, frame, &mut scratch).unwrap();
        let energy: f32 = state.v.iter().map(|v| 0.5 * v.z * v.z).sum();
        if step >= 50 {
            late = late.max(energy);
        }
    }
    late
}

#[test]
fn it_takes_the_energy_out_of_a_bending_vibration() {
    let free = late_vibration_energy(0.0);
    let damped = late_vibration_energy(0.05);
    // Started with 0.5 Σ (0.1 sin)² ≈ 0.04 J.
    assert!(free > 0.02, "the undamped chain keeps vibrating: {free}");
    assert!(damped < 0.3 * free, "damped {damped} vs undamped {free}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Momentum is conserved and kinetic energy never grows, for any chain shape, masses,
    /// velocities, damping time in the candidate's range and substep.
    #[test]
    fn it_conserves_momentum_and_never_adds_energy(
        n in 3usize..24,
        bend in proptest::collection::vec(-1.0f32..1.0, 24),
        m in proptest::collection::vec(0.2f32..5.0, 24),
        vel in proptest::collection::vec(-2.0f32..2.0, 72),
        log_tau in -5.0f32..-0.5,
        log_dt in -6.0f32..-2.0,
    ) {
        let (rest, order) = chain(n, &bend);
        let mut masses = m[..n].to_vec();
        let effect = set_up(&rest, &order, &mut masses, 10f32.powf(log_tau));
        let inv: Vec<f32> = masses.iter().map(|m| 1.0 / m).collect();
        let v0: Vec<Vec3A> = (0..n).map(|i| Vec3A::new(vel[3 * i], vel[3 * i + 1], vel[3 * i + 2])).collect();
        let mut v = v0.clone();
        effect.damp_velocities(10f32.powf(log_dt), &inv, &mut v);
        prop_assert!(v.iter().all(|v| v.is_finite()));
        let (p0, p1) = (momentum(&masses, &v0), momentum(&masses, &v));
        prop_assert!((p1 - p0).length() <= 1e-3 * (1.0 + p0.length()), "momentum {p0} -> {p1}");
        let (e0, e1) = (kinetic(&masses, &v0), kinetic(&masses, &v));
        prop_assert!(e1 <= e0 * (1.0 + 1e-5) + 1e-7, "kinetic energy {e0} -> {e1}");
    }
}
