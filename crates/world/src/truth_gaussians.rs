//! Ground truth for rendering: the fine particles' own Gaussians, written beside a dataset as
//! `truth_ep_NNNN.safetensors` (one per episode), so predicted frames can be compared with
//! frames of the true motion from the same camera.
//!
//! Like `truth.json`, these files are provenance: fitting, training and diagnosis never read
//! them; only visual evaluation (`cargo xtask render`, `cargo xtask eval --visual`) does.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use glam::Vec3;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use crate::Error;
use crate::build::Blueprint;

/// Format tag stored in every file's safetensors metadata (key `format`).
pub const TRUTH_GAUSSIANS_FORMAT: &str = "pgrd-world-gaussians/1";

/// Standard deviation of a fine particle's Gaussian as a multiple of its spacing (the mean
/// distance to its 3 nearest exported neighbours at rest) — the same rule as
/// `gsplat::RigOptions::default()`, so neighbouring Gaussians merge into a closed surface.
pub const SIGMA_PER_SPACING: f32 = 0.6;

/// Opacity of every fine particle's Gaussian.
pub const TRUTH_OPACITY: f32 = 0.95;

/// Largest quantised coordinate: positions are stored as `u16` on the episode's bounding box.
const LEVELS: f32 = 65535.0;

/// The fine particles of one episode as Gaussians: an isotropic Gaussian per particle (colour,
/// standard deviation, opacity) and its true (noise-free) position at every frame.
///
/// Positions are stored quantised to 16 bits per axis on the episode's axis-aligned bounding
/// box: the error is at most half a step, [`TruthGaussians::step_m`] (e.g. 15 µm for a 2 m
/// extent), far below a Gaussian's size. Building, writing and reading are exact after the
/// first quantisation (a file read and written again is byte for byte the same).
///
/// ```
/// use world::TruthGaussians;
/// use glam::Vec3;
/// // Two particles over three frames, moving along x.
/// let pos: Vec<Vec3> = (0..3)
///     .flat_map(|t| [Vec3::new(0.1 * t as f32, 0.0, 0.2), Vec3::new(0.1 * t as f32, 0.05, 0.2)])
///     .collect();
/// let g = TruthGaussians::new(3, &pos, vec![[1.0, 0.0, 0.0]; 2], vec![0.006; 2], vec![0.95; 2], vec![7, 9])?;
/// let back = TruthGaussians::from_bytes(&g.to_bytes()?, "mem".as_ref())?;
/// assert_eq!(back, g);
/// assert!((back.frame(2)[1] - Vec3::new(0.2, 0.05, 0.2)).abs().max_element() < 1e-5);
/// # Ok::<(), world::Error>(())
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct TruthGaussians {
    frames: usize,
    particles: usize,
    origin: Vec3,
    step: Vec3,
    quantised: Vec<[u16; 3]>,
    colors: Vec<[f32; 3]>,
    sigmas_m: Vec<f32>,
    opacities: Vec<f32>,
    fine_indices: Vec<u32>,
}

impl TruthGaussians {
    /// Builds the ground truth of `frames` frames from `positions` (`[frames × n]`, m, frame
    /// major), per-particle `colors` (RGB in `[0, 1]`), standard deviations `sigmas_m` (m,
    /// positive), `opacities` (`(0, 1]`) and the particles' indices in the fine model.
    ///
    /// # Errors
    /// [`Error::Config`] for zero frames or particles, mismatched lengths, non-finite positions,
    /// colours outside `[0, 1]`, non-positive standard deviations or opacities outside `(0, 1]`.
    pub fn new(
        frames: usize,
        positions: &[Vec3],
        colors: Vec<[f32; 3]>,
        sigmas_m: Vec<f32>,
        opacities: Vec<f32>,
        fine_indices: Vec<u32>,
    ) -> Result<Self, Error> {
        let bad = |m: String| Err(Error::Config(format!("truth Gaussians: {m}")));
        let n = colors.len();
        if frames == 0 || n == 0 {
            return bad(format!(
                "{frames} frames of {n} particles: both must be >= 1"
            ));
        }
        if positions.len() != frames * n {
            return bad(format!(
                "{} positions for {frames} frames of {n} particles",
                positions.len()
            ));
        }
        for (name, len) in [
            ("standard deviations", sigmas_m.len()),
            ("opacities", opacities.len()),
            ("fine indices", fine_indices.len()),
        ] {
            if len != n {
                return bad(format!("{len} {name} for {n} particles"));
            }
        }
        if let Some(k) = positions.iter().position(|p| !p.is_finite()) {
            return bad(format!(
                "non-finite position of particle {} at frame {}",
                k % n,
                k / n
            ));
        }
        if let Err(m) = check_appearance(&colors, &sigmas_m, &opacities) {
            return bad(m);
        }
        let lo = positions.iter().copied().fold(Vec3::INFINITY, Vec3::min);
        let hi = positions
            .iter()
            .copied()
            .fold(Vec3::NEG_INFINITY, Vec3::max);
        // A flat axis (all particles at one coordinate) still gets a positive step, so
        // dequantisation never divides by zero and stays exact there.
        let step = ((hi - lo) / LEVELS).max(Vec3::splat(1e-9));
        let quantised = positions
            .iter()
            .map(|p| {
                let q = ((*p - lo) / step)
                    .round()
                    .clamp(Vec3::ZERO, Vec3::splat(LEVELS));
                [q.x as u16, q.y as u16, q.z as u16]
            })
            .collect();
        Ok(TruthGaussians {
            frames,
            particles: n,
            origin: lo,
            step,
            quantised,
            colors,
            sigmas_m,
            opacities,
            fine_indices,
        })
    }

