//! The five fitted physical parameters, their search bounds and the fixed ground constants.

use serde::{Deserialize, Serialize};

use crate::SimError;

/// Normal penalty stiffness of the ground plane per particle, N/m (reference value).
pub const GROUND_STIFFNESS: f32 = 5.0e4;
/// Damping of the normal velocity of a particle in ground contact, N·s/m (reference value).
pub const GROUND_DAMPING: f32 = 5.0e2;
/// Viscous tangential friction coefficient of the ground, N·s/m (reference `kf`).
pub const GROUND_VISCOUS_FRICTION: f32 = 1.0e3;
/// Friction coefficient of the ground itself; the object's fitted coefficient is averaged with it,
/// `mu = (ground_friction + GROUND_MU) / 2`, as in the reference.
pub const GROUND_MU: f32 = 0.5;
/// A rollout whose |x| (m) or |v| (m/s) exceeds this is reported as diverged.
pub const DIVERGENCE_LIMIT: f32 = 1.0e4;

/// The five physical parameters that CMA-ES fits (paper §Physics Backbone).
///
/// Spring forces use absolute units (N per metre of elongation), not per unit strain.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SpringParams {
    /// Spring stiffness, N/m.
    pub stiffness: f32,
    /// Dashpot coefficient along each spring, N·s/m.
    pub damping: f32,
    /// Maximum rest length of a spring (neighbour search radius), m.
    pub threshold: f32,
    /// Maximum number of springs attached to one particle.
    pub max_springs: u32,
    /// Fitted ground friction coefficient (dimensionless, before averaging with [`GROUND_MU`]).
    pub ground_friction: f32,
}

impl SpringParams {
    /// The reference code's fitted rope values: k 17059 N/m, kd 480 N·s/m, threshold 0.034 m,
    /// 112 springs per particle, friction 0.42.
    pub fn reference_rope() -> Self {
        Self {
            stiffness: 17059.0,
            damping: 480.0,
            threshold: 0.034,
            max_springs: 112,
            ground_friction: 0.42,
        }
    }

    /// Check that every value is finite and in range (threshold > 0, the rest >= 0).
    pub fn validate(&self) -> Result<(), SimError> {
        let check = |name: &'static str, v: f32, positive: bool| {
            let ok = v.is_finite() && if positive { v > 0.0 } else { v >= 0.0 };
            if ok {
                Ok(())
            } else {
                Err(SimError::InvalidParameter {
                    name,
                    value: f64::from(v),
                    reason: if positive {
                        "must be finite and > 0"
                    } else {
                        "must be finite and >= 0"
                    },
                })
            }
        };
        check("stiffness", self.stiffness, false)?;
        check("damping", self.damping, false)?;
        check("threshold", self.threshold, true)?;
        check("ground_friction", self.ground_friction, false)
    }

    /// The Coulomb coefficient actually used at the ground: `(ground_friction + GROUND_MU) / 2`.
    pub fn effective_ground_mu(&self) -> f32 {
        0.5 * (self.ground_friction + GROUND_MU)
    }
}

/// Closed search intervals `[low, high]` for the five parameters.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ParamBounds {
    /// Damping, N·s/m.
    pub damping: [f32; 2],
    /// Stiffness, N/m.
    pub stiffness: [f32; 2],
    /// Threshold, m.
    pub threshold: [f32; 2],
    /// Max springs per particle (rounded to an integer when denormalised).
    pub max_springs: [u32; 2],
    /// Ground friction coefficient.
    pub ground_friction: [f32; 2],
}

/// The reference code's CMA-ES bounds.
pub const REFERENCE_BOUNDS: ParamBounds = ParamBounds {
    damping: [1.0, 1000.0],
    stiffness: [10.0, 5.0e4],
    threshold: [0.002, 0.05],
    max_springs: [4, 200],
    ground_friction: [0.01, 0.5],
};

/// The wider bounds the reference code uses for the paper's runs.
pub const PAPER_BOUNDS: ParamBounds = ParamBounds {
    damping: [1.0, 1.0e4],
    stiffness: [10.0, 5.0e5],
    threshold: [0.002, 0.05],
    max_springs: [4, 500],
    ground_friction: [0.01, 0.5],
};

impl ParamBounds {
    /// Map normalised coordinates to parameters, in the reference's order
    /// `[damping, stiffness, threshold, max_springs, ground_friction]`: each `u` is clamped to
    /// [0, 1] and mapped linearly onto its interval; max springs is rounded to the nearest integer.
    /// A non-finite coordinate maps to the interval's low end.
    pub fn denormalize(&self, u: [f64; 5]) -> SpringParams {
        let t = |x: f64| {
            if x.is_finite() {
                x.clamp(0.0, 1.0)
            } else {
                0.0
            }
        };
        let lin = |b: [f32; 2], x: f64| (f64::from(b[0]) + t(x) * f64::from(b[1] - b[0])) as f32;
        let ms = f64::from(self.max_springs[0])
            + t(u[3]) * (f64::from(self.max_springs[1]) - f64::from(self.max_springs[0]));
        SpringParams {
            damping: lin(self.damping, u[0]),
            stiffness: lin(self.stiffness, u[1]),
            threshold: lin(self.threshold, u[2]),
            max_springs: ms.round() as u32,
            ground_friction: lin(self.ground_friction, u[4]),
        }
    }
}
