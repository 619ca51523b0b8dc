//! Why a run stopped, and the bookkeeping behind the tolerance-based criteria.

use serde::{Deserialize, Serialize};

/// The reason a [`crate::CmaEs`] run (or a restart sequence) ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum StopReason {
    /// The best fitness reached [`crate::Termination::target`].
    TargetReached,
    /// The evaluation budget [`crate::Termination::max_evaluations`] is spent.
    MaxEvaluations,
    /// [`crate::Termination::max_generations`] generations have run.
    MaxGenerations,
    /// Recent fitness values lie within [`crate::Termination::tol_fun`] of each other.
    TolFun,
    /// All sampling standard deviations are below [`crate::Termination::tol_x`].
    TolX,
    /// The condition number of `C` exceeds [`crate::Termination::max_condition`].
    ConditionCov,
    /// The step size grew by more than [`crate::Termination::tol_up_sigma`] (divergence).
    TolUpSigma,
    /// Adding 0.1 σ along a principal axis no longer changes the mean (floating-point floor).
    NoEffectAxis,
    /// Adding 0.2 σ √C_ii to a coordinate no longer changes the mean.
    NoEffectCoord,
    /// The median of recent best and median fitness values stopped improving.
    Stagnation,
    /// The state contains a non-finite number; nothing sensible can follow.
    NumericalInstability,
}

impl StopReason {
    /// Whether a restart can make progress after this stop: `false` for reaching the target and
    /// for exhausting the (global) evaluation budget.
    pub fn restartable(self) -> bool {
        !matches!(self, Self::TargetReached | Self::MaxEvaluations)
    }
}

/// Median of a slice (the mean of the two middle values for an even length).
pub(crate) fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let k = v.len();
    if k == 0 {
        f64::NAN
    } else if k % 2 == 1 {
        v[k / 2]
    } else {
        0.5 * (v[k / 2 - 1] + v[k / 2])
    }
}

/// Appends `value` and drops the oldest entries beyond `cap`.
pub(crate) fn push_capped(history: &mut Vec<f64>, value: f64, cap: usize) {
    history.push(value);
    if history.len() > cap {
        let excess = history.len() - cap;
        history.drain(..excess);
    }
}

/// Length of the best-fitness history for the `TolFun` test: `10 + ⌈30 n / λ⌉`.
pub(crate) fn tolfun_window(n: usize, lambda: usize) -> usize {
    10 + (30 * n).div_ceil(lambda)
}

/// Length of the window for the stagnation test: `⌈100 + 100 n^1.5 / λ⌉` (pycma's
/// `tolstagnation` default).
pub(crate) fn stagnation_window(n: usize, lambda: usize) -> usize {
    (100.0 + 100.0 * (n as f64).powf(1.5) / lambda as f64).ceil() as usize
}

/// Number of newest and oldest entries compared by the stagnation test.
pub(crate) const STAGNATION_SAMPLE: usize = 20;

/// `true` when the newest entries of a full window are, in median, no better than its oldest.
pub(crate) fn stagnated(history: &[f64], window: usize) -> bool {
    if history.len() < window || window < 2 * STAGNATION_SAMPLE {
        return false;
    }
    let old = median(&history[..STAGNATION_SAMPLE]);
    let new = median(&history[history.len() - STAGNATION_SAMPLE..]);
    new >= old
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_and_windows() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), 2.5);
        assert_eq!(tolfun_window(10, 10), 40);
        assert_eq!(stagnation_window(10, 10), 417);
        let mut h = vec![];
        for i in 0..5 {
            push_capped(&mut h, i as f64, 3);
        }
        assert_eq!(h, vec![2.0, 3.0, 4.0]);
    }

    #[test]
    fn stagnation_needs_a_full_window_without_progress() {
        let improving: Vec<f64> = (0..100).map(|i| 100.0 - i as f64).collect();
        assert!(!stagnated(&improving, 100));
        let flat = vec![1.0; 100];
        assert!(stagnated(&flat, 100));
        assert!(!stagnated(&flat[..99], 100));
    }
}
