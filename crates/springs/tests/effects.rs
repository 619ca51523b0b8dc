//! The effect extension point: the built-in `AirDrag`, and small effects written here that use
//! every hook (setup, stability, per-rollout state, actions, forces, rest lengths, friction,
//! compliant grasp).

mod common;

use std::any::Any;

use glam::{Vec3, Vec3A};
use springs::{
    Actions, AirDrag, Backbone, BackboneOptions, Effect, GroundContact, ModelSetup, SimConfig,
    SimError, SpringParams, State, Substep, SubstepContext,
};

fn with(effects: Vec<Box<dyn Effect>>) -> BackboneOptions {
    BackboneOptions {
        masses: None,
        effects,
        ..Default::default()
    }
}

fn free() -> SimConfig {
    SimConfig {
        gravity: Vec3::ZERO,
        ground_z: None,
        ..SimConfig::default()
    }
}

#[test]
fn air_drag_decays_velocity_exponentially() {
    // Two far-apart particles (no springs) coasting at 1 m/s: v(t) = exp(-c t / m).
    let x = vec![Vec3::ZERO, Vec3::X];
    let c = 2.0;
    let cfg = SimConfig {
        substep: Substep::Fixed { dt: 1e-3 },
        ..free()
    };
    let bb = Backbone::with_options(
        &x,
        &[],
        SpringParams::reference_rope(),
        cfg,
        with(vec![Box::new(AirDrag { coefficient: c })]),
    )
    .unwrap();
    let init = State {
        x,
        v: vec![Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, -1.0, 0.0)],
    };
    let out = bb.rollout(&init, &Actions::without_grippers(6)).unwrap();
    for (t, v) in out.velocities.iter().enumerate() {
        let expected = (-c * 0.1 * t as f32).exp();
        assert!(
            (v[0].length() - expected).abs() < 2e-3 * expected,
            "t {t}: {} vs {expected}",
            v[0].length()
        );
    }
}

#[test]
fn effects_report_their_stiffness_to_the_bound() {
    let x = vec![Vec3::ZERO];
    let p = SpringParams::reference_rope();
    // Very strong drag: the automatic substep shrinks to keep explicit drag stable ...
    let drag = || {
        with(vec![
            Box::new(AirDrag { coefficient: 1e4 }) as Box<dyn Effect>
        ])
    };
    let bb = Backbone::with_options(&x, &[], p, free(), drag()).unwrap();
    assert!(bb.stable_dt() <= 2.0 / 1e4 * 1.0001);
    let init = State {
        x: x.clone(),
        v: vec![Vec3::X],
    };
    let out = bb.rollout(&init, &Actions::without_grippers(3)).unwrap();
    assert!(out.velocities[2][0].length() < 1e-6);
    // ... while ignoring the bound blows up, and is reported as an error.
    let fixed = SimConfig {
        substep: Substep::Fixed { dt: 1e-3 },
        ..free()
    };
    let bb = Backbone::with_options(&x, &[], p, fixed, drag()).unwrap();
    assert!(matches!(
        bb.rollout(&init, &Actions::without_grippers(3)),
        Err(SimError::Diverged { .. })
    ));
    // Bad effect parameters are rejected at construction.
    let bad = with(vec![Box::new(AirDrag { coefficient: -1.0 })]);
    assert!(matches!(
        Backbone::with_options(&x, &[], p, free(), bad),
        Err(SimError::Effect { .. })
    ));
}

/// Stiffness heterogeneity: springs above `z_split` are `factor` times stiffer.
#[derive(Debug)]
struct StiffTop {
    z_split: f32,
    factor: f32,
}

impl Effect for StiffTop {
    fn name(&self) -> &str {
        "stiff-top"
    }
    fn setup(&mut self, m: &mut ModelSetup<'_>) -> Result<(), SimError> {
        for (k, &[a, b]) in m.stiffness.iter_mut().zip(m.springs) {
            let mid = 0.5 * (m.rest_positions[a as usize] + m.rest_positions[b as usize]);
            if mid.z > self.z_split {
                *k *= self.factor;
            }
        }
        Ok(())
    }
}

