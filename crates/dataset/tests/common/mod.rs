//! Helpers shared by this crate's integration tests.

use std::path::PathBuf;

/// A directory under the system temp dir, removed (with its contents) when dropped, so test
/// runs leave nothing behind. A failing test panics before the drop and keeps it for a look.
pub struct TempDir(PathBuf);

impl std::ops::Deref for TempDir {
    type Target = std::path::Path;
    fn deref(&self) -> &std::path::Path {
        &self.0
    }
}

impl AsRef<std::path::Path> for TempDir {
    fn as_ref(&self) -> &std::path::Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// A fresh, empty `pgrd-<prefix>-<pid>-<name>` directory under the system temp dir.
pub fn tmpdir(prefix: &str, name: &str) -> TempDir {
    let d = std::env::temp_dir().join(format!("pgrd-{prefix}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    TempDir(d)
}
