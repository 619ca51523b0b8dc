//! A development split: choose models on training recordings only, keep the held-out split
//! for one final score.
//!
//! Every pgrd stage that compares models (the diagnosis's rounds, `train --holdout`'s
//! checkpoint and recipe choice) judges on some held-out episodes. When those are the
//! dataset's `val` split and the final numbers are reported on `val` too, the report has seen
//! its own test. [`dev_split`] writes a copy of a dataset in which the last `hold_out`
//! training episodes become `val` (exactly the episodes `train --holdout <hold_out>` holds
//! out of the original), the old `val` becomes `test`, and nothing else changes.
//!
//! Where more recordings can be had (a generated dataset, `gen --val <more>`), two held-out
//! recordings judge a network poorly; [`select_split`] instead keeps the last `select` val
//! episodes as `val`, the selection set, moves the rest of `val` to `test`, and leaves every
//! training episode to train on (`train --select-on-val`).

use std::path::Path;

use crate::meta::{INDEX_FILE, write_index};
use crate::{Dataset, DatasetMeta, Error, Result, Split, write_atomic};

/// What [`dev_split`] wrote: episode counts per split of the new dataset, and the dataset
/// indices of the training episodes that became `val`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DevSplitReport {
    /// Training episodes left in `train`.
    pub train: usize,
    /// The new `val` episodes (the last `hold_out` of the old `train`, or with
    /// [`select_split`] the last `select` of the old `val`).
    pub val: usize,
    /// `test` episodes: the old `val` (less the kept ones) plus any old `test`.
    pub test: usize,
    /// Dataset indices (the same in both datasets) of the new `val` episodes.
    pub val_indices: Vec<usize>,
}

/// The index of `meta` with its last `hold_out` training episodes (in file order) moved to
/// `val` and its `val` episodes moved to `test`. Errors when `hold_out` is 0 or leaves no
/// training episode.
pub fn dev_split_meta(meta: &DatasetMeta, hold_out: usize) -> Result<(DatasetMeta, Vec<usize>)> {
    let train = meta.split_indices(Split::Train);
    if hold_out == 0 || hold_out >= train.len() {
        return Err(Error::invalid(
            INDEX_FILE,
            format!(
                "cannot hold out {hold_out} of {} training episodes (need 1 ..= {})",
                train.len(),
                train.len().saturating_sub(1)
            ),
        ));
    }
    let moved = train[train.len() - hold_out..].to_vec();
    let mut out = meta.clone();
    for (i, e) in out.episodes.iter_mut().enumerate() {
        e.split = match e.split {
            Split::Train if moved.contains(&i) => Split::Val,
            Split::Train => Split::Train,
            Split::Val | Split::Test => Split::Test,
        };
    }
    Ok((out, moved))
}

/// Writes the development split of `src` (see [`dev_split_meta`]) as a new dataset in `out`,
/// which must not exist yet or be an empty directory. Every plain file of `src` besides its
/// index (episodes, provenance, ground-truth Gaussians) is copied unchanged, each atomically;
/// the new index is written last, so an interrupted copy leaves no dataset that opens.
///
/// ```
/// use dataset::{Dataset, DatasetMeta, DatasetWriter, Episode, Manipulation, Split, dev_split};
/// use glam::Vec3;
/// # let base = std::env::temp_dir().join(format!("pgrd-devsplit-doc-{}", std::process::id()));
/// # let (src, out) = (base.join("src"), base.join("dev"));
/// let mut w = DatasetWriter::create(&src, DatasetMeta::new("rope", 10.0, Manipulation::Grasp))?;
/// let ep = Episode::new(1, 1, 1, vec![Vec3::ZERO], vec![Vec3::ZERO])?;
/// for split in [Split::Train, Split::Train, Split::Train, Split::Val] {
///     w.add_episode(&ep, split)?;
/// }
/// let src = w.finish()?;
/// let report = dev_split(&src, &out, 1)?;
/// assert_eq!((report.train, report.val, report.test), (2, 1, 1));
/// assert_eq!(Dataset::open(&out)?.split_indices(Split::Val), vec![2]);
/// # std::fs::remove_dir_all(&base).ok();
/// # Ok::<(), dataset::Error>(())
/// ```
pub fn dev_split(src: &Dataset, out: &Path, hold_out: usize) -> Result<DevSplitReport> {
    let (meta, moved) =
        dev_split_meta(&src.meta, hold_out).map_err(|e| relocate(e, &src.root.join(INDEX_FILE)))?;
    write_copy(src, out, &meta, moved)
}

