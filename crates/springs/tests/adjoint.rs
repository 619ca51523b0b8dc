//! The step's vector-Jacobian product against central finite differences of the step itself:
//! `⟨g, J p⟩` (two perturbed steps) must equal `⟨Jᵀ g, p⟩` (one taped step and its adjoint).

mod common;

use common::Rng;
use glam::Vec3;
use springs::{Actions, Backbone, Dashpot, SimConfig, SpringParams, State, StepTape};

/// One step from `state` under a gripper lifted 2 cm (when any particle is held).
fn step(bb: &Backbone, state: &State, actions: &Actions) -> State {
    let mut s = state.clone();
    let mut sc = bb.scratch();
    bb.step(
        &mut s,
        actions.frame(0).unwrap(),
        actions.frame(1).unwrap(),
        &mut sc,
    )
    .unwrap();
    s
}

fn lift(held: &[i32], at: Vec3) -> Actions {
    if held.iter().all(|&h| h < 0) {
        return Actions::without_grippers(2);
    }
    Actions::new(
        vec![vec![at], vec![at + Vec3::new(0.0, 0.0, 0.02)]],
        vec![vec![true], vec![true]],
    )
    .unwrap()
}

/// Mismatch `|⟨g, J p⟩ − ⟨Jᵀ g, p⟩|` relative to `Σᵢ |gᵢ · (J p)ᵢ|` (the size of the terms
/// the products sum, so a sum that cancels to near zero does not inflate it), the largest over
/// `trials` random pairs `(g, p)`. The finite differences run in f32: measured mismatches are
/// 3e-4 to 5e-3; leaving out the dashpot directions' dependence on positions gave 0.13.
fn mismatch(bb: &Backbone, state: &State, actions: &Actions, seed: u64, trials: usize) -> f64 {
    let n = state.x.len();
    let mut rng = Rng::new(seed);
    let mut tape = StepTape::new();
    let mut taped = state.clone();
    let mut sc = bb.scratch();
    bb.step_taped(
        &mut taped,
        actions.frame(0).unwrap(),
        actions.frame(1).unwrap(),
        &mut sc,
        &mut tape,
    )
    .unwrap();
    assert_eq!(taped, step(bb, state, actions), "taping changed the step");
    let eps = 1e-4_f32;
    let mut worst = 0.0_f64;
    for _ in 0..trials {
        let gx: Vec<Vec3> = (0..n).map(|_| rng.vec3(1.0)).collect();
        let gv: Vec<Vec3> = (0..n).map(|_| rng.vec3(1.0)).collect();
        let px: Vec<Vec3> = (0..n).map(|_| rng.vec3(1.0)).collect();
        let pv: Vec<Vec3> = (0..n).map(|_| rng.vec3(1.0)).collect();
        let shifted = |sign: f32| {
            let mut s = state.clone();
            for i in 0..n {
                s.x[i] += sign * eps * px[i];
                s.v[i] += sign * eps * pv[i];
            }
            step(bb, &s, actions)
        };
        let (up, down) = (shifted(1.0), shifted(-1.0));
        let (mut jp, mut scale) = (0.0_f64, 0.0_f64);
        for i in 0..n {
            let dx = (up.x[i] - down.x[i]) / (2.0 * eps);
            let dv = (up.v[i] - down.v[i]) / (2.0 * eps);
            let term = f64::from(gx[i].dot(dx) + gv[i].dot(dv));
            jp += term;
            scale += term.abs();
        }
        let (mut ax, mut av) = (gx.clone(), gv.clone());
        bb.step_adjoint().vjp(&tape, &mut ax, &mut av).unwrap();
        let jtg: f64 = (0..n)
            .map(|i| f64::from(ax[i].dot(px[i]) + av[i].dot(pv[i])))
            .sum();
        assert!(scale > 1.0, "the check compares nothing: {scale}");
        worst = worst.max((jp - jtg).abs() / scale);
    }
    worst
}

