//! PhysTwin's processed captures (a case directory holding `final_data.pkl` and `split.json`)
//! as a pgrd dataset, cut into episodes the way the PGRD paper cuts its recordings.
//!
//! Source, as PhysTwin's `data_process_sample.py` writes it (a pickled dict of numpy arrays):
//! `object_points` [T, N, 3] (metres, z down: PhysTwin's `reverse_z`; a point the tracker did
//! not see at a frame is stored as zeros there), `object_visibilities` [T, N] and
//! `object_motions_valid` [T, N] (row t: the track is valid from frame t to t + 1),
//! `object_colors` [T, N, 3], `controller_points` [T, C, 3] (the hand or gripper points that
//! drive the object), and `surface_points` / `interior_points` of a shape prior, not used here.
//! `split.json` names the training frames `[0, a)` and the test frames `[a, T)`; without it
//! the first 70 % train, as PhysTwin's `process_data.py` splits. Conversion:
//! - coordinates turned 180° about x, `(x, y, z) → (x, −y, −z)`, so z is up and PhysTwin's
//!   ground plane z = 0 stays the ground;
//! - a point counts as seen at frame t when PhysTwin's tracker saw it there and, for t > 0,
//!   its motion from t − 1 was valid (the mask PhysTwin's own tracking loss uses); where it is
//!   not seen its last seen position is stored (its first, before it was first seen), as the
//!   format asks, whatever the pickle holds there (zeros, NaN); a point never seen is left out;
//! - every `every`-th frame is kept (30 fps → 10 fps by default, the paper's step);
//! - the training and the test frames are each cut into windows of `episode_frames` kept
//!   frames every `stride_frames` (the paper: 4 s episodes every 2 s, so neighbours overlap),
//!   which become the `train` and the `val` episodes; PhysTwin itself scores one rollout from
//!   frame 0 through the test frames instead;
//! - each controller point is a gripper, always closed; by default (`attach`) each is a
//!   particle of the model joined by springs to the object particles near it at a rollout's
//!   start, as PhysTwin joins its controller points: with their own radius and spring count
//!   (`controller_springs` in `dataset.json`; PhysTwin's defaults, 4 cm and 50, unless
//!   [`PhysTwinOptions::controller_springs`] says otherwise, e.g. a case's fitted
//!   `controller_radius` and `controller_max_neighbours`); under `grasp` the object points
//!   within `gripper_radius` of one follow the nearest rigidly instead, and under `push` they
//!   are spheres that push.

use std::path::{Path, PathBuf};

use glam::Vec3;

use super::pickle::{self, NdArray, Value};
use crate::{
    ControllerSprings, DatasetMeta, DatasetWriter, Episode, Error, Manipulation, Result, Split,
};

/// How a capture becomes episodes.
#[derive(Clone, Copy, Debug)]
pub struct PhysTwinOptions {
    /// Keep every `every`-th frame (PhysTwin records at 30 fps).
    pub every: usize,
    /// Kept frames per episode.
    pub episode_frames: usize,
    /// Kept frames between consecutive episodes' first frames.
    pub stride_frames: usize,
    /// Recording rate of the capture, frames per second.
    pub source_fps: f32,
    /// How the controller points act on the object.
    pub manipulation: Manipulation,
    /// Radius within which a controller point holds (`grasp`) or pushes (`push`) object
    /// points, m; unused by `attach`.
    pub gripper_radius_m: f32,
    /// `attach` only: the controller points' own spring rule; `None` joins them by the
    /// object's fitted threshold and spring count.
    pub controller_springs: Option<ControllerSprings>,
}

impl Default for PhysTwinOptions {
    /// The PGRD paper's protocol on PhysTwin's 30 fps captures: 10 fps, 4 s episodes every 2 s.
    fn default() -> Self {
        PhysTwinOptions {
            every: 3,
            episode_frames: 40,
            stride_frames: 20,
            source_fps: 30.0,
            manipulation: Manipulation::Attach,
            gripper_radius_m: 0.02,
            controller_springs: Some(ControllerSprings::PHYSTWIN),
        }
    }
}

