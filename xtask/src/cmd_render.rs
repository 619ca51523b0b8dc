//! `cargo xtask render`: action-conditioned video prediction. The run's model is rolled out on
//! one episode; Gaussians carried by the predicted particles and the reference world's own
//! ground-truth Gaussians (`truth_ep_NNNN.safetensors`) are rendered from the same camera and
//! compared with J, F and LPIPS (`docs/rendering.md`). A recording without them (DEFORM, a
//! PhysTwin import, your own data) is compared with its recorded tracked points instead, both
//! carrying one Gaussian per tracked point ([`GroundTruth::Recorded`]).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use dataset::{Dataset, Episode, Split};
use glam::{Quat, Vec2, Vec3};
use gsplat::{
    Camera, GaussianRig, Gaussians, Image, MASK_THRESHOLD, RigOptions, grid, render, side_by_side,
    write_gif, write_png,
};
use metrics::RolloutAggregate;
use metrics::image::{boundary_f_measure, mask_iou};
use metrics::lpips::Lpips;
use scene::{Protocol, Scene, Window};
use serde::Serialize;
use world::TruthGaussians;

use crate::common::{NetworkPath, ProtocolArg, predict_tracked, read_backbone, read_residual};
use crate::report::write_json;

/// Background colour of every render (a neutral grey-blue that white paper and black fur both
/// stand out from; masks come from opacity, so it only matters for LPIPS and pictures).
pub const BACKGROUND: [f32; 3] = [0.78, 0.80, 0.84];
/// Camera elevation above the horizontal, degrees.
pub const ELEVATION_DEG: f32 = 35.0;
/// Vertical field of view, degrees.
pub const FOV_Y_DEG: f32 = 40.0;
/// Fraction of the half-image the ground truth's extent over the window fills.
pub const FILL: f32 = 0.8;

/// Which Gaussians the prediction carries.
#[derive(clap::ValueEnum, Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Appearance {
    /// The ground truth's own Gaussians at the start frame, bound to the predicted particles: a
    /// perfect first-frame 3DGS reconstruction (the paper fits 3DGS at the first frame), so
    /// every difference comes from the predicted motion.
    #[default]
    Fine,
    /// One Gaussian per tracked particle with the dataset's colour
    /// (`GaussianRig::from_particles`): no appearance from the ground truth at all.
    Tracked,
}

/// Image size and appearance of a video evaluation (default 320 × 240 px, [`Appearance::Fine`];
/// LPIPS, which dominates the time, grows with the pixel count).
#[derive(Clone, Copy, Debug, Serialize)]
pub struct VideoOptions {
    /// Image width, px.
    pub width: usize,
    /// Image height, px.
    pub height: usize,
    /// Gaussians of the prediction.
    pub appearance: Appearance,
}

impl Default for VideoOptions {
    fn default() -> Self {
        VideoOptions {
            width: 320,
            height: 240,
            appearance: Appearance::Fine,
        }
    }
}

/// Arguments of `render`.
#[derive(clap::Args)]
pub struct RenderArgs {
    /// Dataset directory: a reference-world dataset with `truth_ep_NNNN.safetensors`, or a
    /// recording, compared with its own tracked points.
    #[arg(long)]
    pub data: PathBuf,
    /// Run directory holding backbone.json (and residual.safetensors for PGRD).
    #[arg(long)]
    pub run: PathBuf,
    /// Episode (dataset index) [default: the first validation episode].
    #[arg(long)]
    pub episode: Option<usize>,
    /// Output directory for PNGs, the GIF and video.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Image width, px.
    #[arg(long, default_value_t = 320)]
    pub width: usize,
    /// Image height, px.
    #[arg(long, default_value_t = 240)]
    pub height: usize,
    /// Gaussians the prediction carries.
    #[arg(long, value_enum, default_value_t = Appearance::Fine)]
    pub appearance: Appearance,
    /// Evaluation protocol (which frames are predicted).
    #[arg(long, value_enum, default_value_t = ProtocolArg::Paper)]
    pub protocol: ProtocolArg,
    /// Skip LPIPS (J and F only).
    #[arg(long)]
    pub no_lpips: bool,
}

