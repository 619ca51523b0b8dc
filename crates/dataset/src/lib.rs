//! The pgrd dataset format: tracked deformable-object episodes.
//!
//! A dataset is a directory holding `dataset.json` (see [`DatasetMeta`]) and one safetensors file
//! per [`Episode`]. The full contract is in `docs/data-format.md`; this crate is its only reader
//! and writer, so every tool sees the same validation.
//!
//! - [`Dataset::open`] reads and validates `dataset.json`; [`Dataset::load_episode`] reads one
//!   episode and validates shapes, finiteness and index ranges. Every error names the file.
//! - [`DatasetWriter`] writes episodes and the index atomically (temporary file, then rename),
//!   into a new dataset or after an existing one's episodes ([`DatasetWriter::append`]).
//! - [`import`] converts other formats (the DEFORM cable pickles, PhysTwin's captures) into
//!   this one.
//! - [`dev_split`] copies a dataset with its last training episodes as `val` and its `val` as
//!   `test`, so models can be chosen on training recordings and scored once on the rest;
//!   [`select_split`] keeps the last `val` recordings as `val` (a selection set) and moves the
//!   others to `test`, for data where more recordings can be had.
//! - [`merge`] writes the episodes of chosen splits of several datasets of one object as one
//!   new dataset, in the order given (e.g. two kinds of motion to train on), with provenance.
//! - [`carried_frame`] reads a frame with each occluded point carried from its last sighting
//!   (a tracker's stored position for a lost point is stale); [`MaterialNeighbours`] places the
//!   points not seen at all yet, from the neighbours they keep across the training recordings;
//!   [`MaterialPairs`] says how far apart two points usually are, so that a model's springs can
//!   join material neighbours only, not parts that merely touch at the start frame.
//!
//! Units: metres, seconds, z up.
//!
//! ```
//! use dataset::{DatasetMeta, DatasetWriter, Episode, Manipulation, Split, Dataset};
//! use glam::Vec3;
//! # let dir = std::env::temp_dir().join(format!("pgrd-doc-{}", std::process::id()));
//! let meta = DatasetMeta::new("rope", 10.0, Manipulation::Grasp);
//! let mut writer = DatasetWriter::create(&dir, meta)?;
//! let positions = vec![Vec3::ZERO, Vec3::X, Vec3::ZERO, Vec3::X]; // 2 frames x 2 particles
//! let grippers = vec![Vec3::ZERO, Vec3::ZERO]; // 2 frames x 1 gripper
//! writer.add_episode(&Episode::new(2, 2, 1, positions, grippers)?, Split::Train)?;
//! writer.finish()?;
//! let data = Dataset::open(&dir)?;
//! assert_eq!(data.load_episode(0)?.frames(), 2);
//! # std::fs::remove_dir_all(&dir).ok();
//! # Ok::<(), dataset::Error>(())
//! ```

mod atomic;
mod dev_split;
mod episode;
mod error;
pub mod import;
mod merge;
mod meta;
mod neighbours;
mod occlusion;
mod pairs;

pub use atomic::write_atomic;
pub use dev_split::{DevSplitReport, dev_split, dev_split_meta, select_split, select_split_meta};
pub use episode::Episode;
pub use error::Error;
pub use merge::{MERGE_FILE, MergePart, MergeReport, merge};
pub use meta::{
    ControllerSprings, Dataset, DatasetMeta, DatasetWriter, EpisodeEntry, FORMAT_VERSION,
    Manipulation, Split, Structure,
};
pub use neighbours::{MaterialNeighbours, PLACING_NEIGHBOURS};
pub use occlusion::carried_frame;
pub use pairs::{MAX_PAIR_POINTS, MaterialPairs};

/// Result alias for this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
