//! Scene and integrator settings that are not fitted.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::{Obstacles, SimError};

/// How the substep length is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Substep {
    /// Derive the substep from the stability bound (docs/physics.md): `dt = min(safety * dt_max,
    /// max_dt)`, then shortened so that a whole number of substeps fills one model step.
    /// `safety` must lie in (0, 1] (default 0.9). `max_dt` (s, default 2e-3) caps the substep
    /// for accuracy where the bound alone would allow huge substeps (soft springs, no ground):
    /// stability is not accuracy when particles move a sizeable part of a spring length per
    /// substep.
    Auto {
        /// Fraction of the bound to use, in (0, 1].
        safety: f32,
        /// Largest substep allowed, s.
        max_dt: f32,
    },
    /// Like [`Substep::Auto`], but the stiffness part of the bound comes from an estimate of the
    /// largest eigenvalue of the springs' `M^-1 K` at the rest configuration (64 Lanczos steps
    /// at construction, docs/physics.md "Spectral substep") instead of Gershgorin's bound, which
    /// is 1.8–3.3× larger on our scenes. Fewer substeps for the same model; the margin against
    /// deformation (which can raise the eigenvalue above its rest value) is `safety` alone, so
    /// it is tested on the same random scenes as the default but is not a proof.
    Spectral {
        /// Fraction of the estimated limit to use, in (0, 1].
        safety: f32,
        /// Largest substep allowed, s.
        max_dt: f32,
    },
    /// A fixed substep in seconds, shortened to `step_dt / round(step_dt / dt)` so that a whole
    /// number of substeps fills one model step. `Fixed { dt: 2e-5 }` with a 0.1 s step reproduces
    /// the reference's 5000 substeps. No stability check is made; a run that blows up returns
    /// [`SimError::Diverged`].
    Fixed {
        /// Requested substep, s.
        dt: f32,
    },
}

/// How the springs' dashpots are integrated.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum Dashpot {
    /// Implicit pair impulses (a forward and a backward Gauss–Seidel sweep per substep,
    /// docs/physics.md): the substep is set by the springs' stiffness alone. The default.
    #[default]
    Implicit,
    /// The reference code's explicit dashpot: `c (u·(v_b − v_a)) u` is added to each spring's
    /// force before the kick, in the same pass. One pass over the springs per substep instead of
    /// three, but stable only for substeps below about `1 / (2 Σ c / m)`; the automatic substep
    /// accounts for that. With `Substep::Fixed { dt: 2e-5 }` this is the reference's integrator.
    Explicit,
}

/// How grippers act on the object.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Manipulation {
    /// Prehensile: particle `i` with `held[i] = g >= 0` moves rigidly (translation) with gripper
    /// `g` while that gripper is closed, ignoring forces; when it is open the particle is free.
    Grasp,
    /// Non-prehensile: each active gripper (closed flag set) is a sphere of
    /// [`SimConfig::gripper_radius`]; free particles inside it are projected onto its surface and
    /// lose their inward velocity relative to the gripper. `held` is ignored.
    Push,
}