/// Rendered frames of one episode's window: index 0 is the start frame, `k` the frame after
/// step `k`.
pub struct Video {
    /// The camera of every frame.
    pub camera: Camera,
    /// Its azimuth, degrees (0 = looking along −x, counter-clockwise seen from above).
    pub azimuth_deg: f32,
    /// Ground-truth frames.
    pub truth: Vec<Image>,
    /// Predicted frames.
    pub pred: Vec<Image>,
}

/// J, F and LPIPS of one predicted frame against the ground truth.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct StepScores {
    /// Model step (1 = the first predicted frame).
    pub step: usize,
    /// Episode frame.
    pub frame: usize,
    /// Mask IoU (alpha > 0.1), in [0, 1].
    pub j: f64,
    /// DAVIS boundary F-measure, in [0, 1].
    pub f: f64,
    /// LPIPS (AlexNet, v0.1); absent when skipped.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f64>,
}

/// What a prediction is rendered against.
pub enum GroundTruth {
    /// The reference world's own Gaussians (`truth_ep_NNNN.safetensors`, one per fine
    /// particle), written by `cargo xtask gen`.
    World(TruthGaussians),
    /// The episode's recorded tracked points, each carrying one Gaussian with the dataset's
    /// colour (the [`Appearance::Tracked`] construction, moved to every recorded frame): for
    /// recordings, which have no ground-truth Gaussians. The prediction carries the same
    /// Gaussians, so the two start from the same image and every difference is motion. Points
    /// the tracker lost are drawn where the dataset stores them.
    Recorded {
        /// Every frame's tracked positions, m.
        frames: Vec<Vec<Vec3>>,
        /// Per tracked point (grey without the dataset's colours).
        colors: Vec<[f32; 3]>,
    },
}

impl GroundTruth {
    /// Episode `index`'s ground truth: the world's Gaussians when the dataset has them, else
    /// the recorded tracked points.
    pub fn load(data: &Dataset, index: usize, episode: &Episode) -> anyhow::Result<Self> {
        let path = TruthGaussians::path(&data.root, index);
        if !path.exists() {
            return Ok(Self::Recorded {
                frames: (0..episode.frames())
                    .map(|t| episode.frame(t).to_vec())
                    .collect(),
                colors: tracked_colors(episode),
            });
        }
        let truth = TruthGaussians::read(&path)?;
        anyhow::ensure!(
            truth.frames() == episode.frames(),
            "{}: {} frames, but episode {index} has {}",
            path.display(),
            truth.frames(),
            episode.frames()
        );
        Ok(Self::World(truth))
    }

    /// Frames held.
    pub fn frames(&self) -> usize {
        match self {
            Self::World(t) => t.frames(),
            Self::Recorded { frames, .. } => frames.len(),
        }
    }

    /// Positions of the Gaussians' centres at frame `t`, m.
    fn positions(&self, t: usize) -> Vec<Vec3> {
        match self {
            Self::World(truth) => truth.frame(t),
            Self::Recorded { frames, .. } => frames[t].clone(),
        }
    }

    /// Gaussians rendered as the ground truth.
    pub fn gaussian_count(&self) -> usize {
        match self {
            Self::World(t) => t.particles(),
            Self::Recorded { colors, .. } => colors.len(),
        }
    }

    /// What `video.json` and `eval --visual` name it.
    pub fn label(&self) -> &'static str {
        match self {
            Self::World(_) => "the reference world's ground-truth Gaussians",
            Self::Recorded { .. } => "the recorded tracked points, one Gaussian each",
        }
    }

    /// The appearance a prediction can be compared with: the world's own Gaussians allow
    /// either; recorded points only the tracked construction.
    pub fn appearance(&self, asked: Appearance) -> Appearance {
        match self {
            Self::World(_) => asked,
            Self::Recorded { .. } => Appearance::Tracked,
        }
    }

    /// Renders frames `window.start ..= window.start + window.steps`.
    fn render_window(&self, window: Window, camera: &Camera) -> anyhow::Result<Vec<Image>> {
        let frames = window.start..=window.start + window.steps;
        match self {
            Self::World(truth) => frames
                .map(|t| Ok(render(&truth_at(truth, t)?, camera, BACKGROUND)?))
                .collect(),
            Self::Recorded {
                frames: recorded,
                colors,
            } => {
                let mut rig = GaussianRig::from_particles(
                    &recorded[window.start],
                    colors,
                    &RigOptions::default(),
                )?;
                let mut out = vec![render(rig.gaussians(), camera, BACKGROUND)?];
                let later = recorded.iter().enumerate().skip(window.start + 1);
                for (t, frame) in later.take(window.steps) {
                    let g = rig
                        .deform(frame)
                        .with_context(|| format!("moving the recorded Gaussians to frame {t}"))?;
                    out.push(render(g, camera, BACKGROUND)?);
                }
                Ok(out)
            }
        }
    }
}

