//! Merging datasets of one object: training on two kinds of motion, or a selection set drawn
//! from another recording session, needs one dataset that lists both.
//!
//! [`merge`] takes the episodes of one split from each of several datasets, in the order the
//! parts are given, and writes them as a new dataset: each episode file copied byte for byte
//! under a fresh name (`ep_NNNN.safetensors`, the new index), the reference world's
//! ground-truth Gaussians (`truth_ep_NNNN.safetensors`) renamed with their episode, and
//! `merge.json` saying where every episode came from. Order matters to the stages that hold
//! out "the last N training episodes" (`train --holdout`, [`crate::dev_split`]): put the part
//! whose recordings should be held out last.
//!
//! The datasets must describe the same object the same way (object name, frame rate,
//! gravity, ground, manipulation, gripper radius, structure): particle `i` names one material
//! point across a dataset's episodes, which only holds within one object.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::meta::{INDEX_FILE, write_index};
use crate::{Dataset, DatasetMeta, EpisodeEntry, Error, Result, Split, write_atomic};

/// The provenance file [`merge`] writes beside the index.
pub const MERGE_FILE: &str = "merge.json";

/// One part of a merge: the episodes of `split` in `data`, listed in the new dataset as
/// `as_split`.
#[derive(Clone, Copy, Debug)]
pub struct MergePart<'a> {
    /// The source dataset (left unchanged).
    pub data: &'a Dataset,
    /// Which of its episodes to take.
    pub split: Split,
    /// Their split in the merged dataset (usually `split` itself).
    pub as_split: Split,
}

/// What [`merge`] wrote: episode counts per split of the new dataset, and per part.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MergeReport {
    /// Episodes per split of the merged dataset: train, val, test.
    pub counts: [usize; 3],
    /// Episodes taken from each part, in the parts' order.
    pub per_part: Vec<usize>,
}

#[derive(Serialize)]
struct Provenance<'a> {
    format: &'static str,
    episodes: Vec<Origin<'a>>,
}

#[derive(Serialize)]
struct Origin<'a> {
    file: String,
    split: Split,
    from_dataset: String,
    from_file: &'a str,
    from_split: Split,
}

