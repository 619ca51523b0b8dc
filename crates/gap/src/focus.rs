//! Where the backbone's residual points: a start for the `unknown` probe's window.
//!
//! A source of force the library has no term for, such as an attracting or repelling point,
//! pushes every particle toward or away from one place, so the residual displacements
//! `truth − backbone` of the tracked particles lie along lines through it. The point nearest
//! all those lines in the least-squares sense, each line weighted by its residual's squared
//! length (the particles the backbone misses most say the most), is where the probe's window
//! starts, and the weighted RMS distance of the lines from that point is its starting radius.
//! Residuals of a structural error point every which way: their point is somewhere near the
//! data and their spread is wide, so that start is a wide field. Only the refit's starting
//! point depends on it; the probe's form and ranges do not. A start can trap the refit in a
//! poor local fit, so the diagnosis refits the probe from this start and from its broad one
//! (a field about the data's mean) and keeps the lower training loss ([`ProbeStart`]).

use glam::{DMat3, DVec3, Vec3};
use scene::Scene;
use serde::{Deserialize, Serialize};

/// Training scenes whose backbone rollouts locate the focus (the first ones of the split).
pub const FOCUS_SCENES: usize = 32;

/// The point the backbone's residual displacements converge on (or diverge from).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResidualFocus {
    /// The point nearest the residual lines, m.
    pub point_m: [f32; 3],
    /// Weighted RMS distance of the residual lines from that point, m.
    pub spread_m: f32,
    /// Whether the residuals point toward the point (an attracting source) rather than away.
    pub attracting: bool,
}

impl ResidualFocus {
    /// [`ResidualFocus::point_m`] as a vector.
    pub fn point(&self) -> Vec3 {
        Vec3::from_array(self.point_m)
    }

    /// The probe's starting window radius, m: the spread, within the window's range
    /// ([`crate::PROBE_WINDOW_M`]).
    pub fn window_m(&self) -> f64 {
        let [lo, hi] = crate::PROBE_WINDOW_M;
        f64::from(self.spread_m).clamp(lo, hi)
    }
}

/// How the probe's refit started, in a diagnosis's report: it is refitted from the focus and
/// from its broad start (a field about the data's mean with a 1 m window), and the refit with
/// the lower training loss is kept. With a race ([`crate::DiagnoseConfig::race`] > 0) the two
/// starts are raced: both run half the generations, and only the one with the lower training
/// loss then is finished.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProbeStart {
    /// Where the backbone's training residuals converge.
    pub focus: ResidualFocus,
    /// Training loss of the refit started at the focus, m² (halfway when `raced`).
    pub focus_train_loss_m2: f64,
    /// Training loss of the refit started broad, m² (halfway when `raced`).
    pub broad_train_loss_m2: f64,
    /// Whether the kept refit is the one started at the focus.
    pub from_focus: bool,
    /// The starts were raced: the losses above are both refits' halfway ones, on
    /// [`crate::RACE_SCENES`] training scenes (false in reports written before the race, and
    /// without one).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub raced: bool,
}

/// The focus of the residuals `scene.truth − prediction` over the tracked, visible positions
/// of `scenes` (`predictions` index-aligned, positions after each step; `None`: a rollout that
/// failed, left out). A faint pull toward `prior` (a thousandth of the lines' mean weight) keeps
/// the point defined when the lines are parallel (a uniform residual). `None` when there is
/// no residual at all.
///
/// ```
/// use glam::Vec3;
/// // Residuals pointing at (1, 0, 0) from three places: the lines meet there.
/// let truth = [Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 1.0, 0.0), Vec3::new(1.0, 0.0, 2.0)];
/// let pred: Vec<Vec3> = truth.iter().map(|t| *t - (Vec3::new(1.0, 0.0, 0.0) - *t) * 0.01).collect();
/// let f = gap::focus_of_lines(&[(truth.to_vec(), pred)], Vec3::ZERO).unwrap();
/// assert!((f.point() - Vec3::new(1.0, 0.0, 0.0)).length() < 1e-3);
/// assert!(f.attracting && f.spread_m < 1e-3);
/// ```
pub fn residual_focus(
    scenes: &[Scene],
    predictions: &[Option<Vec<Vec<Vec3>>>],
    prior: Vec3,
) -> Option<ResidualFocus> {
    let mut pairs = Vec::new();
    for (s, p) in scenes.iter().zip(predictions) {
        let Some(p) = p else { continue };
        for (t, frame) in p.iter().enumerate().take(s.truth.len()) {
            let (mut truth, mut pred) = (Vec::new(), Vec::new());
            for (i, p) in frame.iter().enumerate().take(s.tracked) {
                if s.visible[t][i] {
                    truth.push(s.truth[t][i]);
                    pred.push(*p);
                }
            }
            pairs.push((truth, pred));
        }
    }
    focus_of_lines(&pairs, prior)
}

