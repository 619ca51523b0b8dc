//! The DEFORM cable recordings (DLO1–DLO3) as a pgrd dataset.
//!
//! Source layout: `<dir>/train/*.pkl` and `<dir>/eval/*.pkl`, each a pickle of a nested list
//! `[frames][3][markers]` of floats: metres, z up, 100 Hz. Conversion:
//! - `train/` becomes the `train` split and `eval/` the `val` split, files in numeric order;
//! - the two markers at each end (0, 1, n−2, n−1) are held by four grippers whose positions are
//!   those markers' recorded trajectories (DEFORM's protocol drives them with robots);
//! - `fps` is 100 (one model step = 0.01 s), no ground plane, structure `chain` so the backbone
//!   may add hidden particles between the ~10 cm-spaced markers.
//!
//! Raw tracking glitches (single-frame spikes) are kept: they are part of the data DEFORM's own
//! numbers were measured on.

use std::path::{Path, PathBuf};

use glam::Vec3;

use super::pickle::{self, Value};
use crate::{DatasetMeta, DatasetWriter, Episode, Error, Manipulation, Result, Split, Structure};

/// Recording rate of the DEFORM motion capture, frames per second.
pub const DEFORM_FPS: f32 = 100.0;

/// One imported recording: its source file and marker trajectories.
#[derive(Clone, Debug)]
pub struct Recording {
    /// The pickle it came from.
    pub source: PathBuf,
    /// Marker positions, frame-major `[frames × markers]`, metres.
    pub positions: Vec<Vec3>,
    /// Number of frames.
    pub frames: usize,
    /// Number of markers.
    pub markers: usize,
}

/// Reads one DEFORM pickle and checks it is `[frames][3][markers]` of finite numbers.
pub fn read_recording(path: &Path) -> Result<Recording> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let value = pickle::parse(&bytes).map_err(|m| Error::invalid(path, m))?;
    let bad = |m: String| Error::invalid(path, m);
    let Value::List(frames) = value else {
        return Err(bad("expected a list of frames".into()));
    };
    if frames.len() < 3 {
        return Err(bad(format!(
            "expected at least 3 frames, found {}",
            frames.len()
        )));
    }
    let mut markers = None;
    let mut positions = Vec::new();
    for (t, frame) in frames.iter().enumerate() {
        let coords = match frame {
            Value::List(c) if c.len() == 3 => c,
            _ => {
                return Err(bad(format!(
                    "frame {t} is not a list of 3 coordinate lists"
                )));
            }
        };
        let mut axes = [&[][..]; 3];
        for (a, axis) in coords.iter().enumerate() {
            let Value::List(values) = axis else {
                return Err(bad(format!("frame {t}, axis {a} is not a list")));
            };
            axes[a] = values;
        }
        let n = axes[0].len();
        if axes.iter().any(|a| a.len() != n) || n < 5 {
            return Err(bad(format!(
                "frame {t}: the three axes must list the same number (>= 5) of markers"
            )));
        }
        match markers {
            None => markers = Some(n),
            Some(m) if m != n => {
                return Err(bad(format!(
                    "frame {t} has {n} markers, earlier frames have {m}"
                )));
            }
            Some(_) => {}
        }
        for i in 0..n {
            let mut p = [0f32; 3];
            for (a, (out, axis)) in p.iter_mut().zip(axes).enumerate() {
                let v = axis[i].as_f64().filter(|v| v.is_finite()).ok_or_else(|| {
                    bad(format!(
                        "frame {t}, axis {a}, marker {i} is not a finite number"
                    ))
                })?;
                *out = v as f32;
            }
            positions.push(Vec3::from_array(p));
        }
    }
    Ok(Recording {
        source: path.to_path_buf(),
        positions,
        frames: frames.len(),
        markers: markers.unwrap_or(0),
    })
}

impl Recording {
    /// This recording as an episode: end markers held by four grippers following them.
    pub fn to_episode(&self) -> Result<Episode> {
        let n = self.markers;
        let ends = [0, 1, n - 2, n - 1];
        let grippers = (0..self.frames)
            .flat_map(|t| ends.map(|i| self.positions[t * n + i]))
            .collect();
        let mut held = vec![-1; n];
        for (g, i) in ends.iter().enumerate() {
            held[*i] = g as i32;
        }
        Episode::new(self.frames, n, 4, self.positions.clone(), grippers)?.with_held(held)
    }
}

/// Pickle files of `dir`, sorted by their numeric stem (then by name).
fn pickles(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut files = Vec::new();
    for entry in entries {
        let path = entry.map_err(|e| Error::io(dir, e))?.path();
        if path.extension().is_some_and(|e| e == "pkl") {
            files.push(path);
        }
    }
    let key = |p: &PathBuf| {
        let stem = p.file_stem().and_then(|s| s.to_str()).unwrap_or("");
        (stem.parse::<u64>().unwrap_or(u64::MAX), stem.to_string())
    };
    files.sort_by_key(key);
    Ok(files)
}

/// A summary of one import, also written as `import.json` beside the dataset.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ImportReport {
    /// Object name written to `dataset.json`.
    pub object: String,
    /// Markers per frame.
    pub markers: usize,
    /// `(episode file, split, source pickle)` for every episode.
    pub episodes: Vec<(String, Split, String)>,
}

/// Converts a DEFORM `DLOk` directory (with `train/` and `eval/`) into a pgrd dataset at `out`.
pub fn import(dir: &Path, out: &Path) -> Result<ImportReport> {
    let object = dir
        .file_name()
        .and_then(|s| s.to_str())
        .unwrap_or("deform")
        .to_string();
    let mut meta = DatasetMeta::new(&object, DEFORM_FPS, Manipulation::Grasp);
    meta.ground_z = None;
    meta.structure = Structure::Chain;
    meta.gripper_radius = 0.0;
    let mut jobs = Vec::new();
    for (sub, split) in [("train", Split::Train), ("eval", Split::Val)] {
        let d = dir.join(sub);
        if !d.is_dir() {
            return Err(Error::invalid(
                &d,
                "missing: a DEFORM directory holds train/ and eval/ folders of .pkl files",
            ));
        }
        jobs.extend(pickles(&d)?.into_iter().map(|p| (p, split)));
    }
    if jobs.is_empty() {
        return Err(Error::invalid(dir, "no .pkl files under train/ or eval/"));
    }
    let mut writer = DatasetWriter::create(out, meta)?;
    let mut report = ImportReport {
        object,
        markers: 0,
        episodes: Vec::new(),
    };
    for (path, split) in jobs {
        let rec = read_recording(&path)?;
        if report.markers != 0 && rec.markers != report.markers {
            return Err(Error::invalid(
                &path,
                format!(
                    "has {} markers, earlier files have {}",
                    rec.markers, report.markers
                ),
            ));
        }
        report.markers = rec.markers;
        // A coordinate beyond f32's range (±3.4e38) is finite in the pickle but not here.
        let episode = rec.to_episode().map_err(|e| {
            e.at(&path)
                .with_note("as 32-bit floats, the format's type (±3.4e38 at most)")
        })?;
        let index = writer.add_episode(&episode, split)?;
        let file = format!("ep_{index:04}.safetensors");
        report
            .episodes
            .push((file, split, path.display().to_string()));
    }
    writer.finish()?;
    let json = serde_json::to_string_pretty(&report)
        .map_err(|e| Error::invalid(out, format!("cannot serialise import report: {e}")))?;
    crate::write_atomic(&out.join("import.json"), json.as_bytes())?;
    Ok(report)
}
