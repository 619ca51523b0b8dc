//! Gaussians carried by simulated particles: particles act as bones.

use std::num::NonZero;

use glam::{Quat, Vec3};
use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::gaussians::normalize_quat;
use crate::procrustes::fit_rotation;
use crate::{Error, Gaussians};

/// Distance floor of the inverse-distance bone weights, metres: a Gaussian sitting on a bone
/// follows that bone (weight ~1e6 times any bone a centimetre away) without dividing by zero.
const WEIGHT_EPS_M: f32 = 1e-6;

type Tree = ImmutableKdTree<f32, u32, 3, 32>;

/// How a [`GaussianRig`] builds and moves its Gaussians.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RigOptions {
    /// Nearest bones blended per Gaussian (reference code: 16).
    pub bones_per_gaussian: usize,
    /// Neighbouring bones in each bone's rotation fit (reference code: 16).
    pub fit_neighbours: usize,
    /// [`GaussianRig::from_particles`]: neighbours whose mean distance is a particle's spacing.
    pub spacing_neighbours: usize,
    /// [`GaussianRig::from_particles`]: Gaussian standard deviation as a multiple of the
    /// particle's spacing (after clamping the spacing to `[0.5, 2] ×` the median spacing).
    pub scale_factor: f32,
    /// [`GaussianRig::from_particles`]: opacity of every Gaussian, `(0, 1]`.
    pub opacity: f32,
}

impl Default for RigOptions {
    fn default() -> Self {
        RigOptions {
            bones_per_gaussian: 16,
            fit_neighbours: 16,
            spacing_neighbours: 3,
            scale_factor: 0.6,
            opacity: 0.95,
        }
    }
}

impl RigOptions {
    /// Checks the counts are positive and the scale factor and opacity are in range.
    ///
    /// # Errors
    /// [`Error::Options`] naming the bad field.
    pub fn validate(&self) -> Result<(), Error> {
        let bad = |m: &str| Err(Error::Options(m.into()));
        if self.bones_per_gaussian == 0 || self.fit_neighbours == 0 || self.spacing_neighbours == 0
        {
            return bad(
                "bones_per_gaussian, fit_neighbours and spacing_neighbours must be at least 1",
            );
        }
        if !(self.scale_factor.is_finite() && self.scale_factor > 0.0) {
            return bad("scale_factor must be finite and positive");
        }
        if !(self.opacity > 0.0 && self.opacity <= 1.0) {
            return bad("opacity must be in (0, 1]");
        }
        Ok(())
    }
}

/// A Gaussian set bound to particles ("bones") that moves with them, step by step.
///
/// Each [`GaussianRig::deform`] maps the Gaussians from the previous bone positions `P` to
/// the new ones `Q`:
/// 1. every bone `j` gets a rotation `Rⱼ`, the Procrustes fit of its `fit_neighbours`
///    nearest bones' offsets `Pₖ − Pⱼ` onto `Qₖ − Qⱼ`;
/// 2. every Gaussian blends its `bones_per_gaussian` nearest bones (nearest at `P`) with
///    weights `∝ 1 / distance`: mean `μ' = Σ wⱼ (Rⱼ (μ − Pⱼ) + Qⱼ)`, orientation
///    `q' = normalise(Σ wⱼ qⱼ) · q` (bone quaternions on one hemisphere), so covariances rotate;
/// 3. scales, opacities and colours are kept.
///
/// ```
/// use gsplat::{GaussianRig, RigOptions};
/// use glam::Vec3;
/// let particles: Vec<Vec3> = (0..20).map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.1)).collect();
/// let colors = vec![[0.8, 0.3, 0.1]; 20];
/// let mut rig = GaussianRig::from_particles(&particles, &colors, &RigOptions::default())?;
/// // Translate every particle 5 cm up: the Gaussians follow rigidly.
/// let moved: Vec<Vec3> = particles.iter().map(|p| *p + Vec3::Z * 0.05).collect();
/// let g = rig.deform(&moved)?;
/// assert!((g.means[7] - moved[7]).length() < 1e-5);
/// # Ok::<(), gsplat::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct GaussianRig {
    options: RigOptions,
    bones: Vec<Vec3>,
    gaussians: Gaussians,
}

