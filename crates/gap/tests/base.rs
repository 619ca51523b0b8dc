//! Base effects: with none the diagnosis is the plain-backbone diagnosis; a base effect is
//! refitted in the control, is not ranked as a candidate, and its refitted model reproduces the
//! control's held-out error.

use fit::{Family, FitConfig};
use gap::{BaseEffect, Candidate, CandidateFamily, DiagnoseConfig};
use scene::Scene;

mod common;
use common::{backbone, scenes};

fn tiny(base: Vec<BaseEffect>) -> DiagnoseConfig {
    DiagnoseConfig {
        population: 4,
        generations: 2,
        samples: 1,
        resamples: 50,
        candidates: vec![Candidate::Drag, Candidate::Bending],
        base,
        probe: false,
        signature_scenes: 1,
        ..DiagnoseConfig::default()
    }
}

/// Held-out MDE (cm) of a model, computed here from the scene API rather than by the crate.
fn mde_cm(family: &CandidateFamily, real: &[f64], val: &[Scene]) -> f64 {
    let (params, _) = family.build(real);
    let per: Vec<f64> = val
        .iter()
        .map(|s| {
            let (_, options) = family.build(real);
            let pred = s.rollout(&params, &s.sim_config(), options).unwrap();
            let e = scene::score_steps(s, &pred, false).unwrap();
            let (sum, n) = scene::sum_over_steps(&e, |x| x.mde);
            100.0 * sum / n as f64
        })
        .collect();
    per.iter().sum::<f64>() / val.len() as f64
}

#[test]
fn without_base_effects_the_control_is_the_plain_backbone_refit() {
    let (train, val) = (scenes(dataset::Split::Train), scenes(dataset::Split::Val));
    // With the final rescoring on, on a subset of the training scenes, so that both are
    // shown to be the fit crate's.
    let cfg = DiagnoseConfig {
        rescore: 2,
        rescore_scenes: train.len() - 1,
        ..tiny(Vec::new())
    };
    let d = gap::diagnose(&train, &val, &backbone(), &cfg, &mut |_| {}).unwrap();
    // The same refit done by hand with the plain family (stiffness, damping, friction only).
    let frame = gap::material_frame(&train).unwrap();
    let plain = CandidateFamily::new(backbone(), None, frame).unwrap();
    assert_eq!(plain.name(), "spring-mass+control");
    let fit_cfg = FitConfig {
        population: cfg.population,
        generations: cfg.generations,
        samples: cfg.samples,
        sigma0: cfg.sigma0,
        seed: cfg.seed,
        rescore: cfg.rescore,
        rescore_scenes: cfg.rescore_scenes,
        rescore_start: cfg.keep_start,
    };
    let out = fit::fit(&train, &plain, &fit_cfg, None, &mut |_| {}).unwrap();
    let fitted: Vec<f64> = d.control.fitted.iter().map(|(_, v)| *v).collect();
    assert_eq!(fitted, out.best, "bit-identical refit");
    assert_eq!(d.control.fitted.len(), 3);
    assert!(d.control.base.is_empty());
    assert_eq!(
        d.control.heldout_mde_cm.to_bits(),
        mde_cm(&plain, &out.best, &val).to_bits()
    );
    assert_eq!(d.ranking.len(), 2);
    for r in &d.ranking {
        assert_eq!(r.heldout_mde_before_cm, d.control.heldout_mde_cm);
    }
}