/// The dataset's colour of each tracked point, grey without one.
fn tracked_colors(episode: &Episode) -> Vec<[f32; 3]> {
    episode
        .colors()
        .map_or_else(|| vec![[0.6; 3]; episode.particles()], <[_]>::to_vec)
}

/// The ground truth's Gaussians at frame `t`: isotropic, one per fine particle.
fn truth_at(truth: &TruthGaussians, t: usize) -> anyhow::Result<Gaussians> {
    let n = truth.particles();
    Ok(Gaussians::new(
        truth.frame(t),
        vec![Quat::IDENTITY; n],
        truth.sigmas_m().iter().map(|s| Vec3::splat(*s)).collect(),
        truth.opacities().to_vec(),
        truth.colors().to_vec(),
    )?)
}

/// The camera of an episode, from the ground truth only (so every model is seen from the same
/// place): [`ELEVATION_DEG`] above the horizontal, at the azimuth (of 12, every 30° from 15°)
/// where the start frame's projection has the largest bounding box (a rope across the view
/// rather than end-on, a sheet face-on), looking at the centre of the bounding box of every
/// ground-truth position in the window, backed off until they fill [`FILL`] of the image;
/// vertical field of view [`FOV_Y_DEG`]. Returns the camera and its azimuth (degrees).
pub fn object_camera(
    truth: &GroundTruth,
    window: Window,
    width: usize,
    height: usize,
) -> anyhow::Result<(Camera, f32)> {
    let all: Vec<Vec3> = (window.start..=window.start + window.steps)
        .flat_map(|t| truth.positions(t))
        .collect();
    let start = truth.positions(window.start);
    let fov = FOV_Y_DEG.to_radians();
    let view = |az_deg: f32| {
        let (el, az) = (ELEVATION_DEG.to_radians(), az_deg.to_radians());
        -Vec3::new(az.cos() * el.cos(), az.sin() * el.cos(), el.sin())
    };
    let spread = |az: f32| -> f32 {
        let Ok(cam) = Camera::framing(&all, view(az), Vec3::Z, fov, width, height, FILL) else {
            return 0.0;
        };
        let (lo, hi) = start
            .iter()
            .filter_map(|p| cam.project(*p))
            .fold((Vec2::INFINITY, Vec2::NEG_INFINITY), |(a, b), (uv, _)| {
                (a.min(uv), b.max(uv))
            });
        ((hi - lo).x * (hi - lo).y).max(0.0)
    };
    // Ties keep the first azimuth.
    let mut azimuth = 15.0;
    let mut best = spread(azimuth);
    for k in 1..12 {
        let az = 15.0 + 30.0 * k as f32;
        let s = spread(az);
        if s > best {
            (azimuth, best) = (az, s);
        }
    }
    let camera = Camera::framing(&all, view(azimuth), Vec3::Z, fov, width, height, FILL)?;
    Ok((camera, azimuth))
}

