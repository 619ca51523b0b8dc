//! Held-out rollout error: choosing a checkpoint by what evaluation measures, on training
//! episodes the optimiser never samples (never on the split a report is made on).

use rayon::prelude::*;

use super::TrainSet;
use crate::{ResidualError, ResidualNet, Result, RolloutOptions, hybrid_rollout};

impl TrainSet {
    /// Moves the last `count` episodes of this set into a new one (for
    /// [`TrainSet::rollout_mde_cm`]). Datasets cut each recording into consecutive, overlapping
    /// episodes in order (the generated ones: ten per recording, each sharing half its frames
    /// with the next), so a block at the end holds whole recordings, shares no frames with the
    /// episodes left to train on (but at one boundary when `count` splits a recording), and
    /// mixes early and late parts of a recording as the val split does. (Until session 44 the
    /// episodes were spread evenly, `⌊j · n / count⌋`: with ten episodes per recording and 20
    /// of 100 held out, those are the 1st and 6th of every recording, half of them a
    /// recording's start from rest, each overlapping its training neighbours; docs/residual.md.)
    /// Errors when fewer than one episode would be left to train on.
    pub fn hold_out(&mut self, count: usize) -> Result<TrainSet> {
        let n = self.episodes.len();
        if count == 0 || count >= n {
            return Err(ResidualError::Input(format!(
                "cannot hold out {count} of {n} training episodes (need 1 ..= {})",
                n.saturating_sub(1)
            )));
        }
        let held = self.episodes.split_off(n - count);
        Ok(TrainSet {
            episodes: held,
            meta: self.meta.clone(),
            params: self.params,
            scene_cfg: self.scene_cfg.clone(),
            options: self.options.clone(),
        })
    }

    /// Dataset indices of this set's episodes.
    pub fn episode_indices(&self) -> Vec<usize> {
        self.episodes.iter().map(|e| e.index).collect()
    }

    /// Per episode, the mean distance (cm) between predicted and recorded positions of the
    /// seen tracked particles over every step of its evaluation window, as `cargo xtask eval`
    /// scores it (its MDE is the mean of these): free-running from the window's start frame,
    /// the hybrid model's rollout when `net` is given, else the backbone's. A diverged hybrid
    /// rollout scores infinity. Episodes run in parallel on the current rayon pool; the result
    /// does not depend on the thread count.
    pub fn rollout_mde_cm(&self, net: Option<&ResidualNet>) -> Result<Vec<f64>> {
        self.episodes
            .par_iter()
            .map(|ep| {
                let scene = &ep.base;
                let mut pred = match net {
                    Some(net) => match hybrid_rollout(
                        net,
                        &ep.backbone,
                        scene,
                        &ep.history,
                        RolloutOptions::default(),
                    ) {
                        Ok(r) => r.positions,
                        Err(ResidualError::Diverged { .. }) => return Ok(f64::INFINITY),
                        Err(e) => return Err(e),
                    },
                    None => {
                        let mut p = ep.backbone.rollout(&scene.init, &scene.actions)?.positions;
                        p.remove(0);
                        p
                    }
                };
                for p in &mut pred {
                    p.truncate(scene.tracked);
                }
                let steps = scene::score_steps(scene, &pred, false)?;
                // An episode the tracker saw nothing of scores 0 for every model: a paired
                // comparison is unaffected.
                let (sum, n) = scene::sum_over_steps(&steps, |s| s.mde);
                Ok(100.0 * sum / n.max(1) as f64)
            })
            .collect()
    }
}

/// Whether `candidate` beats `current` on the same held-out episodes (per-episode errors,
/// e.g. [`TrainSet::rollout_mde_cm`]) by more than one standard error: the mean of the paired
/// differences `current − candidate` must exceed its standard error (sample standard deviation
/// over √n). The one-standard-error rule of model selection: keep the simpler model (the
/// network at step 0, i.e. nearly the backbone, or an earlier choice) unless the held-out
/// evidence against it is clear. Per-episode errors of a few held-out episodes vary by
/// centimetres, while a network that is worse on unseen episodes can still score slightly
/// better on them (`docs/residual-log.md`, "Why PGRD was worse on the teddy"). False for
/// mismatched lengths, fewer than two episodes or any non-finite error.
pub fn clearly_better(candidate: &[f64], current: &[f64]) -> bool {
    paired_difference(candidate, current).is_some_and(|(mean, se)| mean > se)
}

/// The mean of the paired differences `current − candidate` over episodes and its standard
/// error (sample standard deviation over √n), in the errors' unit: what [`clearly_better`]
/// compares. `None` for mismatched lengths, fewer than two episodes or any non-finite error.
pub fn paired_difference(candidate: &[f64], current: &[f64]) -> Option<(f64, f64)> {
    let n = candidate.len();
    if n < 2 || current.len() != n {
        return None;
    }
    if candidate.iter().chain(current).any(|e| !e.is_finite()) {
        return None;
    }
    let d: Vec<f64> = current.iter().zip(candidate).map(|(a, b)| a - b).collect();
    let mean = d.iter().sum::<f64>() / n as f64;
    let var = d.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (n - 1) as f64;
    Some((mean, (var / n as f64).sqrt()))
}