/// A hanging rope held at one end, moving, in the air.
fn hanging(dashpot: Dashpot, damping: f32) -> (Backbone, State, Actions) {
    let x = common::rope(40, 0.2, 0.004, 0.3);
    let held: Vec<i32> = x.iter().map(|p| if p.x < 0.006 { 0 } else { -1 }).collect();
    let params = SpringParams {
        stiffness: 2000.0,
        damping,
        threshold: 0.02,
        max_springs: 20,
        ground_friction: 0.4,
    };
    let config = SimConfig {
        dashpot,
        ..SimConfig::default()
    };
    let bb = Backbone::new(&x, &held, params, config).unwrap();
    let mut rng = Rng::new(7);
    let mut state = State::at_rest(x.clone());
    for v in &mut state.v {
        *v = rng.vec3(0.2);
    }
    let at = x[held.iter().position(|&h| h == 0).unwrap()];
    let actions = lift(&held, at);
    (bb, state, actions)
}

#[test]
fn the_adjoint_is_the_transpose_of_the_step() {
    // Undamped, lightly damped, and damped as fitted backbones are (a few hundred N·s/m),
    // with either dashpot.
    for (dashpot, damping) in [
        (Dashpot::Implicit, 0.0),
        (Dashpot::Implicit, 2.0),
        (Dashpot::Implicit, 200.0),
        (Dashpot::Explicit, 2.0),
    ] {
        let (bb, state, actions) = hanging(dashpot, damping);
        let m = mismatch(&bb, &state, &actions, 2, 4);
        assert!(
            m < 1e-2,
            "{dashpot:?}, damping {damping}: relative mismatch {m}"
        );
    }
}

#[test]
fn the_adjoint_follows_a_rope_sliding_on_the_ground() {
    // A rope lying in ground contact (2 mm deep), sliding slowly (the viscous friction branch)
    // and fast (Coulomb's, whose decrement grows with the depth).
    for speed in [0.01, 1.0] {
        let m = sliding(speed);
        assert!(m < 1e-2, "{speed} m/s: relative mismatch {m}");
    }
}

fn sliding(speed: f32) -> f64 {
    let x: Vec<Vec3> = common::rope(40, 0.2, 0.004, 0.0)
        .into_iter()
        .map(|p| Vec3::new(p.x, p.y, -0.002))
        .collect();
    let params = SpringParams {
        stiffness: 2000.0,
        damping: 0.0,
        threshold: 0.02,
        max_springs: 20,
        ground_friction: 0.4,
    };
    let bb = Backbone::new(&x, &[], params, SimConfig::default()).unwrap();
    let mut state = State::at_rest(x);
    for v in &mut state.v {
        *v = Vec3::new(speed, 0.0, 0.0);
    }
    mismatch(&bb, &state, &Actions::without_grippers(2), 3, 4)
}

#[test]
fn a_held_particle_passes_no_gradient_to_its_velocity() {
    let (bb, state, actions) = hanging(Dashpot::Implicit, 2.0);
    let held: Vec<usize> = (0..state.x.len()).filter(|&i| bb.held()[i] >= 0).collect();
    let mut tape = StepTape::new();
    let mut s = state.clone();
    let mut sc = bb.scratch();
    let (from, to) = (actions.frame(0).unwrap(), actions.frame(1).unwrap());
    bb.step_taped(&mut s, from, to, &mut sc, &mut tape).unwrap();
    let n = s.x.len();
    let (mut gx, mut gv) = (vec![Vec3::ONE; n], vec![Vec3::ONE; n]);
    bb.step_adjoint().vjp(&tape, &mut gx, &mut gv).unwrap();
    assert!(!held.is_empty());
    for &i in &held {
        assert_eq!(gv[i], Vec3::ZERO);
    }
    assert!(gv.iter().any(|g| g.length() > 0.0));
}