/// Writes the episodes `parts` name, in that order, as a new dataset in `out` (a new or empty
/// directory). The index is written last, so an interrupted merge leaves no dataset that
/// opens. Errors, naming the dataset, when a part has no episode of its split or describes
/// another object or another setting than the first part.
///
/// ```
/// use dataset::{Dataset, DatasetMeta, DatasetWriter, Episode, Manipulation, MergePart, Split, merge};
/// use glam::Vec3;
/// # let base = std::env::temp_dir().join(format!("pgrd-merge-doc-{}", std::process::id()));
/// # let (a, b, out) = (base.join("a"), base.join("b"), base.join("ab"));
/// let ep = Episode::new(1, 1, 1, vec![Vec3::ZERO], vec![Vec3::ZERO])?;
/// for (dir, splits) in [(&a, [Split::Train, Split::Val]), (&b, [Split::Train, Split::Train])] {
///     let mut w = DatasetWriter::create(dir, DatasetMeta::new("rope", 10.0, Manipulation::Grasp))?;
///     for split in splits {
///         w.add_episode(&ep, split)?;
///     }
///     w.finish()?;
/// }
/// let (a, b) = (Dataset::open(&a)?, Dataset::open(&b)?);
/// let part = |data, split| MergePart { data, split, as_split: split };
/// let report = merge(&[part(&a, Split::Train), part(&b, Split::Train), part(&a, Split::Val)], &out)?;
/// assert_eq!(report.counts, [3, 1, 0]);
/// assert_eq!(Dataset::open(&out)?.split_indices(Split::Val), vec![3]);
/// # std::fs::remove_dir_all(&base).ok();
/// # Ok::<(), dataset::Error>(())
/// ```
pub fn merge(parts: &[MergePart<'_>], out: &Path) -> Result<MergeReport> {
    let Some(first) = parts.first() else {
        return Err(Error::invalid(out, "a merge needs at least one part"));
    };
    for part in parts {
        check_compatible(&first.data.meta, part.data)?;
        if part.data.meta.split_indices(part.split).is_empty() {
            return Err(Error::invalid(
                part.data.root.join(INDEX_FILE),
                format!("no `{}` episodes to merge", part.split),
            ));
        }
    }
    crate::dev_split::ensure_new_dir(out, "a merge")?;
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let mut meta = DatasetMeta {
        episodes: Vec::new(),
        ..first.data.meta.clone()
    };
    let mut origins = Vec::new();
    let mut per_part = Vec::with_capacity(parts.len());
    for part in parts {
        let indices = part.data.meta.split_indices(part.split);
        per_part.push(indices.len());
        for i in indices {
            let j = meta.episodes.len();
            let from = &part.data.meta.episodes[i];
            let file = format!("ep_{j:04}.safetensors");
            copy_file(&part.data.root.join(&from.file), &out.join(&file))?;
            let truth = part.data.root.join(truth_file(i));
            if truth.is_file() {
                copy_file(&truth, &out.join(truth_file(j)))?;
            }
            origins.push(Origin {
                file: file.clone(),
                split: part.as_split,
                from_dataset: part.data.root.display().to_string(),
                from_file: &from.file,
                from_split: part.split,
            });
            meta.episodes.push(EpisodeEntry {
                file,
                split: part.as_split,
            });
        }
    }
    let provenance = Provenance {
        format: "pgrd-merge/1",
        episodes: origins,
    };
    let text = serde_json::to_string_pretty(&provenance)
        .map_err(|e| Error::invalid(out.join(MERGE_FILE), e.to_string()))?;
    write_atomic(&out.join(MERGE_FILE), text.as_bytes())?;
    write_index(out, &meta)?;
    let count = |s| meta.episodes.iter().filter(|e| e.split == s).count();
    Ok(MergeReport {
        counts: [count(Split::Train), count(Split::Val), count(Split::Test)],
        per_part,
    })
}

/// The reference world's ground-truth Gaussians of episode `index` (`world::TruthGaussians`
/// names them so; this crate does not read them).
fn truth_file(index: usize) -> String {
    format!("truth_ep_{index:04}.safetensors")
}

fn copy_file(from: &Path, to: &Path) -> Result<()> {
    let bytes = std::fs::read(from).map_err(|e| Error::io(from, e))?;
    write_atomic(to, &bytes)
}

/// Errors, naming `data`'s index and the first setting that differs, unless `data` describes
/// the same object the same way as `reference`.
fn check_compatible(reference: &DatasetMeta, data: &Dataset) -> Result<()> {
    let m = &data.meta;
    let differs: Option<(&str, String, String)> = if m.object != reference.object {
        Some(("object", m.object.clone(), reference.object.clone()))
    } else if m.fps != reference.fps {
        Some(("fps", m.fps.to_string(), reference.fps.to_string()))
    } else if m.gravity != reference.gravity {
        Some(("gravity", fmt(&m.gravity), fmt(&reference.gravity)))
    } else if m.ground_z != reference.ground_z {
        Some(("ground_z", fmt(&m.ground_z), fmt(&reference.ground_z)))
    } else if m.manipulation != reference.manipulation {
        Some((
            "manipulation",
            fmt(&m.manipulation),
            fmt(&reference.manipulation),
        ))
    } else if m.gripper_radius != reference.gripper_radius {
        Some((
            "gripper_radius",
            m.gripper_radius.to_string(),
            reference.gripper_radius.to_string(),
        ))
    } else if m.structure != reference.structure {
        Some(("structure", fmt(&m.structure), fmt(&reference.structure)))
    } else if m.controller_springs != reference.controller_springs {
        Some((
            "controller_springs",
            fmt(&m.controller_springs),
            fmt(&reference.controller_springs),
        ))
    } else {
        None
    };
    match differs {
        None => Ok(()),
        Some((key, here, there)) => Err(Error::invalid(
            PathBuf::from(&data.root).join(INDEX_FILE),
            format!(
                "`{key}` is {here} here but {there} in the first part: only datasets of one \
                 object recorded the same way can be merged"
            ),
        )),
    }
}

fn fmt(value: &impl std::fmt::Debug) -> String {
    format!("{value:?}")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{DatasetWriter, Episode, Manipulation};
    use glam::Vec3;

    fn dataset(dir: &Path, meta: DatasetMeta, splits: &[Split], mark: f32) -> Dataset {
        let mut w = DatasetWriter::create(dir, meta).unwrap();
        for (k, split) in splits.iter().enumerate() {
            // Each episode's one particle sits at a distinct height, so copies can be told apart.
            let x = Vec3::new(0.0, 0.0, mark + k as f32);
            let ep = Episode::new(2, 1, 1, vec![x, x], vec![Vec3::ZERO; 2]).unwrap();
            w.add_episode(&ep, *split).unwrap();
        }
        w.finish().unwrap()
    }

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("pgrd-merge-{name}-{}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        dir
    }

    #[test]
    fn episodes_keep_their_content_and_come_in_the_parts_order() {
        let base = scratch("order");
        let meta = DatasetMeta::new("rope", 10.0, Manipulation::Grasp);
        let a = dataset(
            &base.join("a"),
            meta.clone(),
            &[Split::Train, Split::Val, Split::Train],
            0.0,
        );
        let b = dataset(&base.join("b"), meta, &[Split::Train, Split::Test], 10.0);
        std::fs::write(a.root.join(truth_file(2)), b"gaussians of a's third").unwrap();
        let out = base.join("ab");
        let parts = [
            MergePart {
                data: &a,
                split: Split::Train,
                as_split: Split::Train,
            },
            MergePart {
                data: &b,
                split: Split::Train,
                as_split: Split::Train,
            },
            MergePart {
                data: &a,
                split: Split::Val,
                as_split: Split::Val,
            },
            MergePart {
                data: &b,
                split: Split::Test,
                as_split: Split::Val,
            },
        ];
        let report = merge(&parts, &out).unwrap();
        assert_eq!(report.counts, [3, 2, 0]);
        assert_eq!(report.per_part, vec![2, 1, 1, 1]);
        let merged = Dataset::open(&out).unwrap();
        let height = |d: &Dataset, i| d.load_episode(i).unwrap().frame(0)[0].z;
        // a's train (0, 2), b's train (0), a's val (1), b's test (1).
        let expected = [0.0, 2.0, 10.0, 1.0, 11.0];
        for (i, z) in expected.iter().enumerate() {
            assert_eq!(height(&merged, i), *z, "episode {i}");
        }
        assert_eq!(merged.split_indices(Split::Val), vec![3, 4]);
        // a's third episode is the merged dataset's second: its Gaussians follow it.
        let truth = std::fs::read(out.join(truth_file(1))).unwrap();
        assert_eq!(truth, b"gaussians of a's third");
        assert!(!out.join(truth_file(2)).exists());
        let provenance: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join(MERGE_FILE)).unwrap()).unwrap();
        assert_eq!(provenance["episodes"][4]["from_split"], "test");
        assert_eq!(provenance["episodes"][4]["split"], "val");
        std::fs::remove_dir_all(&base).ok();
    }

    #[test]
    fn other_objects_settings_and_empty_parts_are_refused() {
        let base = scratch("refuse");
        let rope = DatasetMeta::new("rope", 10.0, Manipulation::Grasp);
        let a = dataset(&base.join("a"), rope.clone(), &[Split::Train], 0.0);
        let cloth = dataset(
            &base.join("cloth"),
            DatasetMeta::new("cloth", 10.0, Manipulation::Grasp),
            &[Split::Train],
            0.0,
        );
        let fast = dataset(
            &base.join("fast"),
            DatasetMeta::new("rope", 30.0, Manipulation::Grasp),
            &[Split::Train],
            0.0,
        );
        let part = |data| MergePart {
            data,
            split: Split::Train,
            as_split: Split::Train,
        };
        for (other, key) in [(&cloth, "`object`"), (&fast, "`fps`")] {
            let err = merge(&[part(&a), part(other)], &base.join("x")).unwrap_err();
            assert!(err.to_string().contains(key), "{err}");
            assert!(!base.join("x").join(INDEX_FILE).exists());
        }
        let no_val = MergePart {
            data: &a,
            split: Split::Val,
            as_split: Split::Val,
        };
        let err = merge(&[part(&a), no_val], &base.join("y")).unwrap_err();
        assert!(err.to_string().contains("no `val` episodes"), "{err}");
        // Never into a directory that holds something.
        let err = merge(&[part(&a)], &base.join("a")).unwrap_err();
        assert!(err.to_string().contains("not empty"), "{err}");
        assert!(merge(&[], &base.join("z")).is_err());
        std::fs::remove_dir_all(&base).ok();
    }
}
