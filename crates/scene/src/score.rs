use glam::Vec3;

use crate::{Scene, SceneError};

/// Errors of one predicted step against the truth, m. Only particles the tracker saw at that
/// frame count; a frame where it saw none is not scored ([`score_steps`] gives `None`).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct StepErrors {
    /// Mean distance between same-index points.
    pub mde: f64,
    /// One-sided Chamfer, prediction → truth, mean non-squared nearest distance (the PGRD
    /// code's convention).
    pub chamfer_pred_to_gt: f64,
    /// One-sided Chamfer, truth → prediction.
    pub chamfer_gt_to_pred: f64,
    /// Exact EMD, mean matched distance; NaN when not requested.
    pub emd: f64,
}

impl StepErrors {
    /// Two-sided Chamfer: the sum of both one-sided means (PGND's convention).
    pub fn chamfer_two_sided(&self) -> f64 {
        self.chamfer_pred_to_gt + self.chamfer_gt_to_pred
    }
}

fn check(scene: &Scene, pred: &[Vec<Vec3>]) -> Result<(), SceneError> {
    let bad = pred.len() != scene.truth.len() || pred.iter().any(|p| p.len() != scene.tracked);
    if bad {
        return Err(SceneError::PredictionShape {
            got: pred.len(),
            steps: scene.truth.len(),
            particles: pred.first().map_or(0, Vec::len),
        });
    }
    Ok(())
}

fn seen(scene: &Scene, step: usize, pred: &[Vec3]) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
    let vis = &scene.visible[step];
    let idx: Vec<usize> = (0..scene.tracked).filter(|i| vis[*i]).collect();
    let p = idx.iter().map(|i| pred[*i].to_array()).collect();
    let g = idx
        .iter()
        .map(|i| scene.truth[step][*i].to_array())
        .collect();
    (p, g)
}

/// Per-step errors of a prediction (`steps` × `tracked` positions, m); `None` at a step whose
/// frame the tracker saw no tracked point in (nothing to score there: its stored positions are
/// the tracker's last reports).
pub fn score_steps(
    scene: &Scene,
    pred: &[Vec<Vec3>],
    with_emd: bool,
) -> Result<Vec<Option<StepErrors>>, SceneError> {
    check(scene, pred)?;
    let mut solver = metrics::EmdSolver::new();
    pred.iter()
        .enumerate()
        .map(|(s, p)| {
            let (p, g) = seen(scene, s, p);
            if g.is_empty() {
                return Ok(None);
            }
            let c = metrics::chamfer(&p, &g)?;
            Ok(Some(StepErrors {
                mde: metrics::mde(&p, &g)?,
                chamfer_pred_to_gt: c.pred_to_gt,
                chamfer_gt_to_pred: c.gt_to_pred,
                emd: if with_emd {
                    solver.emd(&p, &g)?
                } else {
                    f64::NAN
                },
            }))
        })
        .collect()
}

/// Mean of `f` over the scored steps of `steps` (from [`score_steps`]); `None` when no step was
/// scored.
pub fn mean_over_steps(
    steps: &[Option<StepErrors>],
    f: impl Fn(&StepErrors) -> f64,
) -> Option<f64> {
    let (sum, n) = sum_over_steps(steps, f);
    (n > 0).then(|| sum / n as f64)
}

/// Sum of `f` over the scored steps of `steps`, and their number.
pub fn sum_over_steps(
    steps: &[Option<StepErrors>],
    f: impl Fn(&StepErrors) -> f64,
) -> (f64, usize) {
    let n = steps.iter().flatten().count();
    (steps.iter().flatten().map(f).sum::<f64>(), n)
}

/// Mean squared position error over all steps and seen particles, m²: the fitting loss (0 when
/// nothing was seen).
pub fn position_mse(scene: &Scene, pred: &[Vec<Vec3>]) -> Result<f64, SceneError> {
    check(scene, pred)?;
    let (mut sum, mut count) = (0.0f64, 0usize);
    for (s, p) in pred.iter().enumerate() {
        let vis = &scene.visible[s];
        for (i, (a, b)) in p.iter().zip(&scene.truth[s]).enumerate() {
            if vis[i] {
                sum += f64::from(a.distance_squared(*b));
                count += 1;
            }
        }
    }
    Ok(sum / count.max(1) as f64)
}

/// DEFORM's own score, m: the mean absolute coordinate error over all markers (driven ones
/// included), summed over the predicted steps and divided by the episode's frame count
/// (`steps + 2`: the two given frames count as zero error, as in DEFORM's code, which divides
/// by 500).
pub fn deform_l1(scene: &Scene, pred: &[Vec<Vec3>]) -> Result<f64, SceneError> {
    check(scene, pred)?;
    let per_step = pred.iter().zip(&scene.truth).map(|(p, g)| {
        let total: f64 = p
            .iter()
            .zip(g)
            .map(|(a, b)| f64::from((*a - *b).abs().element_sum()))
            .sum();
        total / (3 * p.len()) as f64
    });
    Ok(per_step.sum::<f64>() / (pred.len() + 2) as f64)
}
