//! A dataset directory written as a whole: into a hidden staging folder beside its target and
//! moved into place only when complete, so that a command that fails half way (a bad source
//! file for `import`, an interrupted `gen`) leaves what was there untouched, and an existing
//! dataset is replaced only when the user said so (`--overwrite`).

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};

/// A staging folder for the dataset to be written at `target`.
#[derive(Debug)]
pub struct StagedDir {
    target: PathBuf,
    staging: PathBuf,
    committed: bool,
}

impl StagedDir {
    /// Prepares to write the dataset at `target`. An error, before anything is written, when
    /// `target` is a file, or a directory that is not empty and `overwrite` is false.
    pub fn new(target: &Path, overwrite: bool) -> anyhow::Result<Self> {
        let name = target
            .file_name()
            .with_context(|| format!("{}: not a directory name", target.display()))?
            .to_string_lossy()
            .into_owned();
        if target.exists() {
            if !target.is_dir() {
                bail!("{} is a file, not a dataset directory", target.display());
            }
            let empty = std::fs::read_dir(target)
                .with_context(|| format!("reading {}", target.display()))?
                .next()
                .is_none();
            if !empty && !overwrite {
                bail!(
                    "{} already exists and is not empty; pass --overwrite to replace it \
                     (the old contents are removed only once the new dataset is complete)",
                    target.display()
                );
            }
        }
        let staging = target.with_file_name(format!(".{name}.partial-{}", std::process::id()));
        if staging.exists() {
            std::fs::remove_dir_all(&staging)
                .with_context(|| format!("removing the stale {}", staging.display()))?;
        }
        Ok(StagedDir {
            target: target.to_path_buf(),
            staging,
            committed: false,
        })
    }

    /// Where to write the dataset now.
    pub fn path(&self) -> &Path {
        &self.staging
    }

    /// Moves the finished dataset to its target, replacing what was there.
    pub fn commit(mut self) -> anyhow::Result<()> {
        if self.target.exists() {
            let old = self
                .staging
                .with_extension(format!("replaced-{}", std::process::id()));
            std::fs::rename(&self.target, &old)
                .with_context(|| format!("moving the old {} aside", self.target.display()))?;
            std::fs::rename(&self.staging, &self.target)
                .with_context(|| format!("moving the new dataset to {}", self.target.display()))?;
            std::fs::remove_dir_all(&old)
                .with_context(|| format!("removing the old dataset ({})", old.display()))?;
        } else {
            std::fs::rename(&self.staging, &self.target)
                .with_context(|| format!("moving the new dataset to {}", self.target.display()))?;
        }
        self.committed = true;
        Ok(())
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if !self.committed {
            // Best effort: a half-written dataset nobody will read.
            let _ = std::fs::remove_dir_all(&self.staging);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("pgrd-staged-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn a_failed_write_leaves_the_old_dataset_and_a_commit_replaces_it_whole() {
        let root = dir("replace");
        let target = root.join("data");
        std::fs::create_dir_all(&target).unwrap();
        std::fs::write(target.join("ep_0004.safetensors"), "old").unwrap();
        // Not empty, not told to overwrite: refused before anything is written.
        let err = StagedDir::new(&target, false).unwrap_err().to_string();
        assert!(err.contains("--overwrite"), "{err}");
        // A write that fails half way (dropped without commit) leaves the target as it was.
        {
            let staged = StagedDir::new(&target, true).unwrap();
            std::fs::create_dir_all(staged.path()).unwrap();
            std::fs::write(staged.path().join("ep_0000.safetensors"), "new").unwrap();
        }
        let names = |d: &Path| -> Vec<String> {
            let mut v: Vec<String> = std::fs::read_dir(d)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            v.sort();
            v
        };
        assert_eq!(names(&target), ["ep_0004.safetensors"]);
        assert_eq!(names(&root), ["data"], "no staging folder left behind");
        // A commit replaces the whole directory: no file of the old dataset remains.
        let staged = StagedDir::new(&target, true).unwrap();
        std::fs::create_dir_all(staged.path()).unwrap();
        std::fs::write(staged.path().join("ep_0000.safetensors"), "new").unwrap();
        staged.commit().unwrap();
        assert_eq!(names(&target), ["ep_0000.safetensors"]);
        assert_eq!(names(&root), ["data"]);
        std::fs::remove_dir_all(&root).ok();
    }

    #[test]
    fn an_empty_or_missing_target_needs_no_overwrite_and_a_file_is_refused() {
        let root = dir("fresh");
        for target in [root.join("new"), root.join("empty")] {
            if target.ends_with("empty") {
                std::fs::create_dir_all(&target).unwrap();
            }
            let staged = StagedDir::new(&target, false).unwrap();
            std::fs::create_dir_all(staged.path()).unwrap();
            std::fs::write(staged.path().join("dataset.json"), "{}").unwrap();
            staged.commit().unwrap();
            assert!(target.join("dataset.json").is_file());
        }
        std::fs::write(root.join("file"), "x").unwrap();
        assert!(StagedDir::new(&root.join("file"), true).is_err());
        std::fs::remove_dir_all(&root).ok();
    }
}