#[test]
fn a_base_effect_is_refitted_in_the_control_and_not_ranked() {
    let (train, val) = (scenes(dataset::Split::Train), scenes(dataset::Split::Val));
    let start = BaseEffect::parse("bending=0.05").unwrap();
    let cfg = tiny(vec![start.clone()]);
    let d = gap::diagnose(&train, &val, &backbone(), &cfg, &mut |_| {}).unwrap();
    // Bending is part of the model, so only drag is ranked.
    let ranked: Vec<&str> = d.ranking.iter().map(|r| r.effect.as_str()).collect();
    assert_eq!(ranked, ["drag"]);
    // The control refitted the bending stiffness along with the backbone.
    let names: Vec<&str> = d.control.fitted.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(
        names,
        [
            "stiffness_n_per_m",
            "damping_ns_per_m",
            "ground_friction",
            "bending_relative_stiffness"
        ]
    );
    let kappa = d.control.fitted[3].1;
    assert!(kappa != 0.05 && (1e-3..=1.0).contains(&kappa), "{kappa}");
    assert_eq!(d.control.base[0].effect, Candidate::Bending);
    assert_eq!(d.control.base[0].values, vec![kappa]);
    // The drag refit carries the base effect too: backbone, bending, drag.
    assert_eq!(d.ranking[0].fitted.len(), 5);
    assert_eq!(d.ranking[0].fitted[3].0, "bending_relative_stiffness");
    // The refitted control, evaluated as a fixed model, reproduces its held-out error.
    let (params, base) = d.refitted_model(&backbone(), None).unwrap();
    let frame = gap::material_frame(&train).unwrap();
    let again = gap::evaluate(&frame, &val, &params, &base).unwrap();
    assert_eq!(again.mde_cm.to_bits(), d.control.heldout_mde_cm.to_bits());
    // ... and the bending springs matter: without them the error differs.
    let bare = gap::evaluate(&frame, &val, &params, &[]).unwrap();
    assert_ne!(bare.mde_cm, again.mde_cm);
    // The next iteration's base: the control plus drag, at its refitted values.
    let (_, next) = d
        .refitted_model(&backbone(), Some(Candidate::Drag))
        .unwrap();
    let effects: Vec<Candidate> = next.iter().map(|b| b.effect).collect();
    assert_eq!(effects, [Candidate::Bending, Candidate::Drag]);
    assert_eq!(
        serde_json::to_value(&d).unwrap()["config"]["base"][0]["effect"],
        "bending"
    );
}

#[test]
fn bad_base_lists_are_errors() {
    let (train, val) = (scenes(dataset::Split::Train), scenes(dataset::Split::Val));
    assert!(BaseEffect::parse("magnet").is_err());
    assert!(BaseEffect::parse("external-field").is_err());
    assert!(BaseEffect::parse("bending=0.1:0.2").is_err());
    assert!(BaseEffect::parse("bending=x").is_err());
    assert!(BaseEffect::parse_list("drag,drag").is_err());
    let b = BaseEffect::parse("drag").unwrap();
    let twice = tiny(vec![b.clone(), b.clone()]);
    let r = gap::diagnose(&train, &val, &backbone(), &twice, &mut |_| {});
    assert!(matches!(r, Err(gap::GapError::Config(_))));
    let frame = gap::material_frame(&train).unwrap();
    assert!(CandidateFamily::with_base(backbone(), &[b], Some(Candidate::Drag), frame).is_err());
    // A refitted value an ulp past a bound is clamped, not refused.
    let top = BaseEffect::new(Candidate::Bending, vec![1.0 + 1e-12]).unwrap();
    assert_eq!(top.values, vec![1.0]);
    let fitted = BaseEffect::new(Candidate::Bending, vec![0.025408515726371702]).unwrap();
    assert_eq!(fitted.label(), "bending=0.0254085157");
    let label = BaseEffect::parse("plasticity=0.02:5").unwrap().label();
    assert_eq!(label, "plasticity=0.02:5");
    assert_eq!(BaseEffect::parse(&label).unwrap().values, vec![0.02, 5.0]);
}

#[test]
fn a_verdict_rule_outside_its_range_is_an_error() {
    let (train, val) = (scenes(dataset::Split::Train), scenes(dataset::Split::Val));
    for (min_shrinkage, probe_margin) in [(-0.01, 0.1), (1.0, 0.1), (f64::NAN, 0.1), (0.05, 2.0)] {
        let mut cfg = tiny(Vec::new());
        cfg.rule.min_shrinkage = min_shrinkage;
        cfg.rule.probe_margin = probe_margin;
        let r = gap::diagnose(&train, &val, &backbone(), &cfg, &mut |_| {});
        assert!(
            matches!(r, Err(gap::GapError::Config(_))),
            "{min_shrinkage}, {probe_margin} accepted"
        );
    }
}

