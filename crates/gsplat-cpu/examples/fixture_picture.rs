//! The picture in `docs/rendering.md`: a fixture episode's tracked particles and a spring-mass
//! prediction of them, both carried by Gaussians (particles as bones) and rendered from one
//! camera.
//!
//! ```text
//! cargo run --release -p pgrd-gsplat-cpu --example fixture_picture -- [fixture dir] [episode] [out dir] [--gif]
//! ```
//! (defaults: `fixtures/rope`, episode 3 (a validation episode), `docs/images`). Writes
//! `<object>-render.png` (top row: ground truth, the tracked particles; bottom row: the
//! spring-mass backbone with the reference rope parameters, not fitted; columns: steps 0, 12,
//! 24 and 37 of the paper's window), with `--gif` also `<object>-render.gif` (every step,
//! prediction | truth, 10 frames per second), and prints J (mask IoU at alpha 0.1) per shown
//! step.

use std::path::PathBuf;

use glam::Vec3;
use gsplat::{
    Camera, GaussianRig, Image, MASK_THRESHOLD, RigOptions, grid, render, side_by_side, write_gif,
    write_png,
};

type Error = Box<dyn std::error::Error>;

const BACKGROUND: [f32; 3] = [0.93, 0.94, 0.96];
const PANEL: (usize, usize) = (320, 240);

fn main() -> Result<(), Error> {
    let gif_too = std::env::args().any(|a| a == "--gif");
    let mut args = std::env::args().skip(1).filter(|a| a != "--gif");
    let dir = PathBuf::from(args.next().unwrap_or_else(|| "fixtures/rope".into()));
    let index: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(3);
    let out = PathBuf::from(args.next().unwrap_or_else(|| "docs/images".into()));
    std::fs::create_dir_all(&out)?;

    let data = dataset::Dataset::open(&dir)?;
    let episode = data.load_episode(index)?;
    let window = scene::Protocol::Paper.window(episode.frames())?;
    let scene = scene::Scene::new(&data.meta, &episode, window, &scene::SceneConfig::default())?;
    let predicted = scene.rollout(
        &springs::SpringParams::reference_rope(),
        &scene.sim_config(),
        Default::default(),
    )?;
    let start = episode.frame(window.start).to_vec();
    let colors = episode
        .colors()
        .map_or_else(|| vec![[0.6; 3]; start.len()], <[_]>::to_vec);

    // One camera for every frame, framing all ground-truth and predicted positions (80 % of
    // the panel) from above at an angle.
    let all: Vec<Vec3> = (window.start..=window.start + window.steps)
        .flat_map(|t| episode.frame(t).to_vec())
        .chain(predicted.iter().flatten().copied())
        .collect();
    let fov = 40f32.to_radians();
    // Of 12 azimuths at 35° elevation, the one where the first frame's projection has the
    // largest bounding box (a rope seen across rather than end-on).
    let view = |az: f32| {
        let (el, az) = (35f32.to_radians(), az.to_radians());
        -Vec3::new(az.cos() * el.cos(), az.sin() * el.cos(), el.sin())
    };
    let spread = |az: f32| -> f32 {
        let Ok(cam) = Camera::framing(&all, view(az), Vec3::Z, fov, PANEL.0, PANEL.1, 0.8) else {
            return 0.0;
        };
        let uv: Vec<_> = start
            .iter()
            .filter_map(|p| cam.project(*p))
            .map(|(uv, _)| uv)
            .collect();
        let (a, b) = uv.iter().fold(
            (glam::Vec2::INFINITY, glam::Vec2::NEG_INFINITY),
            |(a, b), p| (a.min(*p), b.max(*p)),
        );
        ((b - a).x * (b - a).y).max(0.0)
    };
    let azimuth = (0..12)
        .map(|k| 15.0 + 30.0 * k as f32)
        .max_by(|a, b| spread(*a).total_cmp(&spread(*b)))
        .unwrap_or(15.0);
    let camera = Camera::framing(&all, view(azimuth), Vec3::Z, fov, PANEL.0, PANEL.1, 0.8)?;

    let options = RigOptions::default();
    let mut truth_rig = GaussianRig::from_particles(&start, &colors, &options)?;
    let mut pred_rig = truth_rig.clone();
    let first = render(truth_rig.gaussians(), &camera, BACKGROUND)?;
    let mut truth: Vec<Image> = vec![first.clone()];
    let mut pred: Vec<Image> = vec![first];
    for (step, predicted) in predicted.iter().enumerate() {
        truth.push(render(
            truth_rig.deform(episode.frame(window.start + step + 1))?,
            &camera,
            BACKGROUND,
        )?);
        pred.push(render(pred_rig.deform(predicted)?, &camera, BACKGROUND)?);
    }

    let shown = [0, 12, 24, window.steps];
    let row = |images: &[Image]| {
        shown
            .iter()
            .map(|&s| images[s].to_rgb8())
            .collect::<Vec<_>>()
    };
    let object = &data.meta.object;
    let png = out.join(format!("{object}-render.png"));
    write_png(&png, &grid(&[row(&truth), row(&pred)], 4)?)?;
    println!("wrote {}", png.display());
    if gif_too {
        let frames: Vec<_> = pred
            .iter()
            .zip(&truth)
            .map(|(p, t)| side_by_side(p, t, 4))
            .collect();
        let gif = out.join(format!("{object}-render.gif"));
        write_gif(&gif, &frames, 100)?;
        println!("wrote {}", gif.display());
    }

    println!(
        "{}: episode {index}, steps {:?} of the paper window (start frame {})",
        dir.display(),
        shown,
        window.start
    );
    for &s in &shown {
        println!("  step {s:2}: J = {:.3}", iou(&pred[s], &truth[s]));
    }
    let mean = (1..=window.steps)
        .map(|s| iou(&pred[s], &truth[s]))
        .sum::<f64>()
        / window.steps as f64;
    println!("  mean J over steps 1..={}: {mean:.3}", window.steps);
    Ok(())
}

/// Mask IoU at the evaluation threshold (the metrics crate has the reference implementation;
/// this is only the caption's number).
fn iou(a: &Image, b: &Image) -> f64 {
    let (ma, mb) = (a.mask(MASK_THRESHOLD), b.mask(MASK_THRESHOLD));
    let inter = ma.iter().zip(&mb).filter(|(x, y)| **x && **y).count();
    let union = ma.iter().zip(&mb).filter(|(x, y)| **x || **y).count();
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}