/// [`residual_focus`] of explicit `(truth, prediction)` position pairs, m: each residual
/// `truth − prediction` is a line through the truth along it.
pub fn focus_of_lines(pairs: &[(Vec<Vec3>, Vec<Vec3>)], prior: Vec3) -> Option<ResidualFocus> {
    let lines = || {
        pairs.iter().flat_map(|(truth, pred)| {
            truth.iter().zip(pred).filter_map(|(t, p)| {
                let x = t.as_dvec3();
                let r = x - p.as_dvec3();
                let w = r.length_squared();
                // The projector onto the plane across the line: distances from it.
                (w > 0.0 && w.is_finite()).then(|| {
                    let u = r / w.sqrt();
                    let across = DMat3::IDENTITY - DMat3::from_cols(u * u.x, u * u.y, u * u.z);
                    (x, r, w, across)
                })
            })
        })
    };
    let (mut a, mut b, mut total) = (DMat3::ZERO, DVec3::ZERO, 0.0);
    for (x, _, w, across) in lines() {
        a += across * w;
        b += across * x * w;
        total += w;
    }
    if total <= 0.0 {
        return None;
    }
    let prior = prior.as_dvec3();
    let ridge = 1e-3 * (a.x_axis.x + a.y_axis.y + a.z_axis.z) / 3.0;
    let point = (a + DMat3::IDENTITY * ridge).inverse() * (b + prior * ridge);
    if !point.is_finite() {
        return None;
    }
    let (mut spread2, mut toward) = (0.0, 0.0);
    for (x, r, w, across) in lines() {
        spread2 += w * (across * (point - x)).length_squared();
        toward += r.dot(point - x);
    }
    Some(ResidualFocus {
        point_m: point.as_vec3().to_array(),
        spread_m: (spread2 / total).sqrt() as f32,
        attracting: toward > 0.0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Residuals pointing toward `c` (`sign` +1, an attracting source) or away from it (−1),
    /// plus noise of the given spread, m.
    fn radial(c: Vec3, sign: f32, noise: f32) -> Vec<(Vec<Vec3>, Vec<Vec3>)> {
        let mut state = 7u32;
        let mut rnd = move || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        (0..5)
            .map(|_| {
                let truth: Vec<Vec3> = (0..40)
                    .map(|_| c + Vec3::new(rnd(), rnd(), rnd()) * 0.6)
                    .collect();
                let pred = truth
                    .iter()
                    .map(|t| {
                        let r = (c - *t).normalize() * 0.02 * sign
                            + Vec3::new(rnd(), rnd(), rnd()) * noise;
                        *t - r
                    })
                    .collect();
                (truth, pred)
            })
            .collect()
    }

    #[test]
    fn finds_an_attracting_and_a_repelling_source() {
        let c = Vec3::new(0.25, 0.2, 0.0);
        let pull = focus_of_lines(&radial(c, 1.0, 0.002), Vec3::ZERO).unwrap();
        assert!((pull.point() - c).length() < 0.02, "{pull:?}");
        assert!(pull.attracting);
        let push = focus_of_lines(&radial(c, -1.0, 0.002), Vec3::ZERO).unwrap();
        assert!((push.point() - c).length() < 0.02, "{push:?}");
        assert!(!push.attracting);
        // Noisier residuals: the lines pass farther from the point.
        let noisy = focus_of_lines(&radial(c, 1.0, 0.02), Vec3::ZERO).unwrap();
        assert!(
            noisy.spread_m > 2.0 * pull.spread_m,
            "{noisy:?} vs {pull:?}"
        );
    }

    #[test]
    fn parallel_residuals_stay_near_the_prior_and_nothing_gives_none() {
        // A uniform residual (every particle off by the same vector): the lines are parallel
        // and meet nowhere; the faint prior picks the point on them nearest to it.
        let truth: Vec<Vec3> = (0..20)
            .map(|i| Vec3::new(i as f32 * 0.01, 0.0, 0.0))
            .collect();
        let pred: Vec<Vec3> = truth.iter().map(|t| *t - Vec3::Z * 0.01).collect();
        let prior = Vec3::new(0.1, 0.3, 0.5);
        let f = focus_of_lines(&[(truth.clone(), pred)], prior).unwrap();
        assert!(f.point().is_finite());
        // Across the lines the point is their mean (x 0.095, y 0); along them, the prior's z.
        assert!(
            (f.point() - Vec3::new(0.095, 0.0, prior.z)).length() < 1e-3,
            "{f:?}"
        );
        assert!(focus_of_lines(&[(truth.clone(), truth)], prior).is_none());
        assert!(focus_of_lines(&[], prior).is_none());
    }
}