impl GaussianRig {
    /// One isotropic Gaussian per particle at the first frame: centred on the particle, with
    /// its colour, [`RigOptions::opacity`] and standard deviation `scale_factor × spacing`,
    /// where a particle's spacing is the mean distance to its `spacing_neighbours` nearest
    /// other particles, clamped to `[0.5, 2] ×` the median spacing (so stray or doubled
    /// particles do not make giant or vanishing blobs). The particles are the bones.
    ///
    /// # Errors
    /// Fewer than two particles, colours not one per particle, non-finite positions or
    /// colours, all particles at one point, or bad options.
    pub fn from_particles(
        particles: &[Vec3],
        colors: &[[f32; 3]],
        options: &RigOptions,
    ) -> Result<Self, Error> {
        options.validate()?;
        check_points(particles)?;
        if particles.len() < 2 {
            return Err(Error::Particles(format!(
                "need at least 2 particles, got {}",
                particles.len()
            )));
        }
        if colors.len() != particles.len() {
            return Err(Error::Particles(format!(
                "{} colours for {} particles",
                colors.len(),
                particles.len()
            )));
        }
        let tree = build_tree(particles);
        let k = options.spacing_neighbours.min(particles.len() - 1);
        let spacing: Vec<f32> = particles
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let near = nearest(&tree, *p, k + 1);
                let d: Vec<f32> = near
                    .iter()
                    .filter(|n| n.1 as usize != i)
                    .take(k)
                    .map(|n| n.0.sqrt())
                    .collect();
                d.iter().sum::<f32>() / d.len().max(1) as f32
            })
            .collect();
        let mut sorted = spacing.clone();
        sorted.sort_by(f32::total_cmp);
        let median = sorted[sorted.len() / 2];
        if median <= 0.0 || median.is_nan() {
            return Err(Error::Particles(
                "particles have no spread (median spacing 0)".into(),
            ));
        }
        let n = particles.len();
        let gaussians = Gaussians::new(
            particles.to_vec(),
            vec![Quat::IDENTITY; n],
            spacing
                .iter()
                .map(|s| Vec3::splat(options.scale_factor * s.clamp(0.5 * median, 2.0 * median)))
                .collect(),
            vec![options.opacity; n],
            colors.to_vec(),
        )?;
        Self::new(gaussians, particles, options)
    }

    /// Binds an existing Gaussian set (e.g. read from a `.ply`, or several per particle) to
    /// bones at `bones` (same frame as the Gaussians).
    ///
    /// # Errors
    /// No bones, non-finite bone positions, invalid Gaussians or bad options.
    pub fn new(gaussians: Gaussians, bones: &[Vec3], options: &RigOptions) -> Result<Self, Error> {
        options.validate()?;
        check_points(bones)?;
        if bones.is_empty() {
            return Err(Error::Particles("no bones".into()));
        }
        gaussians.validate()?;
        Ok(GaussianRig {
            options: *options,
            bones: bones.to_vec(),
            gaussians,
        })
    }

    /// The Gaussians at the current step.
    pub fn gaussians(&self) -> &Gaussians {
        &self.gaussians
    }

    /// Bone positions at the current step, metres.
    pub fn bones(&self) -> &[Vec3] {
        &self.bones
    }

    /// Moves the Gaussians from the current bone positions to `new_bones` (one step; see the
    /// type's documentation) and returns them.
    ///
    /// # Errors
    /// `new_bones` of another length than the bones, or with non-finite positions; the rig is
    /// left unchanged.
    pub fn deform(&mut self, new_bones: &[Vec3]) -> Result<&Gaussians, Error> {
        check_points(new_bones)?;
        if new_bones.len() != self.bones.len() {
            return Err(Error::Particles(format!(
                "{} new bone positions for {} bones",
                new_bones.len(),
                self.bones.len()
            )));
        }
        let old = &self.bones;
        let tree = build_tree(old);
        let n = old.len();
        let k_fit = self.options.fit_neighbours.min(n - 1);
        let rotations: Vec<Quat> = (0..n)
            .into_par_iter()
            .map(|j| {
                if k_fit == 0 {
                    return Quat::IDENTITY;
                }
                let near = nearest(&tree, old[j], k_fit + 1);
                let (from, to): (Vec<Vec3>, Vec<Vec3>) = near
                    .iter()
                    .map(|nb| nb.1 as usize)
                    .filter(|&k| k != j)
                    .take(k_fit)
                    .map(|k| (old[k] - old[j], new_bones[k] - new_bones[j]))
                    .unzip();
                // Steps are short, so the rotation is near the identity: start there.
                fit_rotation(&from, &to, Quat::IDENTITY)
            })
            .collect();
        let k_bones = self.options.bones_per_gaussian.min(n);
        let g = &self.gaussians;
        let moved: Vec<(Vec3, Quat)> = (0..g.len())
            .into_par_iter()
            .with_min_len(256)
            .map(|i| {
                let mu = g.means[i];
                let near = nearest(&tree, mu, k_bones);
                let weights: Vec<f32> = near
                    .iter()
                    .map(|nb| 1.0 / nb.0.sqrt().max(WEIGHT_EPS_M))
                    .collect();
                let total: f32 = weights.iter().sum();
                let mut mean = Vec3::ZERO;
                let mut blend = [0f32; 4];
                // The heaviest bone fixes the hemisphere (q and -q are one rotation).
                let anchor = rotations[near[0].1 as usize];
                for (nb, w) in near.iter().zip(&weights) {
                    let j = nb.1 as usize;
                    let w = w / total;
                    mean += w * (rotations[j] * (mu - old[j]) + new_bones[j]);
                    let q = rotations[j];
                    let s = if q.dot(anchor) < 0.0 { -w } else { w };
                    for (b, c) in blend.iter_mut().zip(q.to_array()) {
                        *b += s * c;
                    }
                }
                let blend = normalize_quat(Quat::from_array(blend));
                (mean, normalize_quat(blend * g.rotations[i]))
            })
            .collect();
        for (i, (m, q)) in moved.into_iter().enumerate() {
            self.gaussians.means[i] = m;
            self.gaussians.rotations[i] = q;
        }
        self.bones = new_bones.to_vec();
        Ok(&self.gaussians)
    }
}

fn check_points(points: &[Vec3]) -> Result<(), Error> {
    if let Some(i) = points.iter().position(|p| !p.is_finite()) {
        return Err(Error::Particles(format!(
            "non-finite position {} at index {i}",
            points[i]
        )));
    }
    Ok(())
}

fn build_tree(points: &[Vec3]) -> Tree {
    let pts: Vec<[f32; 3]> = points.iter().map(|p| p.to_array()).collect();
    ImmutableKdTree::new_from_slice(&pts)
}

/// Up to `k` nearest points as (squared distance, index), nearest first, equal distances in
/// index order.
fn nearest(tree: &Tree, p: Vec3, k: usize) -> Vec<(f32, u32)> {
    let Some(k) = NonZero::new(k) else {
        return Vec::new();
    };
    let mut near: Vec<(f32, u32)> = tree
        .nearest_n::<SquaredEuclidean>(&p.to_array(), k)
        .into_iter()
        .map(|nb| (nb.distance, nb.item))
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    near
}
