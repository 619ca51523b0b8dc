//! The verdict stage of a diagnosis, from the ranked refits alone: no rollout, no refit. The
//! diagnosis calls it once; [`Diagnosis::rejudge`] calls it again on a stored report with
//! another [`VerdictRule`].

use serde::{Deserialize, Serialize};

use crate::GapError;
use crate::diagnose::{DiagnoseConfig, Diagnosis, RankedEffect, TieBreak};
use crate::learnable::{Learnable, learnable_stage};
use crate::stats::{
    Comparison, Rival, Verdict, VerdictRule, best_candidate, break_tie, decide, paired_shrinkage,
};

/// What the verdict rule makes of a diagnosis's refits.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Judgement {
    /// `"<effect>"`, `"none"` or `"unknown"`.
    pub verdict: String,
    /// The library candidates the rule counts as significant, in the order given.
    pub significant: Vec<String>,
    /// Present when significant candidates were tied on held-out error.
    pub tie_break: Option<TieBreak>,
    /// The probe against the chosen candidate, when both exist.
    pub probe_vs_best: Option<Comparison>,
    /// The network stage applied again ([`crate::add_learnable`]), when the report has a
    /// network with its per-episode errors; `verdict` is the answer after it.
    pub learnable: Option<Learnable>,
}

/// Whether the rule counts a refit as a significant improvement: against the control, and with
/// its effect carrying the gain (`effect_itself`, absent in reports older than the check).
pub(crate) fn counts(e: &RankedEffect, rule: &VerdictRule) -> bool {
    let main = Comparison {
        shrinkage: e.shrinkage,
        ci95: e.ci95,
    };
    main.significant(rule.min_shrinkage) && carries(e, rule)
}

fn carries(e: &RankedEffect, rule: &VerdictRule) -> bool {
    e.effect_itself
        .is_none_or(|c| c.significant(rule.min_shrinkage))
}

/// The verdict from the library refits (`library`, in the order they were refitted: the order
/// seeds the tie-break's bootstraps) and the probe's, under `config.rule` (method step 7 of
/// `docs/gap.md`). Each refit needs its per-episode held-out MDE when it takes part in a
/// paired comparison (tie-break, probe against the chosen candidate).
pub fn judge(
    library: &[RankedEffect],
    probe: Option<&RankedEffect>,
    config: &DiagnoseConfig,
) -> Result<Judgement, GapError> {
    let rule = &config.rule;
    let significant: Vec<bool> = library.iter().map(|e| counts(e, rule)).collect();
    let candidates: Vec<(String, Comparison)> = library
        .iter()
        .filter(|e| carries(e, rule))
        .map(|e| {
            let c = Comparison {
                shrinkage: e.shrinkage,
                ci95: e.ci95,
            };
            (e.effect.clone(), c)
        })
        .collect();
    let by_shrinkage = best_candidate(&candidates, rule)
        .and_then(|name| library.iter().position(|e| e.effect == name));
    // Candidates the held-out error cannot separate from the best go to the signature.
    let mut tie_break = None;
    let chosen = match by_shrinkage {
        Some(b) if rule.signature_tie_break => {
            let mut rivals = Vec::new();
            for (j, e) in library.iter().enumerate() {
                if j == b || !significant[j] {
                    continue;
                }
                rivals.push(Rival {
                    effect: e.effect.clone(),
                    signature_cosine: e.signature_cosine,
                    best_vs_rival: paired_shrinkage(
                        &e.heldout_mde_per_episode_cm,
                        &library[b].heldout_mde_per_episode_cm,
                        config.resamples,
                        config.seed ^ (0x71E0 + j as u64),
                    )?,
                });
            }
            let best = &library[b];
            let (name, tied) = break_tie(
                (&best.effect, best.signature_cosine),
                &rivals,
                rule.tie_break_min_cosine,
            );
            let c = library.iter().position(|e| e.effect == name);
            if tied.len() > 1 {
                tie_break = Some(TieBreak {
                    by_shrinkage: best.effect.clone(),
                    tied,
                    chosen: name,
                });
            }
            c
        }
        other => other,
    };
    let probe = probe.filter(|p| carries(p, rule));
    let probe_vs_best = match (probe, chosen) {
        (Some(p), Some(b)) => Some(paired_shrinkage(
            &library[b].heldout_mde_per_episode_cm,
            &p.heldout_mde_per_episode_cm,
            config.resamples,
            config.seed ^ 0xB0B,
        )?),
        _ => None,
    };
    let probe_vs_control = probe.map(|p| Comparison {
        shrinkage: p.shrinkage,
        ci95: p.ci95,
    });
    let verdict: Verdict = decide(
        chosen.map(|b| library[b].effect.as_str()),
        probe_vs_control,
        probe_vs_best,
        rule,
    );
    Ok(Judgement {
        verdict: verdict.label().to_string(),
        significant: library
            .iter()
            .zip(&significant)
            .filter(|(_, s)| **s)
            .map(|(e, _)| e.effect.clone())
            .collect(),
        tie_break,
        probe_vs_best,
        learnable: None,
    })
}