#[test]
fn setup_can_make_stiffness_heterogeneous() {
    let x = common::lattice(3, 3, 4, 0.01, Vec3::ZERO);
    let p = SpringParams {
        threshold: 0.015,
        ..SpringParams::reference_rope()
    };
    let plain = Backbone::new(&x, &[], p, free()).unwrap();
    let eff = with(vec![Box::new(StiffTop {
        z_split: 0.015,
        factor: 4.0,
    })]);
    let bb = Backbone::with_options(&x, &[], p, free(), eff).unwrap();
    for ((k, &[a, b]), &k0) in bb
        .stiffness()
        .iter()
        .zip(bb.springs())
        .zip(plain.stiffness())
    {
        let top = x[a as usize].z + x[b as usize].z > 0.03;
        assert_eq!(*k, if top { 4.0 * k0 } else { k0 });
    }
    // The bound uses the edited stiffness (docs/physics.md): dt_max = 2 / sqrt(lambda) with
    // lambda = max_i 2 sum_s k_s / m_i.
    let mut row = vec![0.0f32; x.len()];
    for (&[a, b], &k) in bb.springs().iter().zip(bb.stiffness()) {
        row[a as usize] += 2.0 * k;
        row[b as usize] += 2.0 * k;
    }
    let expected = 2.0 / row.iter().fold(0.0f32, |m, &r| m.max(r)).sqrt();
    assert!(
        (bb.stable_dt() - expected).abs() < 1e-5 * expected,
        "{} vs {expected}",
        bb.stable_dt()
    );
    assert!(bb.stable_dt() < 0.75 * plain.stable_dt());
}

/// Per-particle masses through setup (mass distribution): everything 3 kg.
#[derive(Debug)]
struct Heavy;

impl Effect for Heavy {
    fn name(&self) -> &str {
        "heavy"
    }
    fn setup(&mut self, m: &mut ModelSetup<'_>) -> Result<(), SimError> {
        m.masses.fill(3.0);
        Ok(())
    }
}

#[test]
fn masses_change_the_response() {
    // Two particles, one spring stretched by 2 mm: the relative acceleration scales with 1/m.
    let x = vec![Vec3::ZERO, Vec3::new(0.02, 0.0, 0.0)];
    let p = SpringParams {
        damping: 0.0,
        stiffness: 100.0,
        ..SpringParams::reference_rope()
    };
    let init = State {
        x: vec![Vec3::ZERO, Vec3::new(0.022, 0.0, 0.0)],
        v: vec![Vec3::ZERO; 2],
    };
    let cfg = SimConfig {
        step_dt: 0.01,
        substep: Substep::Fixed { dt: 1e-4 },
        ..free()
    };
    let light = Backbone::new(&x, &[], p, cfg).unwrap();
    let heavy = Backbone::with_options(&x, &[], p, cfg, with(vec![Box::new(Heavy)])).unwrap();
    let masses = BackboneOptions {
        masses: Some(vec![3.0, 3.0]),
        effects: Vec::new(),
        ..Default::default()
    };
    let direct = Backbone::with_options(&x, &[], p, cfg, masses).unwrap();
    assert_eq!(heavy.masses(), &[3.0, 3.0]);
    let a = light.rollout(&init, &Actions::without_grippers(2)).unwrap();
    let b = heavy.rollout(&init, &Actions::without_grippers(2)).unwrap();
    assert_eq!(
        b,
        direct
            .rollout(&init, &Actions::without_grippers(2))
            .unwrap()
    );
    // Over 0.01 s (a small part of the period) the speed gained is ~ F t / m.
    let ratio = a.velocities[1][0].x / b.velocities[1][0].x;
    assert!((ratio - 3.0).abs() < 0.05, "ratio {ratio}");
}

/// Plasticity: a spring strained beyond `yield_strain` takes its current length as its new rest
/// length (per-rollout state lives in the rest lengths the scratch owns).
#[derive(Debug)]
struct Plastic {
    yield_strain: f32,
}

