//! Aggregation of per-step rollout errors over episodes, as in the paper's tables.

use serde::Serialize;

use crate::error::MetricsError;

/// Per-step statistics of an error metric over episodes, aggregated as the paper's tables do:
/// for each rollout step the mean and the standard deviation over episodes; the reported value
/// is the mean over steps of the per-step means, and the "±" is the mean over steps of the
/// per-step standard deviations.
///
/// The standard deviation is the population one (divide by the number of episodes, numpy's
/// default `ddof=0`), as the reference code's `np.std` would give.
///
/// ```
/// use metrics::RolloutAggregate;
/// // Two episodes, three steps each (metres).
/// let curves = vec![vec![0.01, 0.02, 0.03], vec![0.03, 0.04, 0.05]];
/// let agg = RolloutAggregate::from_per_episode_curves(&curves)?;
/// assert_eq!(agg.per_step_mean.len(), 3);
/// assert!((agg.mean - 0.03).abs() < 1e-15);
/// assert!((agg.std - 0.01).abs() < 1e-15); // every step: values +-0.01 around the mean
/// let cm = agg.scaled(100.0); // the tables report cm
/// assert!((cm.mean - 3.0).abs() < 1e-12);
/// # Ok::<(), metrics::MetricsError>(())
/// ```
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RolloutAggregate {
    /// Mean over steps of the per-step means.
    pub mean: f64,
    /// Mean over steps of the per-step standard deviations (the tables' "±").
    pub std: f64,
    /// Mean over episodes at each step.
    pub per_step_mean: Vec<f64>,
    /// Population standard deviation over episodes at each step.
    pub per_step_std: Vec<f64>,
    /// Number of episodes aggregated.
    pub episodes: usize,
}

impl RolloutAggregate {
    /// Aggregates `curves[episode][step]`. All curves must have the same, non-zero length.
    ///
    /// # Errors
    /// No episodes, empty or unequal-length curves, or non-finite values.
    pub fn from_per_episode_curves(curves: &[Vec<f64>]) -> Result<Self, MetricsError> {
        let bad = |m: String| Err(MetricsError::InvalidCurves(m));
        let Some(first) = curves.first() else {
            return bad("no episodes".into());
        };
        let steps = first.len();
        if steps == 0 {
            return bad("curves have no steps".into());
        }
        for (e, c) in curves.iter().enumerate() {
            if c.len() != steps {
                return bad(format!(
                    "episode {e} has {} steps, episode 0 has {steps}",
                    c.len()
                ));
            }
            if let Some(s) = c.iter().position(|x| !x.is_finite()) {
                return bad(format!("episode {e} has a non-finite value at step {s}"));
            }
        }
        let n = curves.len() as f64;
        let per_step_mean: Vec<f64> = (0..steps)
            .map(|s| curves.iter().map(|c| c[s]).sum::<f64>() / n)
            .collect();
        // Two-pass variance (around the mean) for accuracy.
        let per_step_std: Vec<f64> = (0..steps)
            .map(|s| {
                let m = per_step_mean[s];
                (curves.iter().map(|c| (c[s] - m) * (c[s] - m)).sum::<f64>() / n).sqrt()
            })
            .collect();
        let k = steps as f64;
        Ok(Self {
            mean: per_step_mean.iter().sum::<f64>() / k,
            std: per_step_std.iter().sum::<f64>() / k,
            per_step_mean,
            per_step_std,
            episodes: curves.len(),
        })
    }

    /// As [`RolloutAggregate::from_per_episode_curves`], for curves with gaps: `None` where an
    /// episode has no value at a step (e.g. the tracker saw nothing there). Each step's mean and
    /// standard deviation are over the episodes with a value there; a step no episode has a
    /// value at gets NaN for both and is left out of [`mean`](Self::mean) and
    /// [`std`](Self::std). Without gaps the result equals `from_per_episode_curves`'s.
    ///
    /// # Errors
    /// No episodes, unequal-length curves, a non-finite value, or no value at all.
    pub fn from_per_episode_curves_with_gaps(
        curves: &[Vec<Option<f64>>],
    ) -> Result<Self, MetricsError> {
        let bad = |m: String| Err(MetricsError::InvalidCurves(m));
        let Some(first) = curves.first() else {
            return bad("no episodes".into());
        };
        let steps = first.len();
        for (e, c) in curves.iter().enumerate() {
            if c.len() != steps {
                return bad(format!(
                    "episode {e} has {} steps, episode 0 has {steps}",
                    c.len()
                ));
            }
            if let Some(s) = c.iter().position(|x| x.is_some_and(|x| !x.is_finite())) {
                return bad(format!("episode {e} has a non-finite value at step {s}"));
            }
        }
        let at = |s: usize| curves.iter().filter_map(move |c| c[s]);
        let per_step_mean: Vec<f64> = (0..steps)
            .map(|s| {
                let n = at(s).count();
                if n == 0 {
                    f64::NAN
                } else {
                    at(s).sum::<f64>() / n as f64
                }
            })
            .collect();
        let per_step_std: Vec<f64> = (0..steps)
            .map(|s| {
                let (m, n) = (per_step_mean[s], at(s).count());
                if n == 0 {
                    f64::NAN
                } else {
                    (at(s).map(|x| (x - m) * (x - m)).sum::<f64>() / n as f64).sqrt()
                }
            })
            .collect();
        let scored: Vec<usize> = (0..steps).filter(|s| at(*s).next().is_some()).collect();
        if scored.is_empty() {
            return bad("no episode has a value at any step".into());
        }
        let k = scored.len() as f64;
        Ok(Self {
            mean: scored.iter().map(|s| per_step_mean[*s]).sum::<f64>() / k,
            std: scored.iter().map(|s| per_step_std[*s]).sum::<f64>() / k,
            per_step_mean,
            per_step_std,
            episodes: curves.len(),
        })
    }

    /// Every value multiplied by `factor` (e.g. 100 for metres -> cm, as the tables report).
    pub fn scaled(&self, factor: f64) -> Self {
        Self {
            mean: self.mean * factor,
            std: self.std * factor.abs(),
            per_step_mean: self.per_step_mean.iter().map(|x| x * factor).collect(),
            per_step_std: self.per_step_std.iter().map(|x| x * factor.abs()).collect(),
            episodes: self.episodes,
        }
    }
}
