//! State, gripper actions and rollout results.

use glam::Vec3;

use crate::SimError;

/// Positions (m) and velocities (m/s) of all particles.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct State {
    /// Positions, m.
    pub x: Vec<Vec3>,
    /// Velocities, m/s.
    pub v: Vec<Vec3>,
}

impl State {
    /// Particles at `x` with zero velocity.
    pub fn at_rest(x: Vec<Vec3>) -> Self {
        let v = vec![Vec3::ZERO; x.len()];
        Self { x, v }
    }

    pub(crate) fn validate(&self, n: usize) -> Result<(), SimError> {
        for (what, a) in [("state.x", &self.x), ("state.v", &self.v)] {
            if a.len() != n {
                return Err(SimError::LengthMismatch {
                    what,
                    expected: n,
                    got: a.len(),
                });
            }
            if let Some(index) = a.iter().position(|p| !p.is_finite()) {
                return Err(SimError::NonFinite { what, index });
            }
        }
        Ok(())
    }
}

/// Gripper positions (m) and closed flags for `T` frames and `G` grippers, one frame per model
/// step. Frame `t` is the gripper state at the start of step `t`; a step from `t` to `t + 1`
/// moves each gripper linearly from frame `t` to frame `t + 1` and uses the closed flags of
/// frame `t`.
#[derive(Debug, Clone, PartialEq)]
pub struct Actions {
    num_frames: usize,
    num_grippers: usize,
    positions: Vec<Vec3>,
    closed: Vec<bool>,
}

/// One frame of [`Actions`]: a position (m) and a closed flag per gripper.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ActionFrame<'a> {
    /// Gripper positions, m.
    pub positions: &'a [Vec3],
    /// Closed (grasping / active) flags.
    pub closed: &'a [bool],
}

impl Actions {
    /// Actions from per-frame lists `[T][G]`; every frame must list the same number of grippers
    /// in both arguments, and positions must be finite.
    pub fn new(positions: Vec<Vec<Vec3>>, closed: Vec<Vec<bool>>) -> Result<Self, SimError> {
        if closed.len() != positions.len() {
            return Err(SimError::LengthMismatch {
                what: "actions.closed frames",
                expected: positions.len(),
                got: closed.len(),
            });
        }
        let g = positions.first().map_or(0, Vec::len);
        let mut flat_p = Vec::with_capacity(g * positions.len());
        let mut flat_c = Vec::with_capacity(g * positions.len());
        for (p, c) in positions.iter().zip(&closed) {
            if p.len() != g {
                return Err(SimError::LengthMismatch {
                    what: "actions.positions grippers",
                    expected: g,
                    got: p.len(),
                });
            }
            if c.len() != g {
                return Err(SimError::LengthMismatch {
                    what: "actions.closed grippers",
                    expected: g,
                    got: c.len(),
                });
            }
            flat_p.extend_from_slice(p);
            flat_c.extend_from_slice(c);
        }
        if let Some(index) = flat_p.iter().position(|p| !p.is_finite()) {
            return Err(SimError::NonFinite {
                what: "actions.positions (flattened)",
                index,
            });
        }
        Ok(Self {
            num_frames: positions.len(),
            num_grippers: g,
            positions: flat_p,
            closed: flat_c,
        })
    }

    /// `num_frames` frames without grippers (free motion).
    pub fn without_grippers(num_frames: usize) -> Self {
        Self {
            num_frames,
            num_grippers: 0,
            positions: Vec::new(),
            closed: Vec::new(),
        }
    }

    /// Number of frames `T`.
    pub fn num_frames(&self) -> usize {
        self.num_frames
    }

    /// Number of grippers `G`.
    pub fn num_grippers(&self) -> usize {
        self.num_grippers
    }

    /// Frame `t`, or `None` when `t >= num_frames()`.
    pub fn frame(&self, t: usize) -> Option<ActionFrame<'_>> {
        if t >= self.num_frames() {
            return None;
        }
        let g = self.num_grippers;
        Some(ActionFrame {
            positions: &self.positions[t * g..(t + 1) * g],
            closed: &self.closed[t * g..(t + 1) * g],
        })
    }
}

/// The states of a rollout: entry `t` is the state at frame `t` (entry 0 is the initial state),
/// one entry per action frame.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Rollout {
    /// Positions per frame, m.
    pub positions: Vec<Vec<Vec3>>,
    /// Velocities per frame, m/s.
    pub velocities: Vec<Vec<Vec3>>,
}
