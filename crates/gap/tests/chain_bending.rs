//! The `bending` candidate on a chain (`BackboneOptions::chain`, a DEFORM cable's order along
//! it): a curvature energy that is zero on a straight chain, linear in the bend, and exerts no
//! net force or torque.

use std::sync::Arc;

use gap::forces::BendingSprings;
use glam::{Vec3, Vec3A};
use springs::{
    Backbone, BackboneOptions, Effect, ModelSetup, SimConfig, SpringParams, SubstepContext,
};

const N: usize = 12;

fn params() -> SpringParams {
    SpringParams {
        stiffness: 1000.0,
        damping: 0.0,
        threshold: 0.025,
        max_springs: 8,
        ground_friction: 0.4,
    }
}

/// A chain along x with 2 cm segments, stored in a shuffled index order so that the chain
/// order, not the index order, has to be followed.
fn straight() -> (Vec<Vec3>, Arc<[u32]>) {
    let order: Vec<u32> = (0..N as u32).map(|i| (i * 5) % N as u32).collect();
    let mut x = vec![Vec3::ZERO; N];
    for (k, &p) in order.iter().enumerate() {
        x[p as usize] = Vec3::new(0.02 * k as f32, 0.0, 0.5);
    }
    (x, order.into())
}

/// The chain-form bending (κ = 0.5) set up on `rest` along `order`, with a plain backbone.
fn set_up(rest: &[Vec3], order: &Arc<[u32]>) -> (Backbone, BendingSprings) {
    let held = vec![-1; rest.len()];
    let p = params();
    let bb =
        Backbone::with_options(rest, &held, p, SimConfig::default(), Default::default()).unwrap();
    let springs = bb.springs().to_vec();
    let mut rest_lengths = bb.rest_lengths().to_vec();
    let mut stiffness = vec![p.stiffness; springs.len()];
    let mut damping = vec![p.damping; springs.len()];
    let mut masses = vec![1.0; rest.len()];
    let mut bending = BendingSprings::new(0.5);
    bending
        .setup(&mut ModelSetup {
            rest_positions: rest,
            held: &held,
            params: &p,
            springs: &springs,
            rest_lengths: &mut rest_lengths,
            stiffness: &mut stiffness,
            damping: &mut damping,
            masses: &mut masses,
            chain: Some(order),
        })
        .unwrap();
    (bb, bending)
}

/// Forces of the chain-form bending at positions `at`, the chain built from `rest`.
fn forces(rest: &[Vec3], order: &Arc<[u32]>, at: &[Vec3]) -> Vec<Vec3A> {
    let (bb, bending) = set_up(rest, order);
    let x: Vec<Vec3A> = at.iter().map(|p| Vec3A::from(*p)).collect();
    let v = vec![Vec3A::ZERO; x.len()];
    let ctx = SubstepContext {
        backbone: &bb,
        dt: 1e-4,
        substep: 0,
        x: &x,
        v: &v,
        grippers: &[],
        gripper_velocities: &[],
        closed: &[],
    };
    let mut f = vec![Vec3A::ZERO; x.len()];
    bending.add_forces(&ctx, &mut (), bb.rest_lengths(), &mut f);
    f
}

/// Each particle's row of the stability bound the chain-form bending adds.
fn stability_rows(rest: &[Vec3], order: &Arc<[u32]>) -> Vec<f32> {
    let (bb, bending) = set_up(rest, order);
    let (mut row, mut damping) = (vec![0.0; rest.len()], vec![0.0; rest.len()]);
    bending.stability(&bb, &mut row, &mut damping);
    row
}

/// The straight chain with the particle `k`-th along it lifted by `h` metres.
fn kinked(x: &[Vec3], order: &[u32], k: usize, h: f32) -> Vec<Vec3> {
    let mut y = x.to_vec();
    y[order[k] as usize].z += h;
    y
}

#[test]
fn a_straight_chain_feels_no_bending_force() {
    let (x, order) = straight();
    // Rest shape straight, and also a straight chain rotated away from its rest direction.
    for f in forces(&x, &order, &x) {
        assert!(f.length() < 1e-6, "{f}");
    }
    let turned: Vec<Vec3> = x.iter().map(|p| Vec3::new(0.0, p.x, 0.5 + p.x)).collect();
    for f in forces(&x, &order, &turned) {
        assert!(f.length() < 1e-3, "{f}");
    }
}

#[test]
fn a_bent_chain_is_pushed_back_straight_without_net_force_or_torque() {
    let (x, order) = straight();
    let y = kinked(&x, &order, 5, 0.004);
    let f = forces(&x, &order, &y);
    let lifted = order[5] as usize;
    assert!(
        f[lifted].z < -1.0,
        "the lifted particle is pushed down: {}",
        f[lifted]
    );
    for k in [4, 6] {
        let p = order[k] as usize;
        assert!(f[p].z > 0.0, "its neighbours are pulled up: {}", f[p]);
    }
    let net: Vec3A = f.iter().copied().sum();
    let torque: Vec3A = y
        .iter()
        .zip(&f)
        .map(|(p, f)| Vec3A::from(*p).cross(*f))
        .sum();
    let scale: f32 = f.iter().map(|f| f.length()).sum();
    assert!(net.length() < 1e-5 * scale, "net force {net}");
    assert!(torque.length() < 1e-5 * scale, "net torque {torque}");
}

#[test]
fn the_bending_force_is_linear_in_the_bend() {
    let (x, order) = straight();
    let p = order[7] as usize;
    let f1 = forces(&x, &order, &kinked(&x, &order, 7, 0.002))[p];
    let f2 = forces(&x, &order, &kinked(&x, &order, 7, 0.004))[p];
    assert!((f2 - 2.0 * f1).length() < 1e-3 * f2.length(), "{f1} {f2}");
    // κ k l̄² = 0.5 · 1000 N/m · (0.02 m)² = 0.2 N·m, and a lift h of one particle of a
    // uniform chain changes the two tangent differences next to it by h/l and the one at
    // it by −2h/l: the force on it is k_b (1 + 4 + 1) h / l² (straight rest).
    let expected = 0.2 * 6.0 * 0.004 / (0.02 * 0.02);
    assert!(
        (f2.z + expected).abs() < 1e-3 * expected,
        "{} vs -{expected}",
        f2.z
    );
}

#[test]
fn a_chain_order_naming_a_missing_or_repeated_particle_is_an_error() {
    let (x, _) = straight();
    let held = vec![-1; x.len()];
    for bad in [vec![0u32, 1, 99], vec![0u32, 1, 1]] {
        let options = BackboneOptions {
            chain: Some(bad.into()),
            ..Default::default()
        };
        let err = Backbone::with_options(&x, &held, params(), SimConfig::default(), options);
        assert!(err.is_err());
    }
}

#[test]
fn a_chain_collapsed_to_a_point_adds_no_force_and_a_finite_stability_bound() {
    let (_, order) = straight();
    let x = vec![Vec3::new(0.1, 0.2, 0.3); N];
    for f in forces(&x, &order, &x) {
        assert_eq!(f, Vec3A::ZERO);
    }
    let mut y = x.clone();
    y[3].z += 0.01;
    for f in forces(&x, &order, &y) {
        assert!(f.is_finite() && f.length() < 1e-6, "{f}");
    }
    assert!(stability_rows(&x, &order).iter().all(|r| *r == 0.0));
    // A straight chain's rows are positive and finite: the bound sees the curvature term.
    let (x, order) = straight();
    assert!(
        stability_rows(&x, &order)
            .iter()
            .all(|r| r.is_finite() && *r > 0.0)
    );
}
