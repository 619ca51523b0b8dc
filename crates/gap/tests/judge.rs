//! The verdict stage on its own: re-judging a stored diagnosis reproduces it under its own
//! rule, and the rule's thresholds move the verdict the way the method says.

use gap::{Candidate, Comparison, DiagnoseConfig, RankedEffect, VerdictRule, judge};

mod common;
use common::{backbone, scenes};

fn refit(
    effect: &str,
    shrinkage: f64,
    lo: f64,
    itself: f64,
    cos: f64,
    per: Vec<f64>,
) -> RankedEffect {
    let mean = per.iter().sum::<f64>() / per.len() as f64;
    RankedEffect {
        effect: effect.to_string(),
        heldout_mde_before_cm: 2.0,
        heldout_mde_after_cm: mean,
        shrinkage,
        ci95: [lo, shrinkage + (shrinkage - lo)],
        significant: false,
        effect_itself: Some(Comparison {
            shrinkage: itself,
            ci95: [itself / 2.0, itself * 1.5],
        }),
        signature_cosine: cos,
        fitted: Vec::new(),
        train_loss_m2: 0.0,
        refit_wall_s: 0.0,
        heldout_mde_per_episode_cm: per,
        raced_out: false,
    }
}

fn config(min_shrinkage: f64) -> DiagnoseConfig {
    DiagnoseConfig {
        rule: VerdictRule {
            min_shrinkage,
            ..VerdictRule::default()
        },
        ..DiagnoseConfig::default()
    }
}

#[test]
fn the_floor_and_the_tie_break_decide_between_refits() {
    let a_per = vec![1.60, 1.70, 1.50, 1.65, 1.55, 1.60, 1.62, 1.58];
    // B: A's errors give or take 0.02 cm, so held-out error cannot separate the two.
    let b_per: Vec<f64> = a_per
        .iter()
        .enumerate()
        .map(|(i, v)| v + if i % 2 == 0 { 0.02 } else { -0.02 })
        .collect();
    let a = refit("drag", 0.20, 0.10, 0.20, 0.1, a_per.clone());
    let b = refit("bending", 0.18, 0.08, 0.18, 0.8, b_per);
    let library = [a.clone(), b.clone()];

    // Both count at the default floor and are tied: the signature names B.
    let j = judge(&library, None, &config(0.05)).unwrap();
    assert_eq!(j.verdict, "bending");
    assert_eq!(j.significant, ["drag", "bending"]);
    let tb = j.tie_break.expect("a tie");
    assert_eq!(
        (tb.by_shrinkage.as_str(), tb.chosen.as_str()),
        ("drag", "bending")
    );

    // A floor between the two leaves A alone; one above both leaves nothing.
    let j = judge(&library, None, &config(0.19)).unwrap();
    assert_eq!((j.verdict.as_str(), j.tie_break), ("drag", None));
    assert_eq!(
        judge(&library, None, &config(0.25)).unwrap().verdict,
        "none"
    );

    // An effect that does not carry its refit's gain cannot be the verdict.
    let mut hollow = a.clone();
    hollow.effect_itself = Some(Comparison {
        shrinkage: 0.01,
        ci95: [-0.02, 0.04],
    });
    assert_eq!(
        judge(&[hollow], None, &config(0.05)).unwrap().verdict,
        "none"
    );

    // A probe far below the chosen candidate makes the gap `unknown`; alone, too.
    let probe = refit("external-field", 0.5, 0.45, 0.5, 0.0, vec![1.0; 8]);
    let j = judge(&library, Some(&probe), &config(0.05)).unwrap();
    assert_eq!(j.verdict, "unknown");
    assert!(j.probe_vs_best.is_some_and(|c| c.shrinkage > 0.3));
    assert_eq!(
        judge(&library, Some(&probe), &config(0.6)).unwrap().verdict,
        "none"
    );
    assert_eq!(
        judge(&[], Some(&probe), &config(0.05)).unwrap().verdict,
        "unknown"
    );
}