/// A capture read from `final_data.pkl`, in pgrd's frame (z up), every frame.
#[derive(Clone, Debug)]
pub struct Capture {
    /// Frames.
    pub frames: usize,
    /// Object points kept (seen at least once).
    pub points: usize,
    /// Controller points.
    pub controllers: usize,
    /// Object positions, frame-major, m; unseen entries hold the last (or first) seen position.
    pub positions: Vec<Vec3>,
    /// Whether each point was seen at each frame, frame-major.
    pub seen: Vec<bool>,
    /// Controller positions, frame-major, m.
    pub controller_positions: Vec<Vec3>,
    /// Each kept point's colour at its first sighting, RGB in [0, 1], if the capture has colours.
    pub colors: Option<Vec<[f32; 3]>>,
    /// Object points of the pickle never seen, left out.
    pub never_seen: usize,
}

/// The array `key` of the pickled dict, checked against `shape` (`None`: any size).
fn shaped<'a>(
    data: &'a Value,
    key: &str,
    shape: &[Option<usize>],
    path: &Path,
) -> Result<&'a NdArray> {
    let a = match data.get(key) {
        Some(Value::Array(a)) => a,
        Some(_) => {
            return Err(Error::invalid(
                path,
                format!("'{key}' is not a numpy array"),
            ));
        }
        None => return Err(Error::invalid(path, format!("no '{key}' array"))),
    };
    let fits = a.shape.len() == shape.len()
        && a.shape
            .iter()
            .zip(shape)
            .all(|(d, s)| s.is_none_or(|s| s == *d));
    if !fits {
        let want: Vec<String> = shape
            .iter()
            .map(|s| s.map_or("_".to_string(), |s| s.to_string()))
            .collect();
        return Err(Error::invalid(
            path,
            format!(
                "'{key}' has shape {:?}, expected [{}]",
                a.shape,
                want.join(", ")
            ),
        ));
    }
    Ok(a)
}

/// Coordinate triples as points of pgrd's frame: PhysTwin's turned 180° about x, so z is up.
fn turned_up(values: &[f64]) -> Vec<Vec3> {
    values
        .chunks_exact(3)
        .map(|c| Vec3::new(c[0] as f32, -(c[1] as f32), -(c[2] as f32)))
        .collect()
}

/// The index of the first point of `points` that is not finite (as 32-bit floats) where `keep`.
fn first_non_finite(points: &[Vec3], keep: impl Fn(usize) -> bool) -> Option<usize> {
    (0..points.len()).find(|k| keep(*k) && !points[*k].is_finite())
}

/// The controller rule a PhysTwin case was fitted with: `controller_radius` (m) and
/// `controller_max_neighbours` from the `optimal_params.pkl` its first stage writes (a pickled
/// dict of Python and numpy numbers). Its other entries are PhysTwin's own model's and are not
/// read: pgrd's backbone fits its own.
pub fn read_controller_rule(path: &Path) -> Result<ControllerSprings> {
    let data = read_dict(
        path,
        "expected a pickled dict of parameters (PhysTwin's optimal_params.pkl)",
    )?;
    let number = |key: &str| -> Result<f64> {
        let value = data.get(key).ok_or_else(|| {
            Error::invalid(
                path,
                format!("no '{key}': is this PhysTwin's optimal_params.pkl?"),
            )
        })?;
        let x = match value {
            Value::Array(a) if a.shape.is_empty() && a.len() == 1 => a.to_f64().first().copied(),
            other => other.as_f64(),
        };
        x.ok_or_else(|| Error::invalid(path, format!("'{key}' is not a number")))
    };
    let radius = number("controller_radius")?;
    let count = number("controller_max_neighbours")?;
    if !(radius.is_finite() && radius > 0.0) {
        return Err(Error::invalid(
            path,
            format!("'controller_radius' must be a positive number of metres, got {radius}"),
        ));
    }
    if !(count.is_finite() && count >= 1.0 && count.fract() == 0.0 && count <= f64::from(u32::MAX))
    {
        return Err(Error::invalid(
            path,
            format!("'controller_max_neighbours' must be a whole number >= 1, got {count}"),
        ));
    }
    Ok(ControllerSprings {
        radius_m: radius as f32,
        max_springs: count as u32,
    })
}

