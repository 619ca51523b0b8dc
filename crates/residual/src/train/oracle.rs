//! The greedy bounded oracle: how much of the backbone's error a perfect corrector could
//! remove under a residual bound, measured on training episodes without training anything.
//!
//! The network changes each free particle's velocity by at most `s` m/s per axis and step
//! ([`ModelConfig::residual_scale`](crate::ModelConfig), 0.1 in the paper). Whether that
//! leaves room for the correction a backbone needs depends on the object: a stem that folds
//! under gravity needs about `g dt` ≈ 1 m/s per 0.1 s step, a rope on a table far less. The
//! oracle rolls the backbone out over an episode's evaluation window and after every step
//! gives each free tracked particle seen in the next recorded frame the velocity change,
//! clamped to the bound, that moves it toward that frame (the guided rollout of
//! [`StartFrom::Guided`](crate::StartFrom)). It knows the next frame, which no network does,
//! but looks no further, so a corrector that anticipates could do better: it is a reference
//! for where the bound rather than the network limits the gain, not a forecast of what
//! training reaches (`docs/residual.md`, "The bound's ceiling").

use rayon::prelude::*;

use super::TrainSet;
use crate::{ResidualError, Result};

impl TrainSet {
    /// The greedy bounded oracle's rollout MDE (cm, scored as `cargo xtask eval` scores) with
    /// `bound` m/s per axis, per episode, for at most `max_episodes` of this set's episodes
    /// spread evenly over it (`⌊j · n / max⌋`; on episodes cut in order from recordings such a
    /// spread can fall on the recordings' starts, so `usize::MAX`, all of them, is the unbiased
    /// choice): pairs of (dataset index, MDE). `bound` 0 is the
    /// backbone alone. Episodes run in parallel on the current rayon pool; the result does not
    /// depend on the thread count.
    ///
    /// ```no_run
    /// # fn main() -> Result<(), residual::ResidualError> {
    /// let data = dataset::Dataset::open("fixtures/flag")?;
    /// let params = springs::SpringParams::reference_rope();
    /// let set = residual::TrainSet::new(&data, dataset::Split::Train, &params, &Default::default())?;
    /// let mean = |v: Vec<(usize, f64)>| v.iter().map(|e| e.1).sum::<f64>() / v.len() as f64;
    /// let backbone = mean(set.oracle_mde_cm(0.0, 30)?);
    /// let paper_bound = mean(set.oracle_mde_cm(0.1, 30)?);
    /// println!("at 0.1 m/s a perfect corrector removes {:.0} %", 100.0 * (1.0 - paper_bound / backbone));
    /// # Ok(()) }
    /// ```
    pub fn oracle_mde_cm(&self, bound: f32, max_episodes: usize) -> Result<Vec<(usize, f64)>> {
        if !(bound.is_finite() && bound >= 0.0) {
            return Err(ResidualError::Input(format!(
                "oracle bound must be finite and >= 0, got {bound} m/s"
            )));
        }
        let n = self.episodes.len();
        let count = max_episodes.max(1);
        let which: Vec<usize> = if n <= count {
            (0..n).collect()
        } else {
            (0..count).map(|j| j * n / count).collect()
        };
        which
            .par_iter()
            .map(|&e| {
                let ep = &self.episodes[e];
                let traj = self.guided_trajectory(ep, bound)?;
                // Entries 0–2 of a trajectory are the history and the start state.
                let pred: Vec<_> = traj.x[3..]
                    .iter()
                    .map(|p| p[..ep.base.tracked].to_vec())
                    .collect();
                let steps = scene::score_steps(&ep.base, &pred, false)?;
                let mde = scene::mean_over_steps(&steps, |s| s.mde).unwrap_or(0.0);
                Ok((ep.index, 100.0 * mde))
            })
            .collect()
    }
}