/// A refined stiffness field is held at its values in every model: the backbone as given and
/// the control refit are those of the family with the field, computed here by hand; a field of
/// the wrong length is an error.
#[test]
fn a_refined_field_is_kept_in_every_model() {
    let (train, val) = (scenes(dataset::Split::Train), scenes(dataset::Split::Val));
    let tracked = train[0].tracked;
    // Stiffer towards one end of the tracked particles' order, up to e¹.
    let field: Vec<f32> = (0..tracked).map(|i| i as f32 / tracked as f32).collect();
    let cfg = DiagnoseConfig {
        field: Some(field.clone()),
        ..tiny(Vec::new())
    };
    let d = gap::diagnose(&train, &val, &backbone(), &cfg, &mut |_| {}).unwrap();
    let frame = gap::material_frame(&train).unwrap();
    let with_field = CandidateFamily::new(backbone(), None, frame.clone())
        .unwrap()
        .with_field(Some(std::sync::Arc::new(field)));
    let given = mde_cm(&with_field, &with_field.x0(), &val);
    assert_eq!(d.backbone_as_given.mde_cm.to_bits(), given.to_bits());
    let plain = CandidateFamily::new(backbone(), None, frame).unwrap();
    let without = mde_cm(&plain, &plain.x0(), &val);
    assert!(
        (given - without).abs() > 1e-3,
        "the field changed nothing: {given} {without}"
    );
    let fitted: Vec<f64> = d.control.fitted.iter().map(|(_, v)| *v).collect();
    assert_eq!(
        d.control.heldout_mde_cm.to_bits(),
        mde_cm(&with_field, &fitted, &val).to_bits()
    );
    let short = DiagnoseConfig {
        field: Some(vec![0.0; tracked - 1]),
        ..tiny(Vec::new())
    };
    assert!(gap::diagnose(&train, &val, &backbone(), &short, &mut |_| {}).is_err());
}

#[test]
fn a_control_that_keeps_its_start_is_no_worse_on_training_than_the_model_as_given() {
    let (train, val) = (scenes(dataset::Split::Train), scenes(dataset::Split::Val));
    // One wide generation: its points all land farther from the training data than the
    // model as given (measured on this fixture with seed 0).
    let cfg = |keep_start| DiagnoseConfig {
        rescore: 2,
        keep_start,
        generations: 1,
        sigma0: 0.5,
        seed: 0,
        ..tiny(Vec::new())
    };
    let frame = gap::material_frame(&train).unwrap();
    let given = CandidateFamily::new(backbone(), None, frame).unwrap();
    let start = given.x0();
    let given_loss = train
        .iter()
        .map(|s| fit::scene_loss(&given, &start, s))
        .sum::<f64>()
        / train.len() as f64;
    let off = gap::diagnose(&train, &val, &backbone(), &cfg(false), &mut |_| {}).unwrap();
    assert!(
        off.control.train_loss_m2 > given_loss,
        "the scenario needs a worse search"
    );
    let on = gap::diagnose(&train, &val, &backbone(), &cfg(true), &mut |_| {}).unwrap();
    assert_eq!(on.control.train_loss_m2, given_loss);
    let fitted: Vec<f64> = on.control.fitted.iter().map(|(_, v)| *v).collect();
    assert_eq!(fitted, start);
    assert_eq!(on.control.heldout_mde_cm, on.backbone_as_given.mde_cm);
}