/// The pickled dict at `path`; `not_a_dict` is the error's message when it holds something
/// else.
fn read_dict(path: &Path, not_a_dict: &str) -> Result<Value> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let data = pickle::parse(&bytes).map_err(|m| Error::invalid(path, m))?;
    if !matches!(data, Value::Dict(_)) {
        return Err(Error::invalid(path, not_a_dict));
    }
    Ok(data)
}

/// Reads a PhysTwin `final_data.pkl` (see the module docs).
pub fn read_capture(path: &Path) -> Result<Capture> {
    let data = read_dict(path, "expected a pickled dict of numpy arrays")?;
    let points = shaped(&data, "object_points", &[None, None, Some(3)], path)?;
    let (frames, n) = (points.shape[0], points.shape[1]);
    if frames < 2 || n == 0 {
        return Err(Error::invalid(
            path,
            format!(
                "'object_points' holds {frames} frames of {n} points; at least 2 frames of 1 point are needed"
            ),
        ));
    }
    let ctrl = shaped(
        &data,
        "controller_points",
        &[Some(frames), None, Some(3)],
        path,
    )?;
    let c = ctrl.shape[1];
    if c == 0 {
        return Err(Error::invalid(
            path,
            "'controller_points' holds no point: nothing drives the object",
        ));
    }
    let visibilities =
        shaped(&data, "object_visibilities", &[Some(frames), Some(n)], path)?.to_bool();
    let valid = shaped(
        &data,
        "object_motions_valid",
        &[Some(frames), Some(n)],
        path,
    )?
    .to_bool();
    let raw = turned_up(&points.to_f64());
    let controller_positions = turned_up(&ctrl.to_f64());
    if let Some(k) = first_non_finite(&controller_positions, |_| true) {
        return Err(Error::invalid(
            path,
            format!(
                "'controller_points' at frame {}, point {} is not a finite 32-bit number",
                k / c,
                k % c
            ),
        ));
    }
    let colors = match data.get("object_colors") {
        None => None,
        Some(_) => {
            let a = shaped(
                &data,
                "object_colors",
                &[Some(frames), Some(n), Some(3)],
                path,
            )?;
            Some(a.to_f64())
        }
    };
    // Seen: the tracker saw it, and (after frame 0) its motion into this frame was valid.
    let seen_raw: Vec<bool> = (0..frames * n)
        .map(|k| visibilities[k] && (k < n || valid[k - n]))
        .collect();
    // Where a point is not seen its stored value is replaced, so it may be anything (zeros in
    // PhysTwin's files, NaN in some trackers').
    if let Some(k) = first_non_finite(&raw, |k| seen_raw[k]) {
        return Err(Error::invalid(
            path,
            format!(
                "'object_points' at frame {}, point {} is seen but not a finite 32-bit number",
                k / n,
                k % n
            ),
        ));
    }
    let kept: Vec<usize> = (0..n)
        .filter(|i| (0..frames).any(|t| seen_raw[t * n + i]))
        .collect();
    let m = kept.len();
    if m == 0 {
        return Err(Error::invalid(
            path,
            "no object point is ever seen with a valid motion",
        ));
    }
    let mut positions = vec![Vec3::ZERO; frames * m];
    let mut seen = vec![false; frames * m];
    let mut first_colors = Vec::with_capacity(m);
    for (j, &i) in kept.iter().enumerate() {
        let first = (0..frames)
            .find(|t| seen_raw[t * n + i])
            .unwrap_or_default();
        let mut last = raw[first * n + i];
        for t in 0..frames {
            if seen_raw[t * n + i] {
                last = raw[t * n + i];
                seen[t * m + j] = true;
            }
            positions[t * m + j] = last;
        }
        if let Some(rgb) = &colors {
            let k = 3 * (first * n + i);
            first_colors.push([0, 1, 2].map(|a| (rgb[k + a] as f32).clamp(0.0, 1.0)));
        }
    }
    Ok(Capture {
        frames,
        points: m,
        controllers: c,
        positions,
        seen,
        controller_positions,
        colors: colors.map(|_| first_colors),
        never_seen: n - m,
    })
}