/// Renders the ground truth and the prediction over `window`: `predicted` holds the tracked
/// particles' positions after each step (`window.steps` entries of `episode.particles()`).
pub fn render_video(
    truth: &GroundTruth,
    episode: &Episode,
    window: Window,
    predicted: &[Vec<Vec3>],
    opts: &VideoOptions,
) -> anyhow::Result<Video> {
    anyhow::ensure!(
        predicted.len() == window.steps,
        "{} predicted steps for a window of {}",
        predicted.len(),
        window.steps
    );
    anyhow::ensure!(
        window.start + window.steps < truth.frames(),
        "window {window:?} beyond the ground truth's {} frames",
        truth.frames()
    );
    let (camera, azimuth_deg) = object_camera(truth, window, opts.width, opts.height)?;
    let start = episode.frame(window.start);
    let options = RigOptions::default();
    let mut rig = match (truth, truth.appearance(opts.appearance)) {
        (GroundTruth::World(world), Appearance::Fine) => {
            GaussianRig::new(truth_at(world, window.start)?, start, &options)?
        }
        _ => GaussianRig::from_particles(start, &tracked_colors(episode), &options)?,
    };
    let mut pred = vec![render(rig.gaussians(), &camera, BACKGROUND)?];
    let truth_frames = truth.render_window(window, &camera)?;
    for (k, p) in predicted.iter().enumerate() {
        let g = rig
            .deform(p)
            .with_context(|| format!("moving the Gaussians at step {}", k + 1))?;
        pred.push(render(g, &camera, BACKGROUND)?);
    }
    Ok(Video {
        camera,
        azimuth_deg,
        truth: truth_frames,
        pred,
    })
}

/// J, F and (with `lpips`) LPIPS of every predicted frame (steps 1 ..= steps; the start frame
/// is given, not predicted).
pub fn score_video(
    video: &Video,
    window: Window,
    lpips: Option<&Lpips>,
) -> anyhow::Result<Vec<StepScores>> {
    (1..video.pred.len())
        .map(|step| {
            let (p, t) = (&video.pred[step], &video.truth[step]);
            let (mp, mt) = (p.mask(MASK_THRESHOLD), t.mask(MASK_THRESHOLD));
            let l = match lpips {
                Some(net) => Some(net.distance(&p.rgb, &t.rgb, p.width, p.height)?),
                None => None,
            };
            Ok(StepScores {
                step,
                frame: window.start + step,
                j: mask_iou(&mp, &mt)?,
                f: boundary_f_measure(&mp, &mt, p.width, p.height)?,
                lpips: l,
            })
        })
        .collect()
}

/// The masks compared (as in the paper's figure): both black, ground truth only (missed) red,
/// prediction only (false alarm) cyan, neither white.
pub fn mask_error(pred: &Image, truth: &Image) -> Image {
    let mut out = Image::blank(pred.width, pred.height);
    let (mp, mt) = (pred.mask(MASK_THRESHOLD), truth.mask(MASK_THRESHOLD));
    for (k, (p, t)) in mp.iter().zip(&mt).enumerate() {
        let c = match (p, t) {
            (true, true) => [0.0, 0.0, 0.0],
            (false, true) => [0.9, 0.1, 0.1],
            (true, false) => [0.1, 0.8, 0.9],
            (false, false) => [1.0, 1.0, 1.0],
        };
        out.rgb[3 * k..3 * k + 3].copy_from_slice(&c);
    }
    out
}

/// Summary of one visual metric over episodes.
#[derive(Serialize)]
pub struct VisualSummary {
    /// Mean over steps of the per-step mean over episodes.
    pub mean: f64,
    /// Mean over steps of the per-step standard deviation over episodes (the tables' ±).
    pub std: f64,
    /// What exactly was measured.
    pub convention: &'static str,
}