#[test]
fn a_tape_from_another_backbone_is_an_error() {
    let (bb, state, actions) = hanging(Dashpot::Implicit, 2.0);
    let mut tape = StepTape::new();
    let n = state.x.len();
    let (mut gx, mut gv) = (vec![Vec3::ZERO; n], vec![Vec3::ZERO; n]);
    assert!(
        bb.step_adjoint().vjp(&tape, &mut gx, &mut gv).is_err(),
        "an empty tape"
    );
    let mut s = state.clone();
    let mut sc = bb.scratch();
    let (from, to) = (actions.frame(0).unwrap(), actions.frame(1).unwrap());
    bb.step_taped(&mut s, from, to, &mut sc, &mut tape).unwrap();
    let other = Backbone::new(
        &state.x[..20],
        &[],
        SpringParams::reference_rope(),
        SimConfig::default(),
    )
    .unwrap();
    let (mut gx, mut gv) = (vec![Vec3::ZERO; 20], vec![Vec3::ZERO; 20]);
    assert!(other.step_adjoint().vjp(&tape, &mut gx, &mut gv).is_err());
    let (mut gx, mut gv) = (vec![Vec3::ZERO; n - 1], vec![Vec3::ZERO; n]);
    assert!(
        bb.step_adjoint().vjp(&tape, &mut gx, &mut gv).is_err(),
        "wrong length"
    );
}

/// Scales every spring's stiffness by `1 + factor[s]` at setup.
#[derive(Debug)]
struct ScaleStiffness(Vec<f32>);

impl springs::Effect for ScaleStiffness {
    fn name(&self) -> &str {
        "scale-stiffness"
    }
    fn setup(&mut self, model: &mut springs::ModelSetup<'_>) -> Result<(), springs::SimError> {
        for (k, f) in model.stiffness.iter_mut().zip(&self.0) {
            *k *= 1.0 + f;
        }
        Ok(())
    }
}

/// The stiffness gradient of one step against central differences in every spring's
/// stiffness at once: `⟨g, ∂(x', v')/∂k · p⟩` from two perturbed backbones must equal
/// `Σ_s (∂L/∂k_s) k_s p_s` from the adjoint, with and without damping (measured mismatch
/// 7e-5 to 9e-4 of the summed terms).
#[test]
fn the_stiffness_gradient_matches_finite_differences() {
    for damping in [0.0, 2.0, 200.0] {
        let (bb, state, actions) = hanging(Dashpot::Implicit, damping);
        let (n, springs) = (state.x.len(), bb.springs().len());
        let mut rng = Rng::new(11);
        let mut tape = StepTape::new();
        let mut taped = state.clone();
        let mut sc = bb.scratch();
        let (from, to) = (actions.frame(0).unwrap(), actions.frame(1).unwrap());
        bb.step_taped(&mut taped, from, to, &mut sc, &mut tape)
            .unwrap();
        for _ in 0..3 {
            let gx: Vec<Vec3> = (0..n).map(|_| rng.vec3(1.0)).collect();
            let gv: Vec<Vec3> = (0..n).map(|_| rng.vec3(1.0)).collect();
            let p: Vec<f32> = (0..springs).map(|_| rng.range(-1.0, 1.0)).collect();
            // 1 %: large enough that f32 rounding of the states stays small next to the
            // difference, small enough that the step is linear in it (central differences).
            let eps = 1e-2_f32;
            let perturbed = |sign: f32| {
                let scale = ScaleStiffness(p.iter().map(|q| sign * eps * q).collect());
                let options = springs::BackboneOptions {
                    masses: None,
                    effects: vec![Box::new(scale)],
                    ..Default::default()
                };
                let held = bb.held().to_vec();
                let b =
                    Backbone::with_options(&state.x, &held, *bb.params(), *bb.config(), options)
                        .unwrap();
                assert_eq!(b.substeps(), bb.substeps());
                step(&b, &state, &actions)
            };
            let (up, down) = (perturbed(1.0), perturbed(-1.0));
            let (mut fd, mut scale) = (0.0_f64, 0.0_f64);
            for i in 0..n {
                let dx = (up.x[i] - down.x[i]) / (2.0 * eps);
                let dv = (up.v[i] - down.v[i]) / (2.0 * eps);
                let term = f64::from(gx[i].dot(dx) + gv[i].dot(dv));
                fd += term;
                scale += term.abs();
            }
            let (mut ax, mut av, mut gk) = (gx.clone(), gv.clone(), vec![0.0_f32; springs]);
            bb.step_adjoint()
                .vjp_stiffness(&tape, &mut ax, &mut av, &mut gk)
                .unwrap();
            let adj: f64 = (0..springs)
                .map(|s| f64::from(gk[s] * bb.stiffness()[s] * p[s]))
                .sum();
            assert!(scale > 1e-3, "the check compares nothing: {scale}");
            let m = (fd - adj).abs() / scale;
            assert!(
                m < 1e-2,
                "damping {damping}: fd {fd} adjoint {adj} (mismatch {m})"
            );
        }
        // The state part is the plain vjp's.
        let gx: Vec<Vec3> = (0..n).map(|_| rng.vec3(1.0)).collect();
        let (mut a1, mut v1) = (gx.clone(), gx.clone());
        let (mut a2, mut v2) = (gx.clone(), gx.clone());
        bb.step_adjoint().vjp(&tape, &mut a1, &mut v1).unwrap();
        let mut gk = vec![0.0; springs];
        bb.step_adjoint()
            .vjp_stiffness(&tape, &mut a2, &mut v2, &mut gk)
            .unwrap();
        assert_eq!((a1, v1), (a2, v2));
        assert!(
            bb.step_adjoint()
                .vjp_stiffness(&tape, &mut gx.clone(), &mut gx.clone(), &mut [0.0; 3])
                .is_err()
        );
    }
}