#[test]
fn a_held_base_effect_keeps_its_value_in_every_refit() {
    let (train, val) = (scenes(dataset::Split::Train), scenes(dataset::Split::Val));
    let start = BaseEffect::parse("bending=0.05").unwrap();
    let cfg = DiagnoseConfig {
        hold_base: true,
        ..tiny(vec![start.clone()])
    };
    let d = gap::diagnose(&train, &val, &backbone(), &cfg, &mut |_| {}).unwrap();
    // The control and the drag refit name the bending stiffness at its given value.
    assert_eq!(d.control.fitted.len(), 4);
    assert_eq!(
        d.control.fitted[3],
        ("bending_relative_stiffness".into(), 0.05)
    );
    assert_eq!(d.control.base, vec![start.clone()]);
    let drag = &d.ranking[0];
    assert_eq!(drag.effect, "drag");
    assert_eq!(drag.fitted.len(), 5);
    assert_eq!(drag.fitted[3], ("bending_relative_stiffness".into(), 0.05));
    assert_eq!(drag.fitted[4].0, "drag_kg_per_m");
    // The held family searches the backbone's three values and drag's only ...
    let frame = gap::material_frame(&train).unwrap();
    let held = CandidateFamily::with_base(
        backbone(),
        std::slice::from_ref(&start),
        Some(Candidate::Drag),
        frame.clone(),
    )
    .unwrap()
    .with_base_held(true)
    .unwrap();
    assert_eq!(held.parameters().params().len(), 4);
    assert_eq!(held.x0().len(), 4);
    // ... and builds the model the refitting family builds with bending at 0.05.
    let free = CandidateFamily::with_base(
        backbone(),
        std::slice::from_ref(&start),
        Some(Candidate::Drag),
        frame.clone(),
    )
    .unwrap();
    let drag_values: Vec<f64> = drag.fitted.iter().map(|(_, v)| *v).collect();
    let held_real: Vec<f64> = [&drag_values[..3], &drag_values[4..]].concat();
    assert_eq!(
        mde_cm(&held, &held_real, &val).to_bits(),
        mde_cm(&free, &drag_values, &val).to_bits()
    );
    assert_eq!(held.named_values(&held_real), drag.fitted);
    // Switching the hold off again restores the refitting family.
    let back = held.with_base_held(false).unwrap();
    assert_eq!(back.parameters().params().len(), 5);
    assert_eq!(back.x0(), free.x0());
    // The refitted models read back as from any other report, the held value in place.
    let (params, base) = d.refitted_model(&backbone(), None).unwrap();
    assert_eq!(base, vec![start]);
    let again = gap::evaluate(&frame, &val, &params, &base).unwrap();
    assert_eq!(again.mde_cm.to_bits(), d.control.heldout_mde_cm.to_bits());
    // Without the hold the same diagnosis moves the bending stiffness.
    let moved = gap::diagnose(
        &train,
        &val,
        &backbone(),
        &tiny(d.config.base.clone()),
        &mut |_| {},
    )
    .unwrap();
    assert_ne!(moved.control.fitted[3].1, 0.05);
    assert_eq!(
        serde_json::to_value(&d).unwrap()["config"]["hold_base"],
        true
    );
    assert!(
        serde_json::to_value(&moved).unwrap()["config"]
            .get("hold_base")
            .is_none()
    );
}

#[test]
fn the_probe_alone_can_hold_the_base_effects() {
    let (train, val) = (scenes(dataset::Split::Train), scenes(dataset::Split::Val));
    let start = BaseEffect::parse("bending=0.05").unwrap();
    let cfg = DiagnoseConfig {
        probe: true,
        probe_factor: 1,
        probe_hold_base: true,
        candidates: vec![Candidate::Drag],
        ..tiny(vec![start.clone()])
    };
    let d = gap::diagnose(&train, &val, &backbone(), &cfg, &mut |_| {}).unwrap();
    // The control and the library candidate refit the bending stiffness ...
    assert_ne!(d.control.fitted[3].1, 0.05);
    assert_ne!(d.ranking[0].fitted[3].1, 0.05);
    // ... the probe keeps it, and its fitted list still names it in its place.
    let probe = d.probe.as_ref().unwrap();
    assert_eq!(probe.fitted[3], ("bending_relative_stiffness".into(), 0.05));
    assert_eq!(
        probe.fitted.len(),
        4 + Candidate::ExternalField.parameters().len()
    );
    assert_eq!(
        serde_json::to_value(&d).unwrap()["config"]["probe_hold_base"],
        true
    );
}