/// Video evaluation of several episodes: `predictions` holds (dataset index, scene, predicted
/// tracked positions after each step). Returns, as JSON for `eval --visual`, the summaries
/// `j`, `f`, `lpips` (fractions, not scaled), their per-step means over episodes
/// (`per_step`), the options and the camera rule.
pub fn visual_metrics(
    data: &Dataset,
    predictions: &[(usize, &Scene, Vec<Vec<Vec3>>)],
    opts: &VideoOptions,
) -> anyhow::Result<serde_json::Value> {
    let lpips = Lpips::new()?;
    let mut curves: [Vec<Vec<f64>>; 3] = Default::default();
    let mut truths = std::collections::BTreeSet::new();
    let mut used = *opts;
    for (i, scene, pred) in predictions {
        let episode = data.load_episode(*i)?;
        let truth = GroundTruth::load(data, *i, &episode)?;
        truths.insert(truth.label());
        used.appearance = truth.appearance(opts.appearance);
        let video = render_video(&truth, &episode, scene.window, pred, opts)
            .with_context(|| format!("rendering episode {i}"))?;
        let scores = score_video(&video, scene.window, Some(&lpips))?;
        curves[0].push(scores.iter().map(|s| s.j).collect());
        curves[1].push(scores.iter().map(|s| s.f).collect());
        curves[2].push(scores.iter().map(|s| s.lpips.unwrap_or(f64::NAN)).collect());
    }
    let conventions = [
        "J: IoU of the alpha > 0.1 masks",
        "F: DAVIS boundary F-measure of the masks, radius ceil(0.008 x diagonal) px",
        "LPIPS v0.1 AlexNet, RGB in [0, 1] on a uniform background",
    ];
    let mut summary = serde_json::json!({
        "options": used,
        "truth": truths.into_iter().collect::<Vec<_>>().join("; "),
        "camera": format!(
            "{ELEVATION_DEG} deg elevation, best of 12 azimuths, {FOV_Y_DEG} deg vertical field \
             of view, ground truth of the window filling {FILL} of the image"
        ),
    });
    let mut per_step = serde_json::json!({});
    for ((name, c), convention) in ["j", "f", "lpips"].iter().zip(&curves).zip(conventions) {
        let agg = RolloutAggregate::from_per_episode_curves(c)?;
        summary[*name] = serde_json::to_value(VisualSummary {
            mean: agg.mean,
            std: agg.std,
            convention,
        })?;
        per_step[*name] = serde_json::to_value(&agg.per_step_mean)?;
    }
    summary["per_step"] = per_step;
    Ok(summary)
}

/// What `render` writes as `video.json`.
#[derive(Serialize)]
struct RenderReport {
    model: String,
    dataset: String,
    object: String,
    episode: usize,
    split: String,
    protocol: String,
    window_start_frame: usize,
    steps: usize,
    options: VideoOptions,
    camera: serde_json::Value,
    /// What the prediction was compared with ([`GroundTruth::label`]).
    truth: &'static str,
    truth_gaussians: usize,
    mean: serde_json::Value,
    per_step: Vec<StepScores>,
    wall_s: f64,
}