impl Effect for Plastic {
    fn name(&self) -> &str {
        "plastic"
    }
    fn end_substep(&self, ctx: &SubstepContext<'_>, _s: &mut dyn Any, rest: &mut [f32]) {
        for (l0, &[a, b]) in rest.iter_mut().zip(ctx.backbone.springs()) {
            let l = (ctx.x[b as usize] - ctx.x[a as usize]).length();
            if (l - *l0).abs() > self.yield_strain * *l0 {
                *l0 = l;
            }
        }
    }
}

#[test]
fn rest_lengths_can_change_during_a_rollout() {
    let x = vec![Vec3::ZERO, Vec3::new(0.02, 0.0, 0.0)];
    let p = SpringParams {
        stiffness: 1000.0,
        damping: 50.0,
        ..SpringParams::reference_rope()
    };
    // Pulled apart at 0.2 m/s for 0.1 s: 20 mm of separation speed, about 4 mm of stretch.
    let init = State {
        x: x.clone(),
        v: vec![Vec3::new(-0.1, 0.0, 0.0), Vec3::new(0.1, 0.0, 0.0)],
    };
    let elastic = Backbone::new(&x, &[], p, free()).unwrap();
    let plastic = Backbone::with_options(
        &x,
        &[],
        p,
        free(),
        with(vec![Box::new(Plastic { yield_strain: 0.01 })]),
    )
    .unwrap();
    let gap = |bb: &Backbone| {
        let out = bb.rollout(&init, &Actions::without_grippers(20)).unwrap();
        out.positions[19][1].x - out.positions[19][0].x
    };
    assert!(
        (gap(&elastic) - 0.02).abs() < 2e-4,
        "elastic springs return to rest"
    );
    assert!(
        gap(&plastic) > 0.0205,
        "plastic springs keep a permanent set"
    );
    // A fresh scratch starts from the original rest lengths again.
    assert_eq!(gap(&plastic), gap(&plastic));
}

/// Actuation delay: the applied gripper motion lags the recorded one by one model step.
#[derive(Debug)]
struct DelayOneStep;

impl Effect for DelayOneStep {
    fn name(&self) -> &str {
        "delay"
    }
    fn new_state(&self, _bb: &Backbone) -> Box<dyn Any + Send> {
        Box::new(None::<Vec<Vec3>>)
    }
    fn adjust_actions(
        &self,
        state: &mut dyn Any,
        from: &mut [Vec3],
        to: &mut [Vec3],
        _closed: &mut [bool],
    ) {
        let prev = state
            .downcast_mut::<Option<Vec<Vec3>>>()
            .expect("own state");
        let recorded_from = from.to_vec();
        let applied_from = prev.clone().unwrap_or_else(|| recorded_from.clone());
        to.copy_from_slice(&recorded_from);
        from.copy_from_slice(&applied_from);
        *prev = Some(recorded_from);
    }
}

#[test]
fn actions_can_be_delayed() {
    let x = common::rope(50, 0.1, 0.002, 0.05);
    let held: Vec<i32> = (0..50).map(|i| if i < 3 { 0 } else { -1 }).collect();
    let frames: Vec<Vec<Vec3>> = (0..5)
        .map(|t| vec![Vec3::new(0.0, 0.0, 0.02 * t as f32)])
        .collect();
    let actions = Actions::new(frames, vec![vec![true]; 5]).unwrap();
    let bb = Backbone::with_options(
        &x,
        &held,
        SpringParams::reference_rope(),
        SimConfig::default(),
        with(vec![Box::new(DelayOneStep)]),
    )
    .unwrap();
    let out = bb.rollout(&State::at_rest(x.clone()), &actions).unwrap();
    for t in 1..5 {
        // Held particles are where the recorded gripper was one frame earlier.
        let lag = 0.02 * (t as f32 - 1.0);
        assert!(
            (out.positions[t][0].z - (x[0].z + lag)).abs() < 1e-5,
            "frame {t}"
        );
    }
}

/// A frictionless ground (a replaced friction law).
#[derive(Debug)]
struct Ice;

impl Effect for Ice {
    fn name(&self) -> &str {
        "ice"
    }
    fn replaces_ground_friction(&self) -> bool {
        true
    }
    fn ground_friction(&self, contact: &GroundContact) -> Vec3A {
        contact.tangential_velocity
    }
}

