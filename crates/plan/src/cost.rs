//! The planning objective: Chamfer distance of predicted states to a target point cloud, plus
//! penalties for gripper positions outside the workspace or inside obstacles.

use glam::Vec3;
use metrics::PointIndex;
use serde::{Deserialize, Serialize};
use springs::BoxObstacle;

use crate::nearest::{MAX_PAIRS, Target};
use crate::{PlanError, Result};

/// Which predicted states the Chamfer term reads.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CostMode {
    /// The state at the end of the horizon.
    #[default]
    Final,
    /// The mean over every step of the horizon (rewards getting there early).
    Running,
}

/// The axis-aligned box the grippers must stay in, m.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Workspace {
    /// Lower corner, m.
    pub min: Vec3,
    /// Upper corner, m.
    pub max: Vec3,
}

impl Workspace {
    /// How far `p` lies outside the workspace, m (0 inside).
    pub fn outside(&self, p: Vec3) -> f32 {
        (self.min - p).max(p - self.max).max(Vec3::ZERO).length()
    }

    /// `p` moved to the nearest point of the workspace.
    pub fn clamp(&self, p: Vec3) -> Vec3 {
        p.clamp(self.min, self.max)
    }
}

/// What a candidate gripper path is scored by (lower is better; units of metres of Chamfer
/// distance).
///
/// `cost = chamfer + violation_cost · (number of (step, gripper) pairs outside the workspace or
/// within `gripper_clearance_m` of an obstacle) + depth_cost · (summed depth of those
/// violations, m)`. The Chamfer distance is the two-sided sum of means (PGND's convention,
/// `metrics::Chamfer::two_sided_sum`).
#[derive(Clone, Debug)]
pub struct Objective {
    target: PointIndex,
    /// The same points for brute-force Chamfer distances of small clouds.
    brute: Target,
    /// Where the grippers may go.
    pub workspace: Workspace,
    /// Obstacles the grippers must keep clear of.
    pub obstacles: Vec<BoxObstacle>,
    /// Clearance between a gripper point and an obstacle, m (the held part of the object and
    /// the fingers around the gripper point).
    pub gripper_clearance_m: f32,
    /// Cost per violating (step, gripper) pair (default 1.0, far above any Chamfer distance of
    /// a tabletop object).
    pub violation_cost: f64,
    /// Cost per metre of violation depth (default 10), so that candidates that violate less are
    /// still ranked.
    pub depth_cost: f64,
    /// Final or running Chamfer.
    pub mode: CostMode,
}

impl Objective {
    /// An objective with the default penalties, `CostMode::Final`, no obstacles and 1 cm
    /// clearance.
    pub fn new(target: &[Vec3], workspace: Workspace) -> Result<Self> {
        if !(workspace.min.is_finite()
            && workspace.max.is_finite()
            && workspace.max.cmpge(workspace.min).all())
        {
            return Err(PlanError::Config {
                // The smallest extent shows what is wrong: negative, or not finite.
                name: "workspace extent (smallest axis, m)",
                value: f64::from((workspace.max - workspace.min).min_element()),
                reason: "corners must be finite with min <= max",
            });
        }
        let pts: Vec<[f32; 3]> = target.iter().map(|p| p.to_array()).collect();
        Ok(Objective {
            target: PointIndex::new(&pts)?,
            brute: Target::new(target),
            workspace,
            obstacles: Vec::new(),
            gripper_clearance_m: 0.01,
            violation_cost: 1.0,
            depth_cost: 10.0,
            mode: CostMode::Final,
        })
    }

    /// Two-sided Chamfer distance (sum of both one-sided means) from `x` to the target, m.
    pub fn chamfer(&self, x: &[Vec3]) -> Result<f64> {
        // Small clouds by brute force (same distances up to f32 rounding); large ones, and
        // empty or non-finite ones (for the error), through the k-d trees.
        if !x.is_empty()
            && x.len() * self.brute.len() <= MAX_PAIRS
            && x.iter().all(|p| p.is_finite())
        {
            return Ok(self.brute.two_sided_sum(x));
        }
        let pts: Vec<[f32; 3]> = x.iter().map(|p| p.to_array()).collect();
        Ok(self.target.chamfer(&pts)?.two_sided_sum())
    }

    /// Penalty of gripper positions (`[step][gripper]`, m).
    pub fn penalty(&self, grippers: &[Vec<Vec3>]) -> f64 {
        let mut total = 0.0;
        for g in grippers.iter().flatten() {
            let out = self.workspace.outside(*g);
            let hit = self
                .obstacles
                .iter()
                .map(|b| (self.gripper_clearance_m - b.distance(*g)).max(0.0))
                .fold(0.0f32, f32::max);
            if out > 0.0 || hit > 0.0 {
                total += self.violation_cost + self.depth_cost * f64::from(out + hit);
            }
        }
        total
    }

    /// Whether gripper point `g` violates the workspace or an obstacle's clearance.
    pub fn violates(&self, g: Vec3) -> bool {
        self.penalty(&[vec![g]]) > 0.0
    }

    /// Cost of predicted positions `[step][particle]` reached along gripper path
    /// `[step][gripper]` (both without the current frame).
    pub fn cost(&self, predicted: &[Vec<Vec3>], grippers: &[Vec<Vec3>]) -> Result<f64> {
        let Some(last) = predicted.last() else {
            return Err(PlanError::Mismatch {
                what: "predicted steps",
                expected: 1,
                got: 0,
            });
        };
        let chamfer = match self.mode {
            CostMode::Final => self.chamfer(last)?,
            CostMode::Running => {
                let mut sum = 0.0;
                for x in predicted {
                    sum += self.chamfer(x)?;
                }
                sum / predicted.len() as f64
            }
        };
        Ok(chamfer + self.penalty(grippers))
    }
}