/// PhysTwin's `split.json`: the end (exclusive) of the training frames, and where it came
/// from; the first 70 % when the file is absent, as PhysTwin's `process_data.py` splits.
pub fn read_train_end(case: &Path, frames: usize) -> Result<(usize, String)> {
    let path = case.join("split.json");
    if !path.exists() {
        let end = (0.7 * frames as f64) as usize;
        return Ok((
            end,
            format!("no split.json: the first 70 % of frames, [0, {end})"),
        ));
    }
    let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| Error::invalid(&path, format!("not JSON: {e}")))?;
    let range = |key: &str| -> Option<(u64, u64)> {
        let a = json.get(key)?.as_array()?;
        Some((a.first()?.as_u64()?, a.get(1)?.as_u64()?))
    };
    let (Some(train), Some(test)) = (range("train"), range("test")) else {
        return Err(Error::invalid(
            &path,
            "expected \"train\": [0, a] and \"test\": [a, T] (frame ranges, end exclusive)",
        ));
    };
    let t = frames as u64;
    if train.0 != 0 || train.1 != test.0 || test.1 != t || train.1 == 0 || train.1 >= t {
        return Err(Error::invalid(
            &path,
            format!(
                "train {train:?} and test {test:?} must split the capture's {frames} frames as [0, a) and [a, {frames})"
            ),
        ));
    }
    Ok((
        train.1 as usize,
        format!(
            "split.json: train [0, {}), test [{}, {frames})",
            train.1, train.1
        ),
    ))
}

/// One episode of an import: where its frames came from.
#[derive(Clone, Debug, serde::Serialize)]
pub struct EpisodeSource {
    /// Episode file in the dataset.
    pub file: String,
    /// Its split.
    pub split: Split,
    /// The capture's frame of its first and last frame.
    pub source_frames: [usize; 2],
}

/// A summary of one import, also written as `import.json` beside the dataset.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PhysTwinReport {
    /// The `final_data.pkl` read.
    pub source: String,
    /// Object name written to `dataset.json` (the case directory's name).
    pub object: String,
    /// Frames of the capture.
    pub frames: usize,
    /// Object points kept (seen at least once).
    pub points: usize,
    /// Object points never seen with a valid motion, left out.
    pub never_seen: usize,
    /// Controller points (grippers).
    pub controllers: usize,
    /// Where the training frames end, and why.
    pub split: String,
    /// Fraction of (frame, point) entries of the episodes that are seen.
    pub seen_fraction: f64,
    /// The conversion's settings.
    pub every: usize,
    /// Kept frames per episode.
    pub episode_frames: usize,
    /// Kept frames between episode starts.
    pub stride_frames: usize,
    /// Every episode written.
    pub episodes: Vec<EpisodeSource>,
    /// How the frame was changed.
    pub coordinates: &'static str,
}

/// Where each window of `len` frames starts in `kept`, one every `stride`.
fn windows(kept: &[usize], len: usize, stride: usize) -> Vec<usize> {
    if kept.len() < len {
        return Vec::new();
    }
    (0..=kept.len() - len).step_by(stride).collect()
}

