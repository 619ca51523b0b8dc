use std::path::PathBuf;

/// Everything that can go wrong reading or writing a dataset. Each variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The file was read but its content breaks the format contract.
    #[error("{path}: {message}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong, in words a user can act on.
        message: String,
    },
}

impl Error {
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }

    pub(crate) fn invalid(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Invalid {
            path: path.into(),
            message: message.into(),
        }
    }

    /// The same error with `note` added to its message (an I/O error is left as it is).
    pub(crate) fn with_note(self, note: &str) -> Self {
        match self {
            Error::Invalid { path, message } => Error::invalid(path, format!("{message} ({note})")),
            other => other,
        }
    }

    /// The same error about `path` (an episode built in memory names no file until its
    /// source's path is known).
    pub(crate) fn at(self, path: impl Into<PathBuf>) -> Self {
        match self {
            Error::Invalid { message, .. } => Error::invalid(path, message),
            Error::Io { source, .. } => Error::io(path, source),
        }
    }
}
