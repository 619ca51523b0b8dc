//! The material laws' composition with bending: a stiffness field and a spring law.

use std::sync::Arc;

use gap::forces::{BendingSprings, StiffnessGradient};
use gap::{BaseEffect, MaterialFrame};
use glam::{Vec3, Vec3A};
use springs::{
    Backbone, BackboneOptions, Effect, ModelSetup, SimConfig, SpringParams, SubstepContext,
};

/// A 10 x 2 strip, 1 cm apart, and its backbone parameters.
fn strip() -> (Vec<Vec3>, SpringParams) {
    let x = (0..20)
        .map(|i| Vec3::new(0.01 * (i / 2) as f32, 0.01 * (i % 2) as f32, 0.1))
        .collect();
    let params = SpringParams {
        stiffness: 1000.0,
        damping: 1.0,
        threshold: 0.015,
        max_springs: 8,
        ground_friction: 0.5,
    };
    (x, params)
}

/// The strip's plain backbone, and its rest lengths and spring stiffness (N/m) after `effects`
/// are set up on it in order.
fn set_up(
    effects: &mut [Box<dyn Effect>],
    x: &[Vec3],
    params: SpringParams,
) -> (Backbone, Vec<f32>, Vec<f32>) {
    let held = vec![-1; x.len()];
    let bb = Backbone::with_options(
        x,
        &held,
        params,
        SimConfig::default(),
        BackboneOptions::default(),
    )
    .unwrap();
    let springs: Vec<[u32; 2]> = bb.springs().to_vec();
    let mut rest: Vec<f32> = bb.rest_lengths().to_vec();
    let mut stiffness = vec![params.stiffness; springs.len()];
    let mut damping = vec![params.damping; springs.len()];
    let mut masses = vec![0.01; x.len()];
    for e in effects.iter_mut() {
        e.setup(&mut ModelSetup {
            rest_positions: x,
            held: &held,
            params: &params,
            springs: &springs,
            rest_lengths: &mut rest,
            stiffness: &mut stiffness,
            damping: &mut damping,
            masses: &mut masses,
            chain: None,
        })
        .unwrap();
    }
    (bb, rest, stiffness)
}

/// Each particle's bending row in the stability bound after `effects` are set up in order.
fn bending_rows(effects: &mut [Box<dyn Effect>], bending_at: usize) -> Vec<f32> {
    let (x, params) = strip();
    let (bb, _, _) = set_up(effects, &x, params);
    let (mut row, mut d) = (vec![0.0; x.len()], vec![0.0; x.len()]);
    effects[bending_at].stability(&bb, &mut row, &mut d);
    row
}

#[test]
fn bending_follows_a_stiffness_field_set_up_before_it() {
    let u: Vec<f32> = (0..20).map(|i| (i / 2) as f32 / 4.5 - 1.0).collect();
    let field = |slope| -> Box<dyn Effect> {
        Box::new(StiffnessGradient {
            slope,
            material: Arc::new(u.clone()),
            lag_slope: 0.0,
            lag: None,
        })
    };
    let plain = bending_rows(&mut [Box::new(BendingSprings::new(0.2))], 0);
    // Neutral field: every factor exactly 1, the same bending bit for bit.
    let neutral = bending_rows(&mut [field(0.0), Box::new(BendingSprings::new(0.2))], 1);
    assert_eq!(plain, neutral);
    // A field that softens the high-u end and stiffens the low-u end by e^8 at the extremes:
    // the bending there follows it, by orders of magnitude both ways.
    let graded = bending_rows(&mut [field(-8.0), Box::new(BendingSprings::new(0.2))], 1);
    assert!(
        graded[19] < 1e-2 * plain[19],
        "{} vs {}",
        graded[19],
        plain[19]
    );
    assert!(graded[0] > 1e2 * plain[0], "{} vs {}", graded[0], plain[0]);
    // Set up after the bending springs, the field does not reach them.
    let late = bending_rows(&mut [Box::new(BendingSprings::new(0.2)), field(-8.0)], 0);
    assert_eq!(plain, late);
}

#[test]
fn compositions_set_the_stiffness_field_up_first() {
    let (x, _) = strip();
    let frame = MaterialFrame::new(&x, Vec3::ZERO).unwrap();
    let effects =
        BaseEffect::parse_list("bending=0.1,drag=0.2,stiffness-heterogeneity=-1.5").unwrap();
    let names: Vec<String> = gap::backbone_options(&effects, &frame)
        .effects
        .iter()
        .map(|e| e.name().to_string())
        .collect();
    assert_eq!(names, ["stiffness-heterogeneity", "bending", "drag"]);
}

/// The bending springs' forces (N) on the strip scaled uniformly by `stretch` about its first
/// particle, built from the base-effect list `list` (set up in the composition's order).
fn bending_forces(list: &str, stretch: f32) -> (Vec<Vec3A>, Vec<f32>) {
    let (x, params) = strip();
    let frame = MaterialFrame::new(&x, Vec3::ZERO).unwrap();
    let mut effects = gap::backbone_options(&BaseEffect::parse_list(list).unwrap(), &frame).effects;
    let (bb, rest, _) = set_up(&mut effects, &x, params);
    let bending = effects.iter().find(|e| e.name() == "bending").unwrap();
    let moved: Vec<Vec3A> = x
        .iter()
        .map(|p| Vec3A::from(x[0] + (*p - x[0]) * stretch))
        .collect();
    let still = vec![Vec3A::ZERO; x.len()];
    let ctx = SubstepContext {
        backbone: &bb,
        dt: 1e-4,
        substep: 0,
        x: &moved,
        v: &still,
        grippers: &[],
        gripper_velocities: &[],
        closed: &[],
    };
    let mut force = vec![Vec3A::ZERO; x.len()];
    bending.add_forces(&ctx, &mut *bending.new_state(&bb), &rest, &mut force);
    let (mut row, mut d) = (vec![0.0; x.len()], vec![0.0; x.len()]);
    bending.stability(&bb, &mut row, &mut d);
    (force, row)
}