/// Converts a PhysTwin case (a directory holding `final_data.pkl`, or the pickle itself) into
/// a pgrd dataset at `out`.
pub fn import(source: &Path, out: &Path, opts: &PhysTwinOptions) -> Result<PhysTwinReport> {
    let (case, pkl): (PathBuf, PathBuf) = if source.is_dir() {
        (source.to_path_buf(), source.join("final_data.pkl"))
    } else {
        let case = source.parent().unwrap_or(Path::new(".")).to_path_buf();
        (case, source.to_path_buf())
    };
    if opts.every == 0 || opts.episode_frames < 3 || opts.stride_frames == 0 {
        return Err(Error::invalid(
            source,
            format!(
                "every ({}) and the stride ({}) must be at least 1 and an episode at least 3 frames ({})",
                opts.every, opts.stride_frames, opts.episode_frames
            ),
        ));
    }
    let cap = read_capture(&pkl)?;
    let (train_end, split) = read_train_end(&case, cap.frames)?;
    let object = case
        .canonicalize()
        .ok()
        .and_then(|p| p.file_name().and_then(|s| s.to_str()).map(str::to_string))
        .unwrap_or_else(|| "phystwin".into());
    let kept: Vec<usize> = (0..cap.frames).step_by(opts.every).collect();
    let (train_frames, test_frames): (Vec<usize>, Vec<usize>) =
        kept.iter().partition(|t| **t < train_end);
    let plan: Vec<(Split, &[usize], Vec<usize>)> = [
        (Split::Train, &train_frames[..]),
        (Split::Val, &test_frames[..]),
    ]
    .into_iter()
    .map(|(s, f)| (s, f, windows(f, opts.episode_frames, opts.stride_frames)))
    .collect();
    for (s, f, w) in &plan {
        if w.is_empty() {
            let part = if *s == Split::Train {
                "training"
            } else {
                "test"
            };
            return Err(Error::invalid(
                &pkl,
                format!(
                    "the {part} frames keep {} frames (one in every {}), fewer than one episode of {}: \
                     give fewer --episode-frames (or a smaller --every)",
                    f.len(),
                    opts.every,
                    opts.episode_frames
                ),
            ));
        }
    }
    let mut meta = DatasetMeta::new(
        &object,
        opts.source_fps / opts.every as f32,
        opts.manipulation,
    );
    meta.gripper_radius = opts.gripper_radius_m;
    if opts.manipulation == Manipulation::Attach {
        meta.controller_springs = opts.controller_springs;
    }
    let mut writer = DatasetWriter::create(out, meta)?;
    let (m, c, len) = (cap.points, cap.controllers, opts.episode_frames);
    let mut report = PhysTwinReport {
        source: pkl.display().to_string(),
        object,
        frames: cap.frames,
        points: m,
        never_seen: cap.never_seen,
        controllers: c,
        split,
        seen_fraction: 0.0,
        every: opts.every,
        episode_frames: len,
        stride_frames: opts.stride_frames,
        episodes: Vec::new(),
        coordinates: "(x, y, z) -> (x, -y, -z): PhysTwin's z points down (reverse_z)",
    };
    let (mut seen, mut total) = (0usize, 0usize);
    for (split, frames, starts) in plan {
        for s in starts {
            let ts = &frames[s..s + len];
            let positions = ts
                .iter()
                .flat_map(|t| cap.positions[t * m..(t + 1) * m].iter().copied())
                .collect();
            let grippers = ts
                .iter()
                .flat_map(|t| cap.controller_positions[t * c..(t + 1) * c].iter().copied())
                .collect();
            let visible: Vec<u8> = ts
                .iter()
                .flat_map(|t| cap.seen[t * m..(t + 1) * m].iter().map(|v| u8::from(*v)))
                .collect();
            seen += visible.iter().filter(|v| **v == 1).count();
            total += visible.len();
            let mut episode =
                Episode::new(len, m, c, positions, grippers)?.with_visible(visible)?;
            if let Some(colors) = &cap.colors {
                episode = episode.with_colors(colors.clone())?;
            }
            let index = writer.add_episode(&episode, split)?;
            report.episodes.push(EpisodeSource {
                file: format!("ep_{index:04}.safetensors"),
                split,
                source_frames: [ts[0], ts[len - 1]],
            });
        }
    }
    report.seen_fraction = seen as f64 / total.max(1) as f64;
    writer.finish()?;
    let json = serde_json::to_string_pretty(&report)
        .map_err(|e| Error::invalid(out, format!("cannot serialise import report: {e}")))?;
    crate::write_atomic(&out.join("import.json"), json.as_bytes())?;
    Ok(report)
}
