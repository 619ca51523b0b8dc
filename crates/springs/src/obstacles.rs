//! Box obstacles: axis-aligned blocks that free particles cannot enter (a table-top block; a
//! slot is two of them). Contact is resolved on positions and velocities after every substep's
//! drift, like the gripper sphere of [`crate::Manipulation::Push`]: a particle found inside a box
//! is moved to the nearest face, loses its velocity into the face, and its velocity along the
//! face shrinks by Coulomb friction (at most `mu` times the normal velocity removed). Projection
//! needs no stiffness, so obstacles leave the stability bound and the substep unchanged.

use glam::{Vec3, Vec3A};
use serde::{Deserialize, Serialize};

use crate::SimError;

/// An axis-aligned box obstacle, corners in metres (`min < max` on every axis).
///
/// ```
/// use glam::Vec3;
/// use springs::BoxObstacle;
/// let block = BoxObstacle::new(Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.1, 0.2, 0.05))?;
/// assert!(block.contains(Vec3::new(0.05, 0.1, 0.01)));
/// assert!((block.distance(Vec3::new(0.05, 0.1, 0.15)) - 0.1).abs() < 1e-6);
/// assert!(BoxObstacle::new(Vec3::ONE, Vec3::ZERO).is_err());
/// # Ok::<(), springs::SimError>(())
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct BoxObstacle {
    /// Lower corner, m.
    pub min: Vec3,
    /// Upper corner, m.
    pub max: Vec3,
}

impl BoxObstacle {
    /// A box from its corners; errors unless both are finite and `min < max` on every axis.
    pub fn new(min: Vec3, max: Vec3) -> Result<Self, SimError> {
        let b = Self { min, max };
        b.validate()?;
        Ok(b)
    }

    /// Check the corners (finite, `min < max` on every axis).
    pub fn validate(&self) -> Result<(), SimError> {
        if !(self.min.is_finite() && self.max.is_finite()) {
            return Err(SimError::InvalidParameter {
                name: "BoxObstacle corners",
                value: f64::NAN,
                reason: "must be finite",
            });
        }
        let extent = self.max - self.min;
        if extent.min_element() <= 0.0 {
            return Err(SimError::InvalidParameter {
                name: "BoxObstacle extent",
                value: f64::from(extent.min_element()),
                reason: "max must exceed min on every axis",
            });
        }
        Ok(())
    }

    /// Whether `p` lies strictly inside the box.
    pub fn contains(&self, p: Vec3) -> bool {
        p.cmpgt(self.min).all() && p.cmplt(self.max).all()
    }

    /// Euclidean distance from `p` to the box, m (0 inside).
    pub fn distance(&self, p: Vec3) -> f32 {
        (self.min - p).max(p - self.max).max(Vec3::ZERO).length()
    }

    /// The box grown by `margin` metres on every side (shrunk for a negative margin).
    pub fn inflated(&self, margin: f32) -> Self {
        Self {
            min: self.min - Vec3::splat(margin),
            max: self.max + Vec3::splat(margin),
        }
    }
}

/// The obstacles of a scene: at most [`Obstacles::MAX`] boxes, stored inline so that
/// [`crate::SimConfig`] stays `Copy`. Serialized as a list of boxes.
///
/// ```
/// use glam::Vec3;
/// use springs::{BoxObstacle, Obstacles};
/// let left = BoxObstacle::new(Vec3::new(-0.3, 0.0, 0.0), Vec3::new(-0.03, 0.04, 0.1))?;
/// let right = BoxObstacle::new(Vec3::new(0.03, 0.0, 0.0), Vec3::new(0.3, 0.04, 0.1))?;
/// let slot = Obstacles::new(&[left, right])?; // a 6 cm slot between two blocks
/// assert_eq!(slot.as_slice().len(), 2);
/// assert!(Obstacles::new(&[left; 9]).is_err());
/// # Ok::<(), springs::SimError>(())
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(into = "Vec<BoxObstacle>", try_from = "Vec<BoxObstacle>")]
pub struct Obstacles {
    boxes: [BoxObstacle; Obstacles::MAX],
    len: u8,
}

impl Obstacles {
    /// Most boxes one scene may hold.
    pub const MAX: usize = 8;

    /// No obstacles (the default).
    pub const NONE: Obstacles = Obstacles {
        boxes: [BoxObstacle {
            min: Vec3::ZERO,
            max: Vec3::ZERO,
        }; Obstacles::MAX],
        len: 0,
    };

    /// A set of boxes; errors on an invalid box or more than [`Obstacles::MAX`] of them.
    pub fn new(boxes: &[BoxObstacle]) -> Result<Self, SimError> {
        if boxes.len() > Self::MAX {
            return Err(SimError::TooLarge {
                what: "obstacle boxes",
                value: boxes.len() as u64,
                limit: Self::MAX as u64,
            });
        }
        let mut out = Self::NONE;
        for (slot, b) in out.boxes.iter_mut().zip(boxes) {
            b.validate()?;
            *slot = *b;
        }
        out.len = boxes.len() as u8;
        Ok(out)
    }

    /// The boxes.
    pub fn as_slice(&self) -> &[BoxObstacle] {
        &self.boxes[..self.len as usize]
    }

    /// Whether there are no boxes.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Check every box (a deserialized or hand-built value may hold anything).
    pub fn validate(&self) -> Result<(), SimError> {
        if self.len as usize > Self::MAX {
            return Err(SimError::TooLarge {
                what: "obstacle boxes",
                value: u64::from(self.len),
                limit: Self::MAX as u64,
            });
        }
        self.as_slice().iter().try_for_each(BoxObstacle::validate)
    }
}