/// Whether `a ≈ r b` component-wise, relative to the largest force.
fn scaled(a: &[Vec3A], b: &[Vec3A], r: f32) -> bool {
    let top = b.iter().map(|f| f.length()).fold(0.0, f32::max);
    top > 0.0
        && a.iter()
            .zip(b)
            .all(|(p, q)| (*p - *q * r).length() <= 1e-4 * top * r.max(1.0))
}

#[test]
fn bending_follows_the_compositions_spring_law() {
    // Compressed by 2 %: the bending springs soften to the law's compression ratio.
    let (plain, plain_row) = bending_forces("bending=0.2", 0.98);
    let (soft, soft_row) = bending_forces("bending=0.2,nonlinear-elasticity=100:0.05", 0.98);
    assert!(
        scaled(&soft, &plain, 0.05),
        "{:?} vs {:?}",
        soft[19],
        plain[19]
    );
    // Stretched by 3 % (every pair at strain 0.03): they stiffen by 1 + β ε².
    let (plain_t, _) = bending_forces("bending=0.2", 1.03);
    let (stiff, _) = bending_forces("bending=0.2,nonlinear-elasticity=100:0.05", 1.03);
    assert!(scaled(&stiff, &plain_t, 1.0 + 100.0 * 0.03 * 0.03));
    // Their stability rows carry the law's largest tangent stiffness, 1 + 3 β ε_max².
    let tangent = 1.0 + 3.0 * 100.0 * gap::forces::STIFFENING_MAX_STRAIN.powi(2);
    for (s, p) in soft_row.iter().zip(&plain_row) {
        assert!((s - tangent * p).abs() <= 1e-5 * tangent * p, "{s} vs {p}");
    }
    // At ratio 1 the compressed springs are linear, bit for bit.
    let (linear, _) = bending_forces("bending=0.2,nonlinear-elasticity=1:1", 0.98);
    assert_eq!(linear, plain);
}

/// The strip's spring stiffness (N/m) and springs after `field` is set up on it.
fn field_stiffness(field: StiffnessGradient) -> (Vec<f32>, Vec<[u32; 2]>) {
    let (x, params) = strip();
    let (bb, _, stiffness) = set_up(&mut [Box::new(field)], &x, params);
    (stiffness, bb.springs().to_vec())
}

#[test]
fn the_lag_term_softens_the_trailing_part_and_keeps_the_rigid_part_at_the_fitted_stiffness() {
    let u: Vec<f32> = (0..20).map(|i| (i / 2) as f32 / 4.5 - 1.0).collect();
    // Lag −1 on the first column pair (moves with the grippers), +1 on the last.
    let lag = Arc::new(u.clone());
    let field = |lag_slope, lag: Option<Arc<Vec<f32>>>| StiffnessGradient {
        slope: 0.0,
        material: Arc::new(u.clone()),
        lag_slope,
        lag,
    };
    let (plain, springs) = field_stiffness(field(0.0, None));
    assert!(plain.iter().all(|k| *k == 1000.0));
    // A zero lag slope, or no lag coordinate, leaves every spring as it was, bit for bit.
    assert_eq!(field_stiffness(field(0.0, Some(lag.clone()))).0, plain);
    assert_eq!(field_stiffness(field(-4.0, None)).0, plain);
    // e = −4: factor exp(−4 λ̄ − 4), 1 where λ̄ = −1 and e^−8 where λ̄ = +1.
    let (soft, _) = field_stiffness(field(-4.0, Some(lag.clone())));
    for (k, [a, b]) in soft.iter().zip(&springs) {
        let mean = 0.5 * (u[*a as usize] + u[*b as usize]);
        let want = 1000.0 * (-4.0 * mean - 4.0f32).exp();
        assert!(
            (k - want).abs() <= 1e-4 * want,
            "spring {a}-{b}: {k} vs {want}"
        );
    }
    let rigid = springs
        .iter()
        .position(|[a, b]| u[*a as usize] == -1.0 && u[*b as usize] == -1.0)
        .unwrap();
    assert_eq!(soft[rigid], 1000.0);
    // The opposite sign softens the rigid end instead, the trailing end keeping k.
    let (stiff_trail, _) = field_stiffness(field(4.0, Some(lag)));
    let trailing = springs
        .iter()
        .position(|[a, b]| u[*a as usize] == 1.0 && u[*b as usize] == 1.0)
        .unwrap();
    assert_eq!(stiff_trail[trailing], 1000.0);
    assert!(stiff_trail[rigid] < 1e-3 * 1000.0);
}

#[test]
fn the_lag_field_is_set_up_before_the_bending_it_scales() {
    let (x, _) = strip();
    let lag: Vec<f32> = (0..20).map(|i| (i / 2) as f32 / 4.5 - 1.0).collect();
    let frame = MaterialFrame::new(&x, Vec3::ZERO)
        .unwrap()
        .with_lag(Some(lag));
    let effects = BaseEffect::parse_list("bending=0.1,stiffness-lag=-3").unwrap();
    let names: Vec<String> = gap::backbone_options(&effects, &frame)
        .effects
        .iter()
        .map(|e| e.name().to_string())
        .collect();
    assert_eq!(names, ["stiffness-lag", "bending"]);
    // The lag slope's range: e^20 at most between the two ends.
    assert!(BaseEffect::parse_list("stiffness-lag=-10").is_ok());
    assert!(BaseEffect::parse_list("stiffness-lag=-10.5").is_err());
}
