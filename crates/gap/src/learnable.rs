//! How much of the gap is learnable: a trained residual network's held-out error beside the
//! diagnosis's models, and the `unknown` verdict it can support.

use serde::{Deserialize, Serialize};

use crate::{Comparison, Diagnosis, GapError, VerdictRule, paired_shrinkage};

/// A trained residual network (backbone + residual velocities) on the diagnosis's held-out
/// episodes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Learnable {
    /// Held-out MDE of the backbone the network was trained on, cm.
    pub backbone_mde_cm: f64,
    /// Held-out MDE of the backbone with the network, cm.
    pub network_mde_cm: f64,
    /// The network against its own backbone: the learnable share of that backbone's error.
    pub vs_backbone: Comparison,
    /// Which of the diagnosis's models `vs_model` compares with: the verdict's effect, or
    /// `control` (the refitted backbone, when the verdict is not an effect).
    pub model: String,
    /// The network against that model: what the network learns beyond it.
    pub vs_model: Comparison,
    /// Whether this comparison turned a `none` verdict into `unknown`.
    pub changed_verdict: bool,
    /// The network's held-out MDE per episode, cm (what [`Diagnosis::rejudge`] needs to apply
    /// this stage again; empty in reports written before 2026-11-27).
    #[serde(default)]
    pub network_per_episode_mde_cm: Vec<f64>,
    /// Its backbone's held-out MDE per episode, cm (empty in reports before 2026-11-27).
    #[serde(default)]
    pub backbone_per_episode_mde_cm: Vec<f64>,
}

/// Adds a trained network's held-out errors to a diagnosis.
///
/// `network_mde_cm` and `backbone_mde_cm` are per held-out episode (cm), in the diagnosis's
/// order: the network's backbone + residual, and that backbone alone. The network is compared
/// with its backbone and with the diagnosis's final model (the verdict's effect refit, or the
/// control refit when the verdict is `none` or `unknown`), by the same paired bootstrap as the
/// candidates. When the verdict is `none` and the network beats the control significantly by
/// at least the probe margin (the same bar the external-field probe must clear), a learnable
/// gap remains that no library effect explains: the verdict becomes `unknown`.
///
/// ```
/// # fn demo(mut d: gap::Diagnosis) -> Result<(), gap::GapError> {
/// let n = d.episodes[1];
/// gap::add_learnable(&mut d, &vec![1.0; n], &vec![2.0; n])?;
/// println!("{} ({:?})", d.verdict, d.learnable.as_ref().map(|l| l.vs_model.shrinkage));
/// # Ok(()) }
/// ```
pub fn add_learnable(
    d: &mut Diagnosis,
    network_mde_cm: &[f64],
    backbone_mde_cm: &[f64],
) -> Result<(), GapError> {
    let (verdict, learnable) = learnable_stage(
        d,
        &d.verdict,
        &d.config.rule,
        network_mde_cm,
        backbone_mde_cm,
    )?;
    d.verdict = verdict;
    d.learnable = Some(learnable);
    Ok(())
}

/// The network stage on `verdict` (the verdict stage's answer under `rule`): the verdict after
/// it, and the comparisons. Shared by [`add_learnable`] and [`Diagnosis::rejudge`], which
/// passes the verdict that another rule gives.
pub(crate) fn learnable_stage(
    d: &Diagnosis,
    verdict: &str,
    rule: &VerdictRule,
    network_mde_cm: &[f64],
    backbone_mde_cm: &[f64],
) -> Result<(String, Learnable), GapError> {
    let n = d.episodes[1];
    if network_mde_cm.len() != n || backbone_mde_cm.len() != n {
        return Err(GapError::Config(format!(
            "the network was scored on {} and {} episodes, the diagnosis held out {n}",
            network_mde_cm.len(),
            backbone_mde_cm.len()
        )));
    }
    let (resamples, seed) = (d.config.resamples, d.config.seed ^ 0x006c_6561_726e);
    let vs_backbone = paired_shrinkage(backbone_mde_cm, network_mde_cm, resamples, seed)?;
    // The verdict's own refit when it names an effect (its held-out errors are those of
    // `how_far.after` when the diagnosis showed that effect), else the control.
    let (model, reference) = match d.ranking.iter().find(|r| r.effect == verdict) {
        Some(r) => (r.effect.clone(), &r.heldout_mde_per_episode_cm),
        None => match &d.how_far {
            Some(h) => ("control".to_string(), &h.before.per_episode_mde_cm),
            None => (
                "backbone as given".to_string(),
                &d.backbone_as_given.per_episode_mde_cm,
            ),
        },
    };
    let vs_model = paired_shrinkage(reference, network_mde_cm, resamples, seed ^ 1)?;
    let changed_verdict =
        verdict == "none" && vs_model.significant(rule.min_shrinkage.max(rule.probe_margin));
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let learnable = Learnable {
        backbone_mde_cm: mean(backbone_mde_cm),
        network_mde_cm: mean(network_mde_cm),
        vs_backbone,
        model,
        vs_model,
        changed_verdict,
        network_per_episode_mde_cm: network_mde_cm.to_vec(),
        backbone_per_episode_mde_cm: backbone_mde_cm.to_vec(),
    };
    let verdict = if changed_verdict { "unknown" } else { verdict };
    Ok((verdict.to_string(), learnable))
}
