//! Training losses: what a training rollout's step is scored with.

use candle_core::{DType, Tensor};
use glam::Vec3;
use scene::Scene;
use serde::{Deserialize, Serialize};

use crate::Result;
use crate::rollout::to_tensor;

/// Per-step training loss over the tracked particles the tracker saw (summed over a segment's
/// steps).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TrainLoss {
    /// Mean squared distance to the truth, cm² (the paper's MSE). A particle's pull grows with
    /// its error, so segments the residual cannot fix (errors of tens of cm) dominate.
    #[default]
    Mse,
    /// Mean Euclidean distance to the truth, cm: the evaluation metric MDE itself, smoothed
    /// within [`DISTANCE_EPS_CM`] of zero. Every particle pulls with unit strength, whatever its
    /// error (`docs/residual-log.md`, "Why PGRD was worse on the teddy").
    Distance,
}

/// Smoothing of [`TrainLoss::Distance`] near zero, cm: a particle at distance `d` costs
/// `sqrt(d² + ε²)`, so the gradient is defined at `d = 0` (within a millimetre of the truth the
/// loss behaves like a squared one); for `d ≥ 1 cm` it exceeds `d` by at most 0.005 cm.
pub const DISTANCE_EPS_CM: f64 = 0.1;

impl TrainLoss {
    /// Name as written in `train.json` and taken by `cargo xtask train --loss`.
    pub fn name(self) -> &'static str {
        match self {
            TrainLoss::Mse => "mse",
            TrainLoss::Distance => "distance",
        }
    }

    /// Unit of the loss values.
    pub fn unit(self) -> &'static str {
        match self {
            TrainLoss::Mse => "cm²",
            TrainLoss::Distance => "cm",
        }
    }
}

/// Loss of step `step` of `scene` given the hybrid positions `x` (metres, `N × 3`, with their
/// graph): over the tracked particles seen at that step (0 when none was).
pub(crate) fn step_loss(kind: TrainLoss, scene: &Scene, step: usize, x: &Tensor) -> Result<Tensor> {
    let dev = x.device();
    let vis = &scene.visible[step];
    let idx: Vec<u32> = (0..scene.tracked)
        .filter(|&i| vis[i])
        .map(|i| i as u32)
        .collect();
    let truth: Vec<Vec3> = idx.iter().map(|&i| scene.truth[step][i as usize]).collect();
    let ids = Tensor::from_slice(&idx, idx.len(), dev)?;
    let diff = (x.index_select(&ids, 0)? - to_tensor(&truth, dev)?)?;
    let count = idx.len().max(1) as f64;
    Ok(match kind {
        TrainLoss::Mse => {
            let m = diff.sqr()?.sum_all()?.to_dtype(DType::F32)?;
            (m * (1e4 / count))?
        }
        TrainLoss::Distance => {
            let eps2 = DISTANCE_EPS_CM * DISTANCE_EPS_CM;
            // Squared distances in cm², per particle.
            let d2 = (diff.sqr()?.sum(1)? * 1e4)?;
            let d = (d2 + eps2)?.sqrt()?;
            (d.sum_all()? / count)?
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;
    use scene::{Protocol, SceneConfig};

    /// A fixture scene whose first step's truth is a 0.1 m spaced line, with every other
    /// tracked particle unseen; returns it and positions whose seen particles are 1, 2 or 3 cm
    /// from the truth along x, y or z, and whose unseen ones are 50 cm off (must not count).
    fn case() -> (Scene, Tensor, f64, f64) {
        let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/rope");
        let data = dataset::Dataset::open(root).unwrap();
        let ep = data.load_episode(0).unwrap();
        let window = Protocol::Paper.window(ep.frames()).unwrap();
        let mut scene = Scene::new(&data.meta, &ep, window, &SceneConfig::default()).unwrap();
        let t = scene.tracked;
        scene.truth[0] = (0..t)
            .map(|i| Vec3::new(0.1 * i as f32, 0.0, 0.5))
            .collect();
        scene.visible[0] = (0..t).map(|i| i % 2 == 0).collect();
        let (mut sum_cm, mut sum_cm2, mut seen) = (0.0, 0.0, 0usize);
        let x: Vec<Vec3> = (0..scene.particles())
            .map(|i| {
                if i >= t {
                    return Vec3::splat(9.0);
                }
                let base = scene.truth[0][i];
                if i % 2 == 1 {
                    return base + Vec3::new(0.5, 0.0, 0.0);
                }
                let d_cm = (1 + i % 3) as f64;
                sum_cm += d_cm;
                sum_cm2 += d_cm * d_cm;
                seen += 1;
                let mut off = Vec3::ZERO;
                off[(i / 2) % 3] = d_cm as f32 / 100.0;
                base + off
            })
            .collect();
        let x = to_tensor(&x, &Device::Cpu).unwrap();
        (scene, x, sum_cm / seen as f64, sum_cm2 / seen as f64)
    }

    #[test]
    fn distance_loss_is_the_mean_distance_of_seen_particles_in_cm() {
        let (scene, x, mde_cm, _) = case();
        let l = step_loss(TrainLoss::Distance, &scene, 0, &x).unwrap();
        let l = f64::from(l.to_scalar::<f32>().unwrap());
        // sqrt(d² + ε²) is within ε²/(2d) = 0.005 cm of d for d ≥ 1 cm.
        assert!((l - mde_cm).abs() < 0.01, "{l} vs {mde_cm} cm");
    }

    #[test]
    fn mse_loss_is_the_mean_squared_distance_of_seen_particles_in_cm2() {
        let (scene, x, _, mse_cm2) = case();
        let l = step_loss(TrainLoss::Mse, &scene, 0, &x).unwrap();
        let l = f64::from(l.to_scalar::<f32>().unwrap());
        assert!((l - mse_cm2).abs() < 1e-3 * mse_cm2, "{l} vs {mse_cm2} cm²");
    }

    #[test]
    fn distance_loss_is_epsilon_at_the_truth_with_a_finite_gradient() {
        let (scene, _, _, _) = case();
        let mut x = scene.truth[0].clone();
        x.resize(scene.particles(), Vec3::ZERO);
        let var = candle_core::Var::from_tensor(&to_tensor(&x, &Device::Cpu).unwrap()).unwrap();
        let l = step_loss(TrainLoss::Distance, &scene, 0, var.as_tensor()).unwrap();
        let l0 = f64::from(l.to_scalar::<f32>().unwrap());
        assert!((l0 - DISTANCE_EPS_CM).abs() < 1e-6, "{l0}");
        let g = l.backward().unwrap();
        let g = g
            .get(var.as_tensor())
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap();
        assert!(g.to_scalar::<f32>().unwrap().is_finite());
    }

    #[test]
    fn configurations_without_a_loss_mean_mse() {
        let v: TrainLoss = serde_json::from_str("\"distance\"").unwrap();
        assert_eq!(v, TrainLoss::Distance);
        assert_eq!(TrainLoss::default(), TrainLoss::Mse);
    }
}
