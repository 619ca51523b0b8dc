//! Gaussian splatting on the CPU.
//!
//! - [`render`]: a tiled rasteriser following the original 3D Gaussian Splatting rules (EWA
//!   projection with a 0.3 px² low-pass, depth-sorted front-to-back alpha compositing with
//!   alpha capped at 0.99, alpha < 1/255 skipped and a 1e-4 transmittance floor), giving
//!   colour, opacity and depth images ([`Image`]); 16 × 16 px tiles run in parallel on rayon.
//! - [`Camera`]: pinhole intrinsics and a world-to-camera pose; [`Camera::look_at`] for world
//!   z up, [`Camera::framing`] to fit a set of points (e.g. every frame of an episode).
//! - [`Gaussians`]: means, quaternions, scales (standard deviations, m), opacities and RGB
//!   colours; [`read_ply`] / [`write_ply`] for the standard 3DGS `.ply` layout.
//! - [`GaussianRig`]: Gaussians carried by simulated particles acting as bones (nearest
//!   bones, per-bone Procrustes rotations, inverse-distance weights), built from the
//!   particles at the first frame and moved step by step.
//! - [`Image::mask`] with [`MASK_THRESHOLD`] for the J/F metrics; [`grid`],
//!   [`side_by_side`], [`write_png`] and [`write_gif`] for pictures.
//!
//! Conventions (see `docs/rendering.md`): metres, world z up; camera frame x right, y down,
//! z forward; pixel `(i, j)` is sampled at `(i + 0.5, j + 0.5)`.
//!
//! ```
//! use gsplat::{Camera, GaussianRig, RigOptions, MASK_THRESHOLD, render};
//! use glam::Vec3;
//! // A 20-particle "rope" along x, 10 cm above the ground, orange.
//! let rope: Vec<Vec3> = (0..20).map(|i| Vec3::new(-0.1 + 0.01 * i as f32, 0.0, 0.1)).collect();
//! let mut rig = GaussianRig::from_particles(&rope, &vec![[0.9, 0.5, 0.1]; 20], &RigOptions::default())?;
//! let cam = Camera::look_at(Vec3::new(0.0, -0.6, 0.4), Vec3::new(0.0, 0.0, 0.1), Vec3::Z,
//!                           45f32.to_radians(), 96, 64)?;
//! let before = render(rig.gaussians(), &cam, [1.0; 3])?;
//! // Lift the rope by 5 cm and render again: the mask moves up the image.
//! let lifted: Vec<Vec3> = rope.iter().map(|p| *p + Vec3::new(0.0, 0.0, 0.05)).collect();
//! let after = render(rig.deform(&lifted)?, &cam, [1.0; 3])?;
//! let mean_row = |m: Vec<bool>| {
//!     let rows: Vec<usize> = m.iter().enumerate().filter(|(_, f)| **f).map(|(k, _)| k / 96).collect();
//!     rows.iter().sum::<usize>() as f32 / rows.len() as f32
//! };
//! assert!(mean_row(after.mask(MASK_THRESHOLD)) < mean_row(before.mask(MASK_THRESHOLD)) - 3.0);
//! # Ok::<(), gsplat::Error>(())
//! ```

mod camera;
mod error;
mod fastexp;
mod frame;
mod gaussians;
mod output;
mod ply;
mod procrustes;
mod project;
mod raster;
mod rig;

pub use camera::{Camera, DEFAULT_NEAR_M, MAX_PIXELS};
pub use error::Error;
pub use frame::{Image, MASK_THRESHOLD};
pub use gaussians::Gaussians;
pub use output::{GAP_COLOR, grid, side_by_side, write_gif, write_png};
pub use ply::{SH_C0, parse_ply, read_ply, write_ply};
pub use project::{JACOBIAN_GUARD, LOW_PASS_PX2, MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE};
pub use raster::{TILE, render};
pub use rig::{GaussianRig, RigOptions};

/// Result alias for this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