    /// Number of frames.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Number of particles (Gaussians).
    pub fn particles(&self) -> usize {
        self.particles
    }

    /// Positions of every particle at frame `t` (dequantised), m.
    ///
    /// # Panics
    /// If `t >= frames()` (an index out of range is a programming error, as for slices).
    pub fn frame(&self, t: usize) -> Vec<Vec3> {
        assert!(t < self.frames, "frame {t} of {}", self.frames);
        self.quantised[t * self.particles..(t + 1) * self.particles]
            .iter()
            .map(|q| self.origin + Vec3::new(q[0] as f32, q[1] as f32, q[2] as f32) * self.step)
            .collect()
    }

    /// Quantisation step per axis, m: stored positions are within half of it of the true ones.
    pub fn step_m(&self) -> Vec3 {
        self.step
    }

    /// Per-particle RGB colour in `[0, 1]`.
    pub fn colors(&self) -> &[[f32; 3]] {
        &self.colors
    }

    /// Per-particle standard deviation of its isotropic Gaussian, m.
    pub fn sigmas_m(&self) -> &[f32] {
        &self.sigmas_m
    }

    /// Per-particle opacity in `(0, 1]`.
    pub fn opacities(&self) -> &[f32] {
        &self.opacities
    }

    /// Index of each particle in the fine model (`truth.json`'s numbering).
    pub fn fine_indices(&self) -> &[u32] {
        &self.fine_indices
    }

    /// File name of episode `index`'s ground truth: `truth_ep_NNNN.safetensors`.
    pub fn file_name(index: usize) -> String {
        format!("truth_ep_{index:04}.safetensors")
    }

    /// Path of episode `index`'s ground truth in the dataset directory `dir`.
    pub fn path(dir: impl AsRef<Path>, index: usize) -> PathBuf {
        dir.as_ref().join(Self::file_name(index))
    }