/// Linear drag, but without a transpose: the adjoint holds its forces fixed.
#[derive(Debug)]
struct OpaqueDrag(f32);

impl springs::Effect for OpaqueDrag {
    fn name(&self) -> &str {
        "opaque-drag"
    }
    fn add_forces(
        &self,
        ctx: &springs::SubstepContext<'_>,
        _state: &mut dyn std::any::Any,
        _rest: &[f32],
        force: &mut [glam::Vec3A],
    ) {
        for (f, v) in force.iter_mut().zip(ctx.v) {
            *f -= self.0 * *v;
        }
    }
}

fn with_effect(bb: &Backbone, x: &[Vec3], effect: Box<dyn springs::Effect>) -> Backbone {
    let options = springs::BackboneOptions {
        masses: None,
        effects: vec![effect],
        ..Default::default()
    };
    Backbone::with_options(x, bb.held(), *bb.params(), *bb.config(), options).unwrap()
}

#[test]
fn the_adjoint_carries_an_effect_that_gives_its_transpose() {
    for dashpot in [Dashpot::Implicit, Dashpot::Explicit] {
        let (plain, state, actions) = hanging(dashpot, 2.0);
        // Strong drag (time constant 0.2 s for 1 kg), so that leaving it out shows.
        let bb = with_effect(
            &plain,
            &state.x,
            Box::new(springs::AirDrag { coefficient: 5.0 }),
        );
        assert!(bb.held_fixed_effects().is_empty());
        let m = mismatch(&bb, &state, &actions, 3, 4);
        assert!(m < 1e-2, "{dashpot:?}: relative mismatch {m}");
        // The same force through an effect without a transpose: held fixed, named, and the
        // check above would fail on it.
        let opaque = with_effect(&plain, &state.x, Box::new(OpaqueDrag(5.0)));
        assert_eq!(opaque.held_fixed_effects(), vec!["opaque-drag"]);
        let m = mismatch(&opaque, &state, &actions, 3, 4);
        assert!(
            m > 5e-2,
            "{dashpot:?}: the held-fixed drag was not missed ({m})"
        );
    }
}