#[test]
fn rejudging_a_diagnosis_under_its_own_rule_reproduces_it() {
    let cfg = DiagnoseConfig {
        population: 4,
        generations: 2,
        samples: 1,
        resamples: 200,
        candidates: vec![Candidate::Drag, Candidate::Bending, Candidate::Friction],
        signature_scenes: 1,
        ..DiagnoseConfig::default()
    };
    let base = backbone();
    let (train, val) = (scenes(dataset::Split::Train), scenes(dataset::Split::Val));
    let d = gap::diagnose(&train, &val, &base, &cfg, &mut |_| {}).unwrap();
    let again = d.rejudge(d.config.rule).unwrap();
    assert_eq!(again.verdict, d.verdict);
    assert_eq!(again.tie_break, d.tie_break);
    assert_eq!(again.probe_vs_best, d.probe_vs_best);
    let flagged: Vec<&str> = d
        .ranking
        .iter()
        .filter(|r| r.significant)
        .map(|r| r.effect.as_str())
        .collect();
    for name in &again.significant {
        assert!(flagged.contains(&name.as_str()), "{name}");
    }
    assert_eq!(again.significant.len(), flagged.len());
    // No refit removes 99 % of the error: under that floor nothing is significant.
    let strict = VerdictRule {
        min_shrinkage: 0.99,
        ..d.config.rule
    };
    let j = d.rejudge(strict).unwrap();
    assert_eq!((j.verdict.as_str(), j.significant.len()), ("none", 0));
    // A rule outside its range is an error, not a verdict.
    assert!(
        d.rejudge(VerdictRule {
            min_shrinkage: 1.5,
            ..strict
        })
        .is_err()
    );
}

#[test]
fn stored_bench_reports_are_reproduced_by_the_rule_they_were_judged_with() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data");
    let reports = [
        ("rope-plasticity-x64-seed1", "plasticity"),
        ("paper-magnet-x4-seed0", "unknown"),
        ("flag-magnet-x4-seed1", "drag"),
    ];
    for (name, verdict) in reports {
        let text = std::fs::read_to_string(format!("{dir}/{name}.json")).unwrap();
        let d: gap::Diagnosis = serde_json::from_str(&text).unwrap();
        assert_eq!(d.verdict, verdict);
        let j = d.rejudge(d.config.rule).unwrap();
        assert_eq!(j.verdict, d.verdict, "{name}");
        assert_eq!(j.tie_break, d.tie_break, "{name}");
        assert_eq!(j.probe_vs_best, d.probe_vs_best, "{name}");
    }
}

/// The network stage is applied again on re-judging: under the report's rule it reproduces the
/// stored stage exactly (after a JSON round trip), and when another rule drops the effect the
/// network is compared with the control instead, and can turn that `none` into `unknown`.
#[test]
fn rejudging_applies_the_network_stage_again() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data");
    let text = std::fs::read_to_string(format!("{dir}/rope-plasticity-x64-seed1.json")).unwrap();
    let mut d: gap::Diagnosis = serde_json::from_str(&text).unwrap();
    assert_eq!(d.verdict, "plasticity");
    let control = d
        .how_far
        .as_ref()
        .unwrap()
        .before
        .per_episode_mde_cm
        .clone();
    // A network that halves the control's error on every episode.
    let halved: Vec<f64> = control.iter().map(|e| 0.5 * e).collect();
    let alone = d.backbone_as_given.per_episode_mde_cm.clone();
    gap::add_learnable(&mut d, &halved, &alone).unwrap();
    assert_eq!(d.verdict, "plasticity");
    let stored = d.learnable.clone().unwrap();
    assert_eq!(
        (stored.model.as_str(), stored.changed_verdict),
        ("plasticity", false)
    );

    let d: gap::Diagnosis = serde_json::from_str(&serde_json::to_string(&d).unwrap()).unwrap();
    let j = d.rejudge(d.config.rule).unwrap();
    assert_eq!(j.verdict, "plasticity");
    assert_eq!(j.learnable.as_ref(), Some(&stored));

    // The two significant refits gain 37-38 % and the probe nothing: a 45 % floor drops them,
    // the verdict stage answers `none`, and the network, halving the control's error, makes it
    // `unknown`.
    let floor = |f: f64| VerdictRule {
        min_shrinkage: f,
        ..d.config.rule
    };
    let mut plain = d.clone();
    plain.learnable = None;
    assert_eq!(plain.rejudge(floor(0.45)).unwrap().verdict, "none");
    assert!(plain.rejudge(floor(0.45)).unwrap().learnable.is_none());
    let j = d.rejudge(floor(0.45)).unwrap();
    let l = j.learnable.as_ref().unwrap();
    assert_eq!(
        (j.verdict.as_str(), l.model.as_str()),
        ("unknown", "control")
    );
    assert!(l.changed_verdict && (l.vs_model.shrinkage - 0.5).abs() < 1e-9);
    // Under a 60 % floor the network's 50 % is not enough: `none` stands.
    let j = d.rejudge(floor(0.6)).unwrap();
    assert_eq!(j.verdict, "none");
    assert!(!j.learnable.unwrap().changed_verdict);

    // A report from before the per-episode errors were stored: the stage is not re-applied.
    let mut old = d.clone();
    let l = old.learnable.as_mut().unwrap();
    l.network_per_episode_mde_cm.clear();
    l.backbone_per_episode_mde_cm.clear();
    let j = old.rejudge(floor(0.45)).unwrap();
    assert_eq!((j.verdict.as_str(), j.learnable), ("none", None));
}