impl From<Obstacles> for Vec<BoxObstacle> {
    fn from(o: Obstacles) -> Self {
        o.as_slice().to_vec()
    }
}

impl TryFrom<Vec<BoxObstacle>> for Obstacles {
    type Error = SimError;
    fn try_from(v: Vec<BoxObstacle>) -> Result<Self, SimError> {
        Obstacles::new(&v)
    }
}

/// Push every free particle (`inv_m > 0`) out of every box: to the face of least penetration,
/// removing the velocity into that face and as much velocity along it as Coulomb friction with
/// coefficient `mu` allows for the normal velocity removed.
pub(crate) fn resolve(
    boxes: &[BoxObstacle],
    mu: f32,
    x: &mut [Vec3A],
    v: &mut [Vec3A],
    inv_m: &[f32],
) {
    for b in boxes {
        let (lo, hi) = (Vec3A::from(b.min), Vec3A::from(b.max));
        for ((p, vel), &im) in x.iter_mut().zip(v.iter_mut()).zip(inv_m) {
            if im == 0.0 || !(p.cmpgt(lo).all() && p.cmplt(hi).all()) {
                continue;
            }
            // Penetration through each of the six faces; leave by the shallowest.
            let below = *p - lo;
            let above = hi - *p;
            let (mut depth, mut axis, mut sign) = (below.x, 0usize, -1.0f32);
            for (d, a, s) in [
                (above.x, 0, 1.0),
                (below.y, 1, -1.0),
                (above.y, 1, 1.0),
                (below.z, 2, -1.0),
                (above.z, 2, 1.0),
            ] {
                if d < depth {
                    (depth, axis, sign) = (d, a, s);
                }
            }
            let mut normal = Vec3A::ZERO;
            normal[axis] = sign;
            p[axis] = if sign > 0.0 { hi[axis] } else { lo[axis] };
            let vn = vel.dot(normal);
            if vn < 0.0 {
                let tangential = *vel - vn * normal;
                let speed = tangential.length();
                let keep = if speed > 0.0 {
                    (1.0 - mu * (-vn) / speed).max(0.0)
                } else {
                    0.0
                };
                *vel = tangential * keep;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_box() -> BoxObstacle {
        BoxObstacle::new(Vec3::ZERO, Vec3::ONE).unwrap()
    }

    #[test]
    fn particle_leaves_through_the_nearest_face_and_loses_inward_velocity() {
        let mut x = [Vec3A::new(0.5, 0.5, 0.9)];
        let mut v = [Vec3A::new(0.0, 0.0, -2.0)];
        resolve(&[unit_box()], 0.0, &mut x, &mut v, &[1.0]);
        assert_eq!(x[0], Vec3A::new(0.5, 0.5, 1.0));
        assert_eq!(v[0], Vec3A::ZERO);
    }

    #[test]
    fn friction_removes_at_most_mu_times_normal_speed() {
        // Sliding at 1 m/s along the top face, hitting it at 0.5 m/s, mu = 0.4: the tangential
        // speed drops by 0.2 m/s.
        let mut x = [Vec3A::new(0.5, 0.5, 0.95)];
        let mut v = [Vec3A::new(1.0, 0.0, -0.5)];
        resolve(&[unit_box()], 0.4, &mut x, &mut v, &[1.0]);
        assert!((v[0] - Vec3A::new(0.8, 0.0, 0.0)).length() < 1e-6);
        // Strong friction stops the slide but never reverses it.
        let mut x = [Vec3A::new(0.5, 0.5, 0.95)];
        let mut v = [Vec3A::new(0.1, 0.0, -0.5)];
        resolve(&[unit_box()], 1.0, &mut x, &mut v, &[1.0]);
        assert_eq!(v[0], Vec3A::ZERO);
    }

    #[test]
    fn outgoing_velocity_kept_and_kinematic_or_outside_particles_untouched() {
        let mut x = [
            Vec3A::new(0.02, 0.5, 0.5),
            Vec3A::new(0.5, 0.5, 0.5),
            Vec3A::new(2.0, 0.5, 0.5),
        ];
        let mut v = [Vec3A::new(-1.0, 0.3, 0.0), Vec3A::X, Vec3A::X];
        resolve(&[unit_box()], 0.5, &mut x, &mut v, &[1.0, 0.0, 1.0]);
        assert_eq!(x[0], Vec3A::new(0.0, 0.5, 0.5));
        assert_eq!(v[0], Vec3A::new(-1.0, 0.3, 0.0));
        assert_eq!(x[1], Vec3A::new(0.5, 0.5, 0.5));
        assert_eq!(x[2], Vec3A::new(2.0, 0.5, 0.5));
    }

    #[test]
    fn list_conversions_validate() {
        let o = Obstacles::new(&[unit_box()]).unwrap();
        let list: Vec<BoxObstacle> = o.into();
        assert_eq!(Obstacles::try_from(list).unwrap(), o);
        let flat = BoxObstacle {
            min: Vec3::ZERO,
            max: Vec3::new(0.0, 1.0, 1.0),
        };
        assert!(Obstacles::try_from(vec![flat]).is_err());
        assert!(Obstacles::NONE.is_empty() && Obstacles::default() == Obstacles::NONE);
    }
}