impl Diagnosis {
    /// The verdict this diagnosis would have reached under another `rule`, from its stored
    /// refits (no rollout or refit is repeated, so it takes microseconds). With the report's own
    /// rule it reproduces the report's verdict, tie-break and probe comparison exactly. When the
    /// report has a network stage ([`crate::add_learnable`]) with its per-episode errors, that
    /// stage is applied again to the new verdict (compared with the model the new verdict
    /// names); reports written before 2026-11-27 lack those errors, and their network stage is
    /// not re-applied (`learnable` is `None`). Errors on reports older than the per-episode
    /// errors of the refits (2026-11-24) when a paired comparison needs them, and on a rule
    /// outside its range.
    ///
    /// ```no_run
    /// # fn demo(d: gap::Diagnosis) -> Result<(), gap::GapError> {
    /// let floor = d.config.rule.min_shrinkage + 0.02;
    /// let stricter = gap::VerdictRule { min_shrinkage: floor, ..d.config.rule };
    /// println!("{} -> {}", d.verdict, d.rejudge(stricter)?.verdict);
    /// # Ok(()) }
    /// ```
    pub fn rejudge(&self, rule: VerdictRule) -> Result<Judgement, GapError> {
        rule.check()?;
        let config = DiagnoseConfig {
            rule,
            ..self.config.clone()
        };
        // The refit order: the candidates less the base effects (the probe comes last).
        let library = config
            .candidates
            .iter()
            .filter(|c| !config.base.iter().any(|b| b.effect == **c))
            .map(|c| {
                self.ranking
                    .iter()
                    .find(|r| r.effect == c.name())
                    .cloned()
                    .ok_or_else(|| {
                        GapError::Config(format!("{} is not in the report's ranking", c.name()))
                    })
            })
            .collect::<Result<Vec<_>, _>>()?;
        let mut judged = judge(&library, self.probe.as_ref(), &config)?;
        if let Some(l) = self
            .learnable
            .as_ref()
            .filter(|l| !l.network_per_episode_mde_cm.is_empty())
        {
            let (verdict, learnable) = learnable_stage(
                self,
                &judged.verdict,
                &rule,
                &l.network_per_episode_mde_cm,
                &l.backbone_per_episode_mde_cm,
            )?;
            judged.verdict = verdict;
            judged.learnable = Some(learnable);
        }
        Ok(judged)
    }

    /// The verdict the library's refits reach on their own, under the report's rule: the
    /// probe and a network stage left out. Where the report says `unknown` it names the
    /// significant library effect the probe outdid, or `none` when there is none: what a user
    /// who adds every effect that holds out adds next (`cargo xtask chain --add-past-unknown`).
    ///
    /// ```no_run
    /// # fn demo(d: gap::Diagnosis) -> Result<(), gap::GapError> {
    /// if d.verdict == "unknown" {
    ///     println!("the library alone: {}", d.library_verdict()?);
    /// }
    /// # Ok(()) }
    /// ```
    pub fn library_verdict(&self) -> Result<String, GapError> {
        let library_alone = Diagnosis {
            probe: None,
            learnable: None,
            ..self.clone()
        };
        Ok(library_alone.rejudge(self.config.rule)?.verdict)
    }
}