/// The index of `meta` with its last `select` `val` episodes (in file order) kept as `val`,
/// its other `val` episodes moved to `test`, and its training episodes unchanged; also the
/// dataset indices of the kept episodes. Errors when `select` is 0 or leaves no episode to
/// move to `test`.
pub fn select_split_meta(meta: &DatasetMeta, select: usize) -> Result<(DatasetMeta, Vec<usize>)> {
    let val = meta.split_indices(Split::Val);
    if select == 0 || select >= val.len() {
        return Err(Error::invalid(
            INDEX_FILE,
            format!(
                "cannot keep {select} of {} val episodes for selection (need 1 ..= {}, so that \
                 some stay to be reported on as test)",
                val.len(),
                val.len().saturating_sub(1)
            ),
        ));
    }
    let kept = val[val.len() - select..].to_vec();
    let mut out = meta.clone();
    for (i, e) in out.episodes.iter_mut().enumerate() {
        if e.split == Split::Val && !kept.contains(&i) {
            e.split = Split::Test;
        }
    }
    Ok((out, kept))
}

/// Writes the selection split of `src` (see [`select_split_meta`]) as a new dataset in `out`,
/// copied as [`dev_split`] copies: a new or empty directory, every file atomically, the index
/// last.
pub fn select_split(src: &Dataset, out: &Path, select: usize) -> Result<DevSplitReport> {
    let (meta, kept) = select_split_meta(&src.meta, select)
        .map_err(|e| relocate(e, &src.root.join(INDEX_FILE)))?;
    write_copy(src, out, &meta, kept)
}

/// Copies every plain file of `src` but its index to the new or empty directory `out`, then
/// writes `meta` as the index.
fn write_copy(
    src: &Dataset,
    out: &Path,
    meta: &DatasetMeta,
    val_indices: Vec<usize>,
) -> Result<DevSplitReport> {
    ensure_new_dir(out, "a development split")?;
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let entries = std::fs::read_dir(&src.root).map_err(|e| Error::io(&src.root, e))?;
    for entry in entries {
        let entry = entry.map_err(|e| Error::io(&src.root, e))?;
        let path = entry.path();
        // Follows links: an episode stored as a link to a file is copied as that file.
        if !path.is_file() || entry.file_name() == INDEX_FILE {
            continue;
        }
        let bytes = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
        // A listed episode is read as it is copied, so a damaged one stops the copy here
        // rather than in whatever later reads the split.
        let name = entry.file_name();
        if meta
            .episodes
            .iter()
            .any(|e| std::ffi::OsStr::new(&e.file) == name)
        {
            crate::Episode::from_bytes(&bytes, &path)?;
        }
        write_atomic(&out.join(name), &bytes)?;
    }
    write_index(out, meta)?;
    let count = |s| meta.episodes.iter().filter(|e| e.split == s).count();
    Ok(DevSplitReport {
        train: count(Split::Train),
        val: count(Split::Val),
        test: count(Split::Test),
        val_indices,
    })
}

/// Errors unless `out` does not exist or is an empty directory: `what` (a new dataset) is
/// always written to a new directory, never over another.
pub(crate) fn ensure_new_dir(out: &Path, what: &str) -> Result<()> {
    let occupied = out.exists()
        && std::fs::read_dir(out)
            .map_err(|e| Error::io(out, e))?
            .next()
            .is_some();
    if occupied {
        return Err(Error::invalid(
            out,
            format!(
                "the output directory exists and is not empty ({what} is always written to a \
                 new directory)"
            ),
        ));
    }
    Ok(())
}

/// The same error, naming `path` (the source index) instead of the bare index file name.
fn relocate(e: Error, path: &Path) -> Error {
    match e {
        Error::Invalid { message, .. } => Error::invalid(path, message),
        other => other,
    }
}