    /// Serialises to safetensors bytes (deterministic).
    ///
    /// # Errors
    /// Only if the safetensors encoder fails.
    pub fn to_bytes(&self) -> Result<Vec<u8>, Error> {
        let (t, n) = (self.frames, self.particles);
        let f32s = |v: &mut dyn Iterator<Item = f32>| -> Vec<u8> {
            v.flat_map(|x| x.to_le_bytes()).collect()
        };
        let owned: Vec<(&str, Dtype, Vec<usize>, Vec<u8>)> = vec![
            (
                "positions",
                Dtype::U16,
                vec![t, n, 3],
                self.quantised
                    .iter()
                    .flatten()
                    .flat_map(|q| q.to_le_bytes())
                    .collect(),
            ),
            (
                "origin",
                Dtype::F32,
                vec![3],
                f32s(&mut self.origin.to_array().into_iter()),
            ),
            (
                "step",
                Dtype::F32,
                vec![3],
                f32s(&mut self.step.to_array().into_iter()),
            ),
            (
                "colors",
                Dtype::F32,
                vec![n, 3],
                f32s(&mut self.colors.iter().flatten().copied()),
            ),
            (
                "sigmas",
                Dtype::F32,
                vec![n],
                f32s(&mut self.sigmas_m.iter().copied()),
            ),
            (
                "opacities",
                Dtype::F32,
                vec![n],
                f32s(&mut self.opacities.iter().copied()),
            ),
            (
                "fine_indices",
                Dtype::U32,
                vec![n],
                self.fine_indices
                    .iter()
                    .flat_map(|i| i.to_le_bytes())
                    .collect(),
            ),
        ];
        let encode = |m: String| Error::Config(format!("truth Gaussians: {m}"));
        let views = owned
            .iter()
            .map(|(name, dtype, shape, bytes)| {
                TensorView::new(*dtype, shape.clone(), bytes).map(|v| (*name, v))
            })
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| encode(format!("cannot build tensors: {e}")))?;
        // A single metadata entry: safetensors writes a HashMap, whose order is only
        // deterministic with one key.
        let info = HashMap::from([("format".to_string(), TRUTH_GAUSSIANS_FORMAT.to_string())]);
        safetensors::serialize(views, Some(info)).map_err(|e| encode(format!("{e}")))
    }

    /// Parses safetensors bytes; `path` only names the source in errors.
    ///
    /// # Errors
    /// [`Error::Read`] for anything that is not a valid ground-truth file: wrong format tag,
    /// missing or unknown tensors, wrong dtypes or shapes, non-finite values, colours,
    /// standard deviations or opacities out of range, quantised positions out of range.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Self, Error> {
        let bad = |m: String| Error::Read {
            path: path.to_path_buf(),
            message: m,
        };
        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        let (_, meta) = SafeTensors::read_metadata(bytes)
            .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        let format = meta
            .metadata()
            .as_ref()
            .and_then(|m| m.get("format").cloned());
        if format.as_deref() != Some(TRUTH_GAUSSIANS_FORMAT) {
            return Err(bad(format!(
                "format tag {format:?}, expected \"{TRUTH_GAUSSIANS_FORMAT}\""
            )));
        }
        const NAMES: [&str; 7] = [
            "positions",
            "origin",
            "step",
            "colors",
            "sigmas",
            "opacities",
            "fine_indices",
        ];
        if let Some(name) = st.names().into_iter().find(|n| !NAMES.contains(n)) {
            return Err(bad(format!("unknown tensor '{name}'")));
        }
        let tensor = |name: &str, dtype: Dtype, rank: usize| {
            let t = st
                .tensor(name)
                .map_err(|_| bad(format!("missing tensor '{name}'")))?;
            if t.dtype() != dtype || t.shape().len() != rank {
                return Err(bad(format!(
                    "'{name}' is {:?} {:?}, expected {dtype:?} of rank {rank}",
                    t.dtype(),
                    t.shape()
                )));
            }
            Ok(t)
        };
        let positions = tensor("positions", Dtype::U16, 3)?;
        let (frames, n) = (positions.shape()[0], positions.shape()[1]);
        if positions.shape()[2] != 3 || frames == 0 || n == 0 {
            return Err(bad(format!(
                "'positions' has shape {:?}, expected [frames >= 1, particles >= 1, 3]",
                positions.shape()
            )));
        }
        let shaped = |name: &str, dtype: Dtype, shape: &[usize]| {
            let t = tensor(name, dtype, shape.len())?;
            if t.shape() != shape {
                return Err(bad(format!(
                    "'{name}' has shape {:?}, expected {shape:?}",
                    t.shape()
                )));
            }
            Ok(t.data().to_vec())
        };
        let f32s = |b: Vec<u8>| -> Vec<f32> {
            b.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect()
        };
        let origin = f32s(shaped("origin", Dtype::F32, &[3])?);
        let step = f32s(shaped("step", Dtype::F32, &[3])?);
        let (origin, step) = (Vec3::from_slice(&origin), Vec3::from_slice(&step));
        if !origin.is_finite() || !step.is_finite() || step.min_element() <= 0.0 {
            return Err(bad(format!(
                "bad quantisation box: origin {origin}, step {step} (finite, step > 0)"
            )));
        }
        let colors: Vec<[f32; 3]> = f32s(shaped("colors", Dtype::F32, &[n, 3])?)
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        let sigmas_m = f32s(shaped("sigmas", Dtype::F32, &[n])?);
        let opacities = f32s(shaped("opacities", Dtype::F32, &[n])?);
        let fine_indices = shaped("fine_indices", Dtype::U32, &[n])?
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        check_appearance(&colors, &sigmas_m, &opacities).map_err(bad)?;
        let quantised = positions
            .data()
            .chunks_exact(6)
            .map(|c| {
                [
                    u16::from_le_bytes([c[0], c[1]]),
                    u16::from_le_bytes([c[2], c[3]]),
                    u16::from_le_bytes([c[4], c[5]]),
                ]
            })
            .collect();
        Ok(TruthGaussians {
            frames,
            particles: n,
            origin,
            step,
            quantised,
            colors,
            sigmas_m,
            opacities,
            fine_indices,
        })
    }

    /// Reads and validates a ground-truth file.
    ///
    /// # Errors
    /// [`Error::Read`] if the file cannot be read, or as [`TruthGaussians::from_bytes`].
    pub fn read(path: impl AsRef<Path>) -> Result<Self, Error> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|e| Error::Read {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        Self::from_bytes(&bytes, path)
    }

    /// Writes the file atomically.
    ///
    /// # Errors
    /// [`Error::Dataset`] if the file cannot be written.
    pub fn write(&self, path: impl AsRef<Path>) -> Result<(), Error> {
        Ok(dataset::write_atomic(path.as_ref(), &self.to_bytes()?)?)
    }
}

