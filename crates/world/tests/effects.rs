//! Every effect, switched on alone, changes the recorded trajectories measurably relative to no
//! effects; and with no effects the same seed gives the same data.

use world::{EffectKind, Effects, GenConfig, ObjectKind, Observation, generate};

/// A noise-free, coarse recording of 6 s (two overlapping episodes) of `object` with `effects`;
/// all tracked positions.
fn run(object: ObjectKind, effects: Effects) -> Vec<glam::Vec3> {
    let mut cfg = GenConfig::fixture(object);
    (cfg.train_episodes, cfg.val_episodes, cfg.tracked) = (2, 0, 60);
    cfg.effects = effects;
    cfg.observation = Observation::none();
    cfg.seed = 3;
    let data = generate(&cfg).unwrap();
    data.episodes
        .iter()
        .flat_map(|(e, _)| e.positions().iter().copied())
        .collect()
}

/// Mean distance between corresponding tracked positions, m.
fn mean_gap(a: &[glam::Vec3], b: &[glam::Vec3]) -> f32 {
    a.iter().zip(b).map(|(p, q)| p.distance(*q)).sum::<f32>() / a.len() as f32
}

/// Which object shows each effect (friction needs ground contact, grasp slip a heavy held body).
fn showcase(kind: EffectKind) -> ObjectKind {
    match kind {
        EffectKind::Drag
        | EffectKind::ActuationDelay
        | EffectKind::RotatingFrame
        | EffectKind::Fan => ObjectKind::Flag,
        EffectKind::StiffnessHeterogeneity => ObjectKind::Duster,
        EffectKind::NonlinearElasticity | EffectKind::GraspSlip | EffectKind::MassDistribution => {
            ObjectKind::Sloth
        }
        EffectKind::Bending
        | EffectKind::Friction
        | EffectKind::Plasticity
        | EffectKind::Magnet => ObjectKind::Rope,
    }
}

#[test]
fn each_effect_alone_changes_trajectories() {
    let objects = [
        ObjectKind::Flag,
        ObjectKind::Duster,
        ObjectKind::Sloth,
        ObjectKind::Rope,
    ];
    let baselines: Vec<(ObjectKind, Vec<glam::Vec3>)> = objects
        .iter()
        .map(|&o| (o, run(o, Effects::none())))
        .collect();
    let mut report = Vec::new();
    for kind in EffectKind::ALL {
        let object = showcase(kind);
        let base = &baselines.iter().find(|(o, _)| *o == object).unwrap().1;
        let gap = mean_gap(base, &run(object, Effects::only(object, kind)));
        report.push(format!("{kind} on {object}: mean gap {:.2} mm", gap * 1e3));
        // 3 mm: three times the default tracking noise, i.e. clearly visible in data.
        assert!(gap > 0.003, "{}", report.join("\n"));
    }
    println!("{}", report.join("\n"));
}

#[test]
fn no_effects_same_seed_same_data() {
    let a = run(ObjectKind::Rope, Effects::none());
    let b = run(ObjectKind::Rope, Effects::none());
    assert_eq!(a, b);
}