#[test]
fn ground_friction_can_be_replaced() {
    let z = -9.8 / springs::GROUND_STIFFNESS;
    let x = vec![Vec3::new(0.0, 0.0, z)];
    let init = State {
        x: x.clone(),
        v: vec![Vec3::new(0.5, 0.0, 0.0)],
    };
    let cfg = SimConfig {
        clamp_to_ground: false,
        ..SimConfig::default()
    };
    let p = SpringParams::reference_rope();
    let ice = Backbone::with_options(&x, &[], p, cfg, with(vec![Box::new(Ice)])).unwrap();
    let out = ice.rollout(&init, &Actions::without_grippers(4)).unwrap();
    assert!((out.velocities[3][0].x - 0.5).abs() < 1e-6);
    let normal = Backbone::new(&x, &[], p, cfg).unwrap();
    let out = normal
        .rollout(&init, &Actions::without_grippers(4))
        .unwrap();
    assert!(out.velocities[3][0].x < 0.4);
}

/// Grasp slip: held particles hang on the gripper by a spring of stiffness `k` to the point
/// where they were grasped, instead of moving rigidly.
#[derive(Debug)]
struct CompliantGrasp {
    k: f32,
}

impl Effect for CompliantGrasp {
    fn name(&self) -> &str {
        "compliant-grasp"
    }
    fn compliant_grasp(&self) -> bool {
        true
    }
    fn stability(&self, bb: &Backbone, row: &mut [f32], _damping: &mut [f32]) {
        for (r, &h) in row.iter_mut().zip(bb.held()) {
            if h >= 0 {
                *r += self.k;
            }
        }
    }
    fn new_state(&self, bb: &Backbone) -> Box<dyn Any + Send> {
        // Offset of each held particle from its gripper, fixed at the first substep.
        Box::new(vec![None::<Vec3>; bb.num_particles()])
    }
    fn add_forces(
        &self,
        ctx: &SubstepContext<'_>,
        state: &mut dyn Any,
        _rest: &[f32],
        force: &mut [Vec3A],
    ) {
        let offsets = state
            .downcast_mut::<Vec<Option<Vec3>>>()
            .expect("own state");
        for (i, &h) in ctx.backbone.held().iter().enumerate() {
            if h < 0 || !ctx.closed[h as usize] {
                continue;
            }
            let g = ctx.grippers[h as usize];
            let off = *offsets[i].get_or_insert(Vec3::from(ctx.x[i]) - g);
            force[i] += self.k * (Vec3A::from(g + off) - ctx.x[i]);
        }
    }
}

#[test]
fn grasp_can_be_made_compliant() {
    let x = common::rope(60, 0.12, 0.002, 0.01);
    let held: Vec<i32> = (0..60).map(|i| if i < 4 { 0 } else { -1 }).collect();
    let frames: Vec<Vec<Vec3>> = (0..6)
        .map(|t| vec![Vec3::new(0.0, 0.0, 0.03 * t as f32)])
        .collect();
    let actions = Actions::new(frames, vec![vec![true]; 6]).unwrap();
    let p = SpringParams::reference_rope();
    let plain = Backbone::new(&x, &held, p, SimConfig::default()).unwrap();
    let eff = with(vec![Box::new(CompliantGrasp { k: 2e6 })]);
    let soft = Backbone::with_options(&x, &held, p, SimConfig::default(), eff).unwrap();
    // The anchor springs are in the bound: a 2e6 N/m anchor shortens the substep.
    assert!(soft.stable_dt() < plain.stable_dt());
    let a = plain.rollout(&State::at_rest(x.clone()), &actions).unwrap();
    let b = soft.rollout(&State::at_rest(x.clone()), &actions).unwrap();
    for t in 1..6 {
        // Kinematic: exactly on the gripper path. Compliant: close to it, but not on it.
        let target = x[0].z + 0.03 * t as f32;
        assert!((a.positions[t][0].z - target).abs() < 1e-5);
        let off = (target - b.positions[t][0].z).abs();
        assert!(off > 1e-6 && off < 2e-3, "frame {t}: off by {off}");
    }
}
