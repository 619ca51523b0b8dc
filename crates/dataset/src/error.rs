use std::path::PathBuf;

/// Everything that can go wrong reading or writing a dataset. Each variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The file could not be read or written.
    #[error("{path}: {cause}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error. Part of the message, so not its `source()`: a chain of causes would
        /// repeat it.
        cause: std::io::Error,
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
            cause: source,
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
            Error::Io { cause, .. } => Error::io(path, cause),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_io_error_is_told_once() {
        let e = Error::io("data/x.json", std::io::Error::other("boom"));
        assert_eq!(e.to_string(), "data/x.json: boom");
        // Its cause is in the message, so a report of the chain of causes does not repeat it.
        assert!(std::error::Error::source(&e).is_none());
    }
}