/// Settings of one simulation scene.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SimConfig {
    /// Length of one model step, s (0.1 s: the reference's 10 Hz).
    pub step_dt: f32,
    /// Gravity, m/s². Default (0, 0, -9.8): z is up.
    pub gravity: Vec3,
    /// Height of the ground plane z = h (normal +z), m; `None` for no ground.
    pub ground_z: Option<f32>,
    /// Clamp free particles to `z >= ground_z` at the end of every model step, as the reference
    /// does (default true). The clamp lifts particles resting in penalty contact by their
    /// penetration (load / [`crate::GROUND_STIFFNESS`]) once per step, which feeds a small
    /// oscillation; set false for a purely penalty-based contact.
    pub clamp_to_ground: bool,
    /// How grippers act.
    pub manipulation: Manipulation,
    /// Gripper sphere radius for [`Manipulation::Push`], m (reference default 0.04).
    pub gripper_radius: f32,
    /// Substep selection.
    pub substep: Substep,
    /// Dashpot integration (default [`Dashpot::Implicit`]).
    #[serde(default, skip_serializing_if = "Dashpot::is_implicit")]
    pub dashpot: Dashpot,
    /// Split every rollout into this many slabs that run in parallel on the rayon pool
    /// (default 1: no split). The model is the same; only the order in which each particle's
    /// spring forces and dashpot impulses are summed changes, so results differ from
    /// `partitions = 1` in the last bits but are identical for any thread count. Worth it for
    /// single large rollouts (≈ 1000 particles and more) on an idle machine; batches already
    /// use every core. At most 64.
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub partitions: u32,
    /// Box obstacles free particles cannot enter (default none; see [`Obstacles`]).
    #[serde(default, skip_serializing_if = "Obstacles::is_empty")]
    pub obstacles: Obstacles,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            step_dt: 0.1,
            gravity: Vec3::new(0.0, 0.0, -9.8),
            ground_z: Some(0.0),
            clamp_to_ground: true,
            manipulation: Manipulation::Grasp,
            gripper_radius: 0.04,
            substep: Substep::AUTO,
            dashpot: Dashpot::Implicit,
            partitions: 1,
            obstacles: Obstacles::NONE,
        }
    }
}

impl Substep {
    /// The default automatic substep: `Auto { safety: 0.9, max_dt: 2e-3 }`.
    pub const AUTO: Substep = Substep::Auto {
        safety: 0.9,
        max_dt: 2e-3,
    };
}

impl Substep {
    /// The spectral substep with the default safety and cap: `Spectral { safety: 0.9, max_dt:
    /// 2e-3 }`.
    pub const SPECTRAL: Substep = Substep::Spectral {
        safety: 0.9,
        max_dt: 2e-3,
    };
}

fn one() -> u32 {
    1
}

fn is_one(p: &u32) -> bool {
    *p == 1
}

impl Dashpot {
    fn is_implicit(&self) -> bool {
        *self == Dashpot::Implicit
    }
}

impl SimConfig {
    /// Check every field (finite, positive where needed).
    pub fn validate(&self) -> Result<(), SimError> {
        let bad =
            |name: &'static str, value: f32, reason: &'static str| SimError::InvalidParameter {
                name,
                value: f64::from(value),
                reason,
            };
        if !(self.step_dt.is_finite() && self.step_dt > 0.0) {
            return Err(bad("step_dt", self.step_dt, "must be finite and > 0"));
        }
        if !self.gravity.is_finite() {
            return Err(bad("gravity", f32::NAN, "must be finite"));
        }
        if let Some(h) = self.ground_z
            && !h.is_finite()
        {
            return Err(bad("ground_z", h, "must be finite"));
        }
        if !(self.gripper_radius.is_finite() && self.gripper_radius >= 0.0) {
            return Err(bad(
                "gripper_radius",
                self.gripper_radius,
                "must be finite and >= 0",
            ));
        }
        self.obstacles.validate()?;
        if !(1..=64).contains(&self.partitions) {
            return Err(bad(
                "partitions",
                self.partitions as f32,
                "must be in 1..=64",
            ));
        }
        match self.substep {
            Substep::Auto { safety, max_dt } | Substep::Spectral { safety, max_dt } => {
                if !(safety > 0.0 && safety <= 1.0) {
                    return Err(bad("Substep::safety", safety, "must be in (0, 1]"));
                }
                if !(max_dt.is_finite() && max_dt > 0.0) {
                    return Err(bad("Substep::max_dt", max_dt, "must be finite and > 0"));
                }
            }
            Substep::Fixed { dt } => {
                if !(dt.is_finite() && dt > 0.0) {
                    return Err(bad("Substep::Fixed::dt", dt, "must be finite and > 0"));
                }
            }
        }
        Ok(())
    }
}