/// Without the probe the library's refits name the effect the probe outdid: on the stored
/// `unknown` report the one significant refit (drag), on the others their own verdict; with
/// that refit's interval reaching 0 there is nothing to name, while the probe alone still
/// makes the gap `unknown`.
#[test]
fn the_library_verdict_names_what_the_probe_outdid() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data");
    let read = |name: &str| -> gap::Diagnosis {
        serde_json::from_str(&std::fs::read_to_string(format!("{dir}/{name}.json")).unwrap())
            .unwrap()
    };
    let magnet = read("paper-magnet-x4-seed0");
    assert_eq!(magnet.verdict, "unknown");
    let significant: Vec<&str> = (magnet.ranking.iter())
        .filter(|r| r.significant)
        .map(|r| r.effect.as_str())
        .collect();
    assert_eq!(significant, ["drag"]);
    assert_eq!(magnet.library_verdict().unwrap(), "drag");
    for (name, verdict) in [
        ("flag-magnet-x4-seed1", "drag"),
        ("rope-plasticity-x64-seed1", "plasticity"),
    ] {
        let d = read(name);
        assert_eq!(d.verdict, verdict);
        assert_eq!(d.library_verdict().unwrap(), verdict, "{name}");
    }
    let mut weak = magnet.clone();
    let drag = weak
        .ranking
        .iter_mut()
        .find(|r| r.effect == "drag")
        .unwrap();
    drag.ci95[0] = -0.05;
    assert_eq!(weak.rejudge(weak.config.rule).unwrap().verdict, "unknown");
    assert_eq!(weak.library_verdict().unwrap(), "none");
}

/// A real tie broken by a signature that explains almost nothing of the residual (the rope's
/// grasp slip of seed 57: cosines 0.107 for plasticity against 0.066): the rule it was judged
/// with (no floor) names plasticity, the default floor keeps the largest shrinkage.
#[test]
fn a_weak_signature_does_not_overrule_the_held_out_error() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data");
    let text = std::fs::read_to_string(format!("{dir}/rope-grasp-slip-x64-seed57.json")).unwrap();
    let d: gap::Diagnosis = serde_json::from_str(&text).unwrap();
    assert_eq!(d.verdict, "plasticity");
    assert_eq!(
        d.config.rule.tie_break_min_cosine, 0.0,
        "saved before the field"
    );
    let own = d.rejudge(d.config.rule).unwrap();
    assert_eq!(own.verdict, "plasticity");
    assert_eq!(own.tie_break, d.tie_break);
    let floored = d
        .rejudge(VerdictRule {
            tie_break_min_cosine: VerdictRule::default().tie_break_min_cosine,
            ..d.config.rule
        })
        .unwrap();
    assert_eq!(floored.verdict, "grasp-slip");
    let tb = floored.tie_break.unwrap();
    assert_eq!(tb.tied, ["grasp-slip", "plasticity"]);
    assert_eq!(
        (tb.by_shrinkage.as_str(), tb.chosen.as_str()),
        ("grasp-slip", "grasp-slip")
    );
    // Out of range is an error, not a verdict.
    let bad = VerdictRule {
        tie_break_min_cosine: 1.5,
        ..d.config.rule
    };
    assert!(d.rejudge(bad).is_err());
}
