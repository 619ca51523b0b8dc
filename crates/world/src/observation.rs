//! The observation model: what a point tracker makes of the true positions.

use glam::Vec3;
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::Error;

/// Tracking noise, slow drift and occlusion of the tracked points (the gripper position comes
/// from the robot and is exact).
///
/// Per tracked point and stored frame k (Δ = 0.1 s):
/// - observed = true + drift_k + noise_k, noise ~ N(0, σ_n²) per axis, independent per frame;
/// - drift is an Ornstein–Uhlenbeck process per axis: stationary std σ_d, correlation time τ_d:
///   `drift_{k+1} = e^{−Δ/τ_d} drift_k + σ_d √(1 − e^{−2Δ/τ_d}) ξ`;
/// - occlusion is a two-state Markov chain: a visible point becomes occluded with probability
///   `1 − e^{−λΔ}` (λ = `occlusion_rate_hz`, or `near_gripper_rate_hz` within
///   `near_gripper_radius_m` of the gripper) and reappears with probability `1 − e^{−Δ/T}`
///   (T = `occlusion_mean_s`). While occluded, `visible` is 0 and the stored position stays at
///   the last visible observation (the tracker holds it).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Observation {
    /// White tracking noise σ_n per axis, m.
    pub noise_std_m: f32,
    /// Stationary drift σ_d per axis, m.
    pub drift_std_m: f32,
    /// Drift correlation time τ_d, s.
    pub drift_time_s: f32,
    /// Rate at which a visible point gets occluded, 1/s.
    pub occlusion_rate_hz: f32,
    /// Mean occlusion duration T, s.
    pub occlusion_mean_s: f32,
    /// Occlusion rate for points near the gripper (fingers hide them), 1/s.
    pub near_gripper_rate_hz: f32,
    /// What counts as near the gripper, m.
    pub near_gripper_radius_m: f32,
}

impl Default for Observation {
    /// Millimetre-level tracking: 1 mm noise, 2 mm drift over 3 s; in steady state about 2 % of
    /// the points away from the gripper are occluded and about half of those near it.
    fn default() -> Self {
        Observation {
            noise_std_m: 0.001,
            drift_std_m: 0.002,
            drift_time_s: 3.0,
            occlusion_rate_hz: 0.04,
            occlusion_mean_s: 0.4,
            near_gripper_rate_hz: 2.0,
            near_gripper_radius_m: 0.04,
        }
    }
}

impl Observation {
    /// Perfect observation: the true positions, always visible.
    pub fn none() -> Self {
        Observation {
            noise_std_m: 0.0,
            drift_std_m: 0.0,
            drift_time_s: 1.0,
            occlusion_rate_hz: 0.0,
            occlusion_mean_s: 0.4,
            near_gripper_rate_hz: 0.0,
            near_gripper_radius_m: 0.0,
        }
    }

    /// Parses `none` or `default`.
    pub fn parse(spec: &str) -> Result<Self, Error> {
        match spec.trim() {
            "none" => Ok(Observation::none()),
            "default" => Ok(Observation::default()),
            other => Err(Error::Config(format!(
                "unknown observation model '{other}' (expected 'none' or 'default')"
            ))),
        }
    }

    /// Checks that every number is finite and in range.
    pub fn validate(&self) -> Result<(), Error> {
        let ok = |v: f32| v.is_finite() && v >= 0.0;
        let all = [
            self.noise_std_m,
            self.drift_std_m,
            self.occlusion_rate_hz,
            self.near_gripper_rate_hz,
            self.near_gripper_radius_m,
        ]
        .into_iter()
        .all(ok);
        if !(all && self.drift_time_s > 0.0 && self.drift_time_s.is_finite()) {
            return Err(Error::Config(
                "observation: noise, drift, rates and radius must be finite and >= 0; drift time > 0"
                    .into(),
            ));
        }
        if !(self.occlusion_mean_s > 0.0 && self.occlusion_mean_s.is_finite()) {
            return Err(Error::Config(
                "observation: occlusion mean must be > 0 s".into(),
            ));
        }
        Ok(())
    }

    /// Observes `truth` (`[frames × n]`, frame-major) with gripper positions `gripper`
    /// (`[frames]`) sampled every `dt` seconds; returns observed positions and visibility flags.
    pub(crate) fn apply(
        &self,
        truth: &[Vec3],
        n: usize,
        gripper: &[Vec3],
        dt: f32,
        rng: &mut impl Rng,
    ) -> (Vec<Vec3>, Vec<u8>) {
        let frames = truth.len() / n.max(1);
        let keep = (-dt / self.drift_time_s).exp();
        let kick = self.drift_std_m * (1.0 - keep * keep).sqrt();
        let p_on = 1.0 - (-self.occlusion_rate_hz * dt).exp();
        let p_on_near = 1.0 - (-self.near_gripper_rate_hz * dt).exp();
        let p_off = 1.0 - (-dt / self.occlusion_mean_s).exp();
        let mut drift: Vec<Vec3> = (0..n).map(|_| normal(rng) * self.drift_std_m).collect();
        let mut hidden = vec![false; n];
        let mut observed = Vec::with_capacity(truth.len());
        let mut visible = Vec::with_capacity(truth.len());
        for k in 0..frames {
            for i in 0..n {
                let t = truth[k * n + i];
                if k > 0 {
                    drift[i] = drift[i] * keep + normal(rng) * kick;
                    let u: f32 = rng.random_range(0.0..1.0);
                    hidden[i] = if hidden[i] {
                        u >= p_off
                    } else {
                        let near = t.distance(gripper[k]) < self.near_gripper_radius_m;
                        u < if near { p_on_near } else { p_on }
                    };
                }
                let noise = normal(rng) * self.noise_std_m;
                if hidden[i] {
                    // Hold the last visible observation.
                    let last = observed[(k - 1) * n + i];
                    observed.push(last);
                    visible.push(0);
                } else {
                    observed.push(t + drift[i] + noise);
                    visible.push(1);
                }
            }
        }
        (observed, visible)
    }
}

fn normal(rng: &mut impl Rng) -> Vec3 {
    Vec3::new(
        StandardNormal.sample(rng),
        StandardNormal.sample(rng),
        StandardNormal.sample(rng),
    )
}
