use std::path::PathBuf;

/// Everything that can go wrong in this crate. Bad input is reported, never panicked on.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A camera parameter is out of range (zero size, non-finite or non-positive focal length,
    /// degenerate look-at, ...).
    #[error("camera: {0}")]
    Camera(String),
    /// A Gaussian attribute is non-finite or out of range.
    #[error("gaussian {index}: {what}")]
    Gaussian {
        /// Index of the offending Gaussian.
        index: usize,
        /// What is wrong with it.
        what: String,
    },
    /// Attribute arrays of a [`crate::Gaussians`] set have different lengths.
    #[error("gaussian attributes of different lengths: {0}")]
    Length(String),
    /// A particle position (rig input) is non-finite or the particle set is unusable.
    #[error("particles: {0}")]
    Particles(String),
    /// A rig option is out of range.
    #[error("rig options: {0}")]
    Options(String),
    /// Images that must have one size do not, or an image list is empty.
    #[error("images: {0}")]
    ImageSize(String),
    /// A `.ply` file could not be understood.
    #[error("ply {path}: {what}")]
    Ply {
        /// The file (or `<memory>` for in-memory input).
        path: PathBuf,
        /// What is wrong with it.
        what: String,
    },
    /// Reading or writing a file failed.
    #[error("{path}: {cause}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error. Part of the message, so not its `source()`: a chain of causes would
        /// repeat it.
        cause: std::io::Error,
    },
    /// PNG or GIF encoding failed.
    #[error("{path}: encoding: {cause}")]
    Encode {
        /// The file being written.
        path: PathBuf,
        /// The underlying error. Part of the message, so not its `source()`: a chain of causes would
        /// repeat it.
        cause: image::ImageError,
    },
}
