//! A set of 3D Gaussians (structure of arrays).

use glam::{Mat3, Quat, Vec3};

use crate::Error;

/// 3D Gaussians, one entry per Gaussian in each array.
///
/// Gaussian `i` has covariance `Σ = R S Sᵀ Rᵀ` with `R` the rotation of `rotations[i]` and
/// `S = diag(scales[i])`: the scales are standard deviations in metres along the Gaussian's
/// local axes (not the logarithms a 3DGS `.ply` stores). Colour is RGB (spherical harmonics of
/// degree 0 already evaluated), nominally in `[0, 1]`; values outside are composited as they
/// are and clamped only when an image is converted to 8 bits.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Gaussians {
    /// Centres, world coordinates, metres.
    pub means: Vec<Vec3>,
    /// Orientations (need not be unit length; they are normalised when used).
    pub rotations: Vec<Quat>,
    /// Standard deviations along the local axes, metres (zero allowed: a flat or point-like
    /// Gaussian still covers the 0.3 px² screen-space low-pass).
    pub scales: Vec<Vec3>,
    /// Opacities in `[0, 1]`.
    pub opacities: Vec<f32>,
    /// RGB colours.
    pub colors: Vec<[f32; 3]>,
}

impl Gaussians {
    /// A validated set from its attribute arrays.
    ///
    /// # Errors
    /// As [`Gaussians::validate`].
    pub fn new(
        means: Vec<Vec3>,
        rotations: Vec<Quat>,
        scales: Vec<Vec3>,
        opacities: Vec<f32>,
        colors: Vec<[f32; 3]>,
    ) -> Result<Self, Error> {
        let g = Gaussians {
            means,
            rotations,
            scales,
            opacities,
            colors,
        };
        g.validate()?;
        Ok(g)
    }

    /// Isotropic Gaussians of standard deviation `sigma_m` metres and one opacity at `means`
    /// with `colors` (e.g. one per fine particle of a simulated object).
    ///
    /// # Errors
    /// As [`Gaussians::validate`].
    pub fn isotropic(
        means: Vec<Vec3>,
        colors: Vec<[f32; 3]>,
        sigma_m: f32,
        opacity: f32,
    ) -> Result<Self, Error> {
        let n = means.len();
        Gaussians::new(
            means,
            vec![Quat::IDENTITY; n],
            vec![Vec3::splat(sigma_m); n],
            vec![opacity; n],
            colors,
        )
    }

    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.means.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// Appends all of `other`'s Gaussians (e.g. several objects in one scene).
    pub fn append(&mut self, other: &Gaussians) {
        self.means.extend_from_slice(&other.means);
        self.rotations.extend_from_slice(&other.rotations);
        self.scales.extend_from_slice(&other.scales);
        self.opacities.extend_from_slice(&other.opacities);
        self.colors.extend_from_slice(&other.colors);
    }

    /// Checks that all arrays have one length and every attribute is usable: finite means,
    /// finite non-zero quaternions, finite non-negative scales, opacities in `[0, 1]`, finite
    /// colours.
    ///
    /// # Errors
    /// [`Error::Length`] or [`Error::Gaussian`] naming the first offending Gaussian.
    pub fn validate(&self) -> Result<(), Error> {
        let n = self.means.len();
        let lens = [
            ("rotations", self.rotations.len()),
            ("scales", self.scales.len()),
            ("opacities", self.opacities.len()),
            ("colors", self.colors.len()),
        ];
        for (name, len) in lens {
            if len != n {
                return Err(Error::Length(format!("{n} means but {len} {name}")));
            }
        }
        for i in 0..n {
            let bad = |what: String| Err(Error::Gaussian { index: i, what });
            if !self.means[i].is_finite() {
                return bad(format!("non-finite mean {}", self.means[i]));
            }
            let q = self.rotations[i];
            if !q.is_finite() {
                return bad(format!("non-finite rotation {q}"));
            }
            // Squared norm in f64 so that tiny but valid quaternions are not rejected.
            let norm2: f64 = q
                .to_array()
                .iter()
                .map(|&c| f64::from(c) * f64::from(c))
                .sum();
            if norm2 < 1e-24 {
                return bad("zero rotation quaternion".into());
            }
            let s = self.scales[i];
            if !(s.is_finite() && s.min_element() >= 0.0) {
                return bad(format!("scales {s} must be finite and non-negative"));
            }
            let o = self.opacities[i];
            if !(0.0..=1.0).contains(&o) {
                return bad(format!("opacity {o} outside [0, 1]"));
            }
            if !self.colors[i].iter().all(|c| c.is_finite()) {
                return bad(format!("non-finite colour {:?}", self.colors[i]));
            }
        }
        Ok(())
    }

    /// World-frame covariance of Gaussian `i`, m². Panics if `i` is out of range.
    pub fn covariance(&self, i: usize) -> Mat3 {
        covariance(self.rotations[i], self.scales[i])
    }
}

/// `R diag(s²) Rᵀ` for a (possibly unnormalised) quaternion.
pub(crate) fn covariance(q: Quat, s: Vec3) -> Mat3 {
    let r = Mat3::from_quat(normalize_quat(q));
    let m = r * Mat3::from_diagonal(s);
    m * m.transpose()
}

/// Normalises in f64 so that very small (but validated non-zero) quaternions survive.
pub(crate) fn normalize_quat(q: Quat) -> Quat {
    let a = q.to_array().map(f64::from);
    let n = a.iter().map(|c| c * c).sum::<f64>().sqrt();
    if n == 0.0 || !n.is_finite() {
        return Quat::IDENTITY;
    }
    Quat::from_xyzw(
        (a[0] / n) as f32,
        (a[1] / n) as f32,
        (a[2] / n) as f32,
        (a[3] / n) as f32,
    )
}