fn check_appearance(colors: &[[f32; 3]], sigmas: &[f32], opacities: &[f32]) -> Result<(), String> {
    if let Some(i) = colors
        .iter()
        .position(|c| !c.iter().all(|v| (0.0..=1.0).contains(v)))
    {
        return Err(format!(
            "colour {:?} of particle {i} outside [0, 1]",
            colors[i]
        ));
    }
    if let Some(i) = sigmas.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(format!(
            "standard deviation {} m of particle {i} is not positive and finite",
            sigmas[i]
        ));
    }
    if let Some(i) = opacities.iter().position(|o| !(*o > 0.0 && *o <= 1.0)) {
        return Err(format!(
            "opacity {} of particle {i} outside (0, 1]",
            opacities[i]
        ));
    }
    Ok(())
}

/// The fine particles that carry Gaussians: the surface particles (what a camera sees), at most
/// `max` of them spread evenly over the rest shape (farthest-point sampling from the lowest
/// index; no random choice), in ascending order. `max == 0` selects none.
pub(crate) fn select(bp: &Blueprint, max: usize) -> Vec<u32> {
    let surface: Vec<u32> = (0..bp.len() as u32)
        .filter(|&i| bp.surface[i as usize])
        .collect();
    if surface.len() <= max {
        return surface;
    }
    if max == 0 {
        return Vec::new();
    }
    let pts: Vec<Vec3> = surface.iter().map(|&i| bp.rest[i as usize]).collect();
    let mut dist = vec![f32::INFINITY; pts.len()];
    let mut picked = Vec::with_capacity(max);
    let mut k = 0;
    while picked.len() < max {
        picked.push(surface[k]);
        for (d, p) in dist.iter_mut().zip(&pts) {
            *d = d.min(p.distance_squared(pts[k]));
        }
        // Ties go to the lowest index (max_by keeps the last maximum, so compare reversed
        // indices too).
        k = (0..pts.len())
            .max_by(|&a, &b| dist[a].total_cmp(&dist[b]).then(b.cmp(&a)))
            .unwrap_or(0);
    }
    picked.sort_unstable();
    picked
}

/// Per-particle standard deviations (m) of the `selected` particles' Gaussians:
/// [`SIGMA_PER_SPACING`] × the mean rest distance to their 3 nearest selected neighbours,
/// clamped to `[0.5, 2] ×` the median so doubled or stray particles make neither vanishing nor
/// giant blobs.
pub(crate) fn sigmas(bp: &Blueprint, selected: &[u32]) -> Vec<f32> {
    let pts: Vec<Vec3> = selected.iter().map(|&i| bp.rest[i as usize]).collect();
    let spacing: Vec<f32> = pts
        .iter()
        .enumerate()
        .map(|(a, p)| {
            // Brute force: a few hundred to a few thousand particles, once per dataset.
            let mut near = [f32::INFINITY; 3];
            for (b, q) in pts.iter().enumerate() {
                if a == b {
                    continue;
                }
                let d = p.distance(*q);
                if d < near[2] {
                    near[2] = d;
                    near.sort_by(f32::total_cmp);
                }
            }
            let found: Vec<f32> = near.into_iter().filter(|d| d.is_finite()).collect();
            if found.is_empty() {
                bp.spacing
            } else {
                found.iter().sum::<f32>() / found.len() as f32
            }
        })
        .collect();
    let mut sorted = spacing.clone();
    sorted.sort_by(f32::total_cmp);
    let median = sorted.get(sorted.len() / 2).copied().unwrap_or(bp.spacing);
    let median = if median > 0.0 { median } else { bp.spacing };
    spacing
        .iter()
        .map(|s| SIGMA_PER_SPACING * s.clamp(0.5 * median, 2.0 * median))
        .collect()
}

/// The ground truth of each episode: `fine` holds a recording's selected fine positions
/// (`[frames × selected.len()]`); episode `j` covers frames `starts[j] .. starts[j] + frames`.
pub(crate) fn episodes(
    bp: &Blueprint,
    selected: &[u32],
    sigmas_m: &[f32],
    fine: &[Vec3],
    starts: &[usize],
    frames: usize,
) -> Result<Vec<TruthGaussians>, Error> {
    let m = selected.len();
    let colors: Vec<[f32; 3]> = selected.iter().map(|&i| bp.colors[i as usize]).collect();
    starts
        .iter()
        .map(|&f0| {
            TruthGaussians::new(
                frames,
                &fine[f0 * m..(f0 + frames) * m],
                colors.clone(),
                sigmas_m.to_vec(),
                vec![TRUTH_OPACITY; m],
                selected.to_vec(),
            )
        })
        .collect()
}