/// Runs `render`.
pub fn run(args: &RenderArgs) -> anyhow::Result<()> {
    let t0 = Instant::now();
    let data = Dataset::open(&args.data)?;
    let index = match args.episode {
        Some(k) => k,
        None => *data
            .split_indices(Split::Val)
            .first()
            .with_context(|| format!("{} has no validation episode", args.data.display()))?,
    };
    let split = data
        .meta
        .episodes
        .get(index)
        .with_context(|| {
            format!(
                "--episode {index}: {} has {} episodes",
                args.data.display(),
                data.meta.episodes.len()
            )
        })?
        .split;
    let episode = data.load_episode(index)?;
    let truth = GroundTruth::load(&data, index, &episode)?;
    if matches!(truth, GroundTruth::Recorded { .. }) {
        println!(
            "note: {} has no ground-truth Gaussians (a recording, not `cargo xtask gen`'s world): \
             the prediction is compared with {}, as `--appearance tracked`",
            args.data.display(),
            truth.label()
        );
    }
    let protocol: Protocol = args.protocol.into();
    let window = protocol.window(episode.frames())?;
    let backbone = read_backbone(&args.run)?;
    backbone.note_other_object(&data);
    let scene = Scene::new(
        &data.meta,
        &episode,
        window,
        &backbone.setting().scene_config(&data)?,
    )
    .with_context(|| format!("episode {index}"))?;
    let net = read_residual(&args.run)?;
    let history = match &net {
        Some(_) => Some(residual::History::from_episode(
            &scene,
            &episode,
            data.meta.fps,
        )?),
        None => None,
    };
    let model = if net.is_some() {
        "pgrd".to_string()
    } else {
        backbone.label()
    };
    let options = backbone.options_for(&data, protocol)?;
    let predicted = predict_tracked(
        &scene,
        &backbone.params,
        &options,
        net.as_ref(),
        history.as_ref(),
        NetworkPath::ForwardOnly,
    )
    .with_context(|| format!("{model} rollout of episode {index}"))?;
    let opts = VideoOptions {
        width: args.width,
        height: args.height,
        appearance: truth.appearance(args.appearance),
    };
    let video = render_video(&truth, &episode, window, &predicted, &opts)?;
    let lpips = if args.no_lpips {
        None
    } else {
        Some(Lpips::new()?)
    };
    let scores = score_video(&video, window, lpips.as_ref())?;

    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    for (k, (p, t)) in video.pred.iter().zip(&video.truth).enumerate() {
        write_png(args.out.join(format!("pred_{k:02}.png")), &p.to_rgb8())?;
        write_png(args.out.join(format!("truth_{k:02}.png")), &t.to_rgb8())?;
    }
    let frames: Vec<_> = video
        .pred
        .iter()
        .zip(&video.truth)
        .map(|(p, t)| side_by_side(p, t, 4))
        .collect();
    // One GIF frame per model step, shown for the step's duration (real time).
    let frame_ms = (1000.0 * data.meta.step_dt()).round() as u32;
    write_gif(args.out.join("compare.gif"), &frames, frame_ms)?;
    let last = window.steps;
    let shown = [0, last / 3, 2 * last / 3, last];
    let row = |images: &[Image]| shown.iter().map(|&s| images[s].to_rgb8()).collect();
    let errors = shown
        .iter()
        .map(|&s| mask_error(&video.pred[s], &video.truth[s]).to_rgb8())
        .collect();
    write_png(
        args.out.join("strip.png"),
        &grid(&[row(&video.truth), row(&video.pred), errors], 4)?,
    )?;

    let mean_of = |f: &dyn Fn(&StepScores) -> Option<f64>| -> Option<f64> {
        let v: Option<Vec<f64>> = scores.iter().map(f).collect();
        v.filter(|v| !v.is_empty())
            .map(|v| v.iter().sum::<f64>() / v.len() as f64)
    };
    let mean = serde_json::json!({
        "j": mean_of(&|s| Some(s.j)),
        "f": mean_of(&|s| Some(s.f)),
        "lpips": mean_of(&|s| s.lpips),
    });
    let cam = &video.camera;
    let report = RenderReport {
        model: model.clone(),
        dataset: args.data.display().to_string(),
        object: data.meta.object.clone(),
        episode: index,
        split: split.to_string(),
        protocol: protocol.name().into(),
        window_start_frame: window.start,
        steps: window.steps,
        options: opts,
        camera: serde_json::json!({
            "eye_m": cam.eye().to_array(),
            "azimuth_deg": video.azimuth_deg,
            "elevation_deg": ELEVATION_DEG,
            "fov_y_deg": FOV_Y_DEG,
            "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
            "width": cam.width, "height": cam.height,
            "world_to_camera_rotation": cam.rotation.to_cols_array(),
            "world_to_camera_translation_m": cam.translation.to_array(),
        }),
        truth: truth.label(),
        truth_gaussians: truth.gaussian_count(),
        mean,
        per_step: scores,
        wall_s: t0.elapsed().as_secs_f64(),
    };
    write_json(&args.out.join("video.json"), &report)?;
    let m = &report.mean;
    println!(
        "{model} on {} episode {index} ({split}), {} steps, {}x{} px: J {:.3}, F {:.3}{}  ({:.1} s) -> {}",
        report.object,
        report.steps,
        opts.width,
        opts.height,
        m["j"].as_f64().unwrap_or(f64::NAN),
        m["f"].as_f64().unwrap_or(f64::NAN),
        m["lpips"]
            .as_f64()
            .map(|l| format!(", LPIPS {l:.4}"))
            .unwrap_or_default(),
        report.wall_s,
        args.out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A "prediction" that follows the recording exactly: its frames after the window's start.
    fn recorded_steps(episode: &Episode, window: Window) -> Vec<Vec<Vec3>> {
        (1..=window.steps)
            .map(|k| episode.frame(window.start + k).to_vec())
            .collect()
    }

    /// A fixture episode rendered end to end: the prediction's first frame is the ground
    /// truth's, following the (noisy) tracked positions keeps the masks close, and a
    /// prediction frozen at the start does worse on a moving object.
    #[test]
    fn fixture_frames_compare_as_expected() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/flag");
        let data = Dataset::open(&root).unwrap();
        let index = data.split_indices(Split::Val)[0];
        let episode = data.load_episode(index).unwrap();
        let truth = GroundTruth::load(&data, index, &episode).unwrap();
        assert!(matches!(truth, GroundTruth::World(_)));
        // Five steps of the paper window keep the test quick.
        let window = Window { start: 2, steps: 5 };
        let opts = VideoOptions {
            width: 96,
            height: 72,
            appearance: Appearance::Fine,
        };
        let following = recorded_steps(&episode, window);
        let frozen = vec![episode.frame(window.start).to_vec(); window.steps];
        let video = render_video(&truth, &episode, window, &following, &opts).unwrap();
        assert_eq!((video.pred.len(), video.truth.len()), (6, 6));
        assert_eq!(video.pred[0].rgb, video.truth[0].rgb);
        assert_eq!(video.pred[0].alpha, video.truth[0].alpha);
        // Every ground-truth position of the window is inside the image.
        for t in window.start..=window.start + window.steps {
            for p in truth.positions(t) {
                let (uv, _) = video.camera.project(p).unwrap();
                assert!(uv.x > 0.0 && uv.y > 0.0 && uv.x < 96.0 && uv.y < 72.0);
            }
        }
        let lpips = Lpips::new().unwrap();
        let good = score_video(&video, window, Some(&lpips)).unwrap();
        let still = render_video(&truth, &episode, window, &frozen, &opts).unwrap();
        let bad = score_video(&still, window, Some(&lpips)).unwrap();
        let mean = |s: &[StepScores], f: fn(&StepScores) -> f64| {
            s.iter().map(f).sum::<f64>() / s.len() as f64
        };
        assert!(mean(&good, |s| s.j) > 0.8, "{good:?}");
        assert!(
            mean(&good, |s| s.j) > mean(&bad, |s| s.j) + 0.05,
            "{good:?} {bad:?}"
        );
        assert!(mean(&good, |s| s.lpips.unwrap()) < mean(&bad, |s| s.lpips.unwrap()));
        assert_eq!(good.last().unwrap().frame, 7);

        // The tracked-particle appearance renders too, with the same camera.
        let tracked = VideoOptions {
            appearance: Appearance::Tracked,
            ..opts
        };
        let t = render_video(&truth, &episode, window, &following, &tracked).unwrap();
        assert_eq!(t.camera, video.camera);
        assert_ne!(t.pred[0].rgb, video.pred[0].rgb);

        // Wrong inputs are errors.
        assert!(render_video(&truth, &episode, window, &following[..4], &opts).is_err());
        let long = Window {
            start: 2,
            steps: 40,
        };
        assert!(render_video(&truth, &episode, long, &vec![vec![]; 40], &opts).is_err());
    }

    /// A recording without ground-truth Gaussians (the numpy writer's chain) is compared with
    /// its recorded tracked points: a prediction that follows them renders the very same
    /// images, whatever appearance was asked for, and one frozen at the start does worse.
    #[test]
    fn a_recording_is_compared_with_its_tracked_points() {
        let root =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/numpy_writer/chain");
        let data = Dataset::open(&root).unwrap();
        let index = data.split_indices(Split::Val)[0];
        let episode = data.load_episode(index).unwrap();
        let truth = GroundTruth::load(&data, index, &episode).unwrap();
        assert!(matches!(truth, GroundTruth::Recorded { .. }));
        assert_eq!(truth.frames(), episode.frames());
        assert_eq!(truth.gaussian_count(), episode.particles());
        assert_eq!(truth.appearance(Appearance::Fine), Appearance::Tracked);
        let window = Window {
            start: 2,
            steps: 20,
        };
        let opts = VideoOptions {
            width: 96,
            height: 72,
            appearance: Appearance::Fine,
        };
        let following = recorded_steps(&episode, window);
        let video = render_video(&truth, &episode, window, &following, &opts).unwrap();
        for (p, t) in video.pred.iter().zip(&video.truth) {
            assert_eq!(p.rgb, t.rgb);
            assert_eq!(p.alpha, t.alpha);
        }
        let frozen = vec![episode.frame(window.start).to_vec(); window.steps];
        let still = render_video(&truth, &episode, window, &frozen, &opts).unwrap();
        let scores = score_video(&still, window, None).unwrap();
        let worst = scores.iter().map(|s| s.j).fold(1.0, f64::min);
        assert!(worst < 0.9, "{scores:?}");
    }
}
