//! Box obstacles of the reference world: axis-aligned blocks standing in the scene (a slot is
//! two of them). Contact is position-level like the ground's: after the constraint sweeps, a
//! particle closer to a box than its contact radius is moved out through the nearest face, and
//! static/kinetic friction acts on its slide along that face during the substep.

use glam::Vec3;

use crate::Error;

/// An axis-aligned box obstacle, corners in metres.
///
/// ```
/// use glam::Vec3;
/// use world::BoxObstacle;
/// let block = BoxObstacle::new(Vec3::ZERO, Vec3::new(0.3, 0.04, 0.1))?;
/// assert!(block.contains(Vec3::new(0.1, 0.02, 0.05)));
/// assert!(BoxObstacle::new(Vec3::ZERO, Vec3::new(0.3, 0.0, 0.1)).is_err());
/// # Ok::<(), world::Error>(())
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoxObstacle {
    /// Lower corner, m.
    pub min: Vec3,
    /// Upper corner, m.
    pub max: Vec3,
}

impl BoxObstacle {
    /// A box from its corners; errors unless both are finite and `min < max` on every axis.
    pub fn new(min: Vec3, max: Vec3) -> Result<Self, Error> {
        if !(min.is_finite() && max.is_finite()) || (max - min).min_element() <= 0.0 {
            return Err(Error::Config(format!(
                "box obstacle needs finite corners with min < max on every axis, got {min} .. {max}"
            )));
        }
        Ok(Self { min, max })
    }

    /// Whether `p` lies strictly inside the box.
    pub fn contains(&self, p: Vec3) -> bool {
        p.cmpgt(self.min).all() && p.cmplt(self.max).all()
    }
}

/// Moves every free particle (`w > 0`) at least `contact` metres out of every box, through the
/// face of least penetration. A particle pushed out by `d` keeps still along the face if its
/// slide this substep (`x − x0`, tangential part) is below `mu_static d`, otherwise the slide is
/// shortened by `mu_kinetic d` (the ground's friction law, on the box face).
pub(crate) fn solve_boxes(
    boxes: &[BoxObstacle],
    x: &mut [Vec3],
    x0: &[Vec3],
    w: &[f32],
    contact: f32,
    mu_static: f32,
    mu_kinetic: f32,
) {
    for b in boxes {
        let lo = b.min - Vec3::splat(contact);
        let hi = b.max + Vec3::splat(contact);
        for i in 0..x.len() {
            let p = x[i];
            if w[i] == 0.0 || !(p.cmpgt(lo).all() && p.cmplt(hi).all()) {
                continue;
            }
            let below = p - lo;
            let above = hi - p;
            let (mut depth, mut axis, mut outward) = (below.x, 0usize, false);
            for (d, a, out) in [
                (above.x, 0, true),
                (below.y, 1, false),
                (above.y, 1, true),
                (below.z, 2, false),
                (above.z, 2, true),
            ] {
                if d < depth {
                    (depth, axis, outward) = (d, a, out);
                }
            }
            x[i][axis] = if outward { hi[axis] } else { lo[axis] };
            let mut slide = x[i] - x0[i];
            slide[axis] = 0.0;
            let len = slide.length();
            if len < mu_static * depth {
                x[i] -= slide;
            } else if len > 0.0 {
                x[i] -= slide * (mu_kinetic * depth / len).min(1.0);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pushed_out_through_the_nearest_face_with_friction() {
        let b = BoxObstacle::new(Vec3::ZERO, Vec3::ONE).unwrap();
        // 5 mm under the top face, slid 1 mm along it this substep: static friction holds it.
        let mut x = [Vec3::new(0.5, 0.5, 0.995)];
        let x0 = [Vec3::new(0.499, 0.5, 1.01)];
        solve_boxes(&[b], &mut x, &x0, &[1.0], 0.002, 0.5, 0.4);
        assert!(
            (x[0] - Vec3::new(0.499, 0.5, 1.002)).length() < 1e-6,
            "{x:?}"
        );
        // A kinematic particle is left alone.
        let mut x = [Vec3::new(0.5, 0.5, 0.5)];
        let x0 = x;
        solve_boxes(&[b], &mut x, &x0, &[0.0], 0.002, 0.5, 0.4);
        assert_eq!(x[0], Vec3::splat(0.5));
    }
}
