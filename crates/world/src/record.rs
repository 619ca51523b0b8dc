//! One continuous recording: place the object, settle it, drive the gripper, sample the tracked
//! particles at 10 fps, observe them.

use glam::Vec3;
use rand::Rng;

use crate::build::{Blueprint, place};
use crate::effects::Effects;
use crate::motion::{
    Motion, MotionStyle, PokePlanner, grasp_motion, planning_motion, probing_motion,
};
use crate::observation::Observation;
use crate::rng::{stream, tag};
use crate::sim::{GraspMode, Sim};
use crate::{Error, ObjectKind};

/// Seconds per stored frame (one model step).
pub(crate) const STEP_S: f32 = 0.1;
/// Unrecorded settling before every recording, s.
pub(crate) const SETTLE_S: f32 = 1.5;
/// Velocity damping rate while settling, 1/s.
const SETTLE_RATE: f32 = 8.0;
/// Radius of the pushing finger, m.
pub(crate) const PUSH_RADIUS: f32 = 0.02;

/// Everything a recording needs that is shared by all recordings of a dataset.
pub(crate) struct Scene<'a> {
    pub kind: ObjectKind,
    pub bp: &'a Blueprint,
    pub effects: &'a Effects,
    pub observation: &'a Observation,
    pub tracked: &'a [u32],
    /// Fine particles whose true positions are kept for ground-truth rendering.
    pub gaussian_particles: &'a [u32],
    pub seed: u64,
    pub motion: MotionStyle,
}

/// The sampled recording.
pub(crate) struct Recording {
    /// Observed tracked positions `[frames × n]`, m.
    pub observed: Vec<Vec3>,
    /// Visibility `[frames × n]`.
    pub visible: Vec<u8>,
    /// Recorded (commanded) gripper positions `[frames]`, m.
    pub grippers: Vec<Vec3>,
    /// True positions of the scene's `gaussian_particles` `[frames × m]`, m.
    pub fine: Vec<Vec3>,
}

/// The grasp mode implied by the effects for `n` held particles.
pub(crate) fn grasp_mode(effects: &Effects, n: usize) -> GraspMode {
    match &effects.grasp_slip {
        Some(g) if n > 0 => GraspMode::Compliant {
            compliance: n as f32 / g.stiffness_n_m,
            max_force: g.slip_force_n / n as f32,
        },
        _ => GraspMode::Kinematic,
    }
}

/// Simulates recording `index` for `frames` stored frames.
pub(crate) fn record(scene: &Scene<'_>, index: u64, frames: usize) -> Result<Recording, Error> {
    let bp = scene.bp;
    let mut place_rng = stream(scene.seed, &[tag::PLACEMENT, index]);
    let mut motion_rng = stream(scene.seed, &[tag::MOTION, index]);
    // Planning tasks start from the straight rope; half the planning-style recordings do too.
    let straight = scene.motion == MotionStyle::Planning && place_rng.random_bool(0.5);
    let (x, g0) = place(scene.kind, bp, straight, &mut place_rng);
    let push = scene.kind.is_push().then_some(PUSH_RADIUS);
    let mut sim = Sim::new(bp, scene.effects, x, push);
    let planner = push.map(|radius| PokePlanner {
        radius,
        spacing: bp.spacing,
    });
    let h = STEP_S / bp.substeps as f32;
    let lag = scene.effects.actuation_delay.map_or(0.0, |d| d.lag_s);
    let duration = frames as f32 * STEP_S + 1.0;

    // Settle (not recorded) with the gripper at its start; for grasped objects the grasp closes
    // first, so hanging objects settle into their hanging shape.
    let mut motion: Motion;
    let settle_gripper = match &planner {
        Some(p) => {
            let (m, start) = p.start(&sim.x, &mut motion_rng);
            motion = m;
            start
        }
        None => {
            sim.attach(&bp.held, 0, g0, grasp_mode(scene.effects, bp.held.len()));
            motion = Motion::default_at(g0);
            g0
        }
    };
    sim.settle_rate = SETTLE_RATE;
    let settle_substeps = (SETTLE_S / h).round() as usize;
    for _ in 0..settle_substeps {
        sim.substep(h, &[settle_gripper]);
    }
    sim.settle_rate = 0.0;
    if planner.is_none() {
        let c = crate::build::centroid_of(&sim.x);
        let centre = match scene.kind {
            ObjectKind::Rope => Vec3::new(c.x, c.y, 0.0),
            _ => Vec3::new(g0.x, g0.y, 0.0),
        };
        // How far the settled object reaches below the gripper, m.
        let hang = || (g0.z - sim.x.iter().map(|p| p.z).fold(f32::INFINITY, f32::min)).max(0.0);
        motion = match scene.motion {
            MotionStyle::Everyday => {
                grasp_motion(scene.kind, g0, centre, duration, &mut motion_rng)
            }
            MotionStyle::Probing => {
                probing_motion(scene.kind, g0, hang(), centre, duration, &mut motion_rng)
            }
            MotionStyle::Planning => {
                planning_motion(scene.kind, g0, hang(), duration, &mut motion_rng)
            }
        };
    }

    let n = scene.tracked.len();
    let mut truth = Vec::with_capacity(frames * n);
    let mut grippers = Vec::with_capacity(frames);
    let mut fine = Vec::with_capacity(frames * scene.gaussian_particles.len());
    for k in 0..frames {
        let t = k as f32 * STEP_S;
        if let Some(p) = &planner {
            p.extend(&mut motion, &sim.x, t + lag + 2.0, &mut motion_rng);
        }
        truth.extend(scene.tracked.iter().map(|&i| sim.x[i as usize]));
        fine.extend(scene.gaussian_particles.iter().map(|&i| sim.x[i as usize]));
        grippers.push(motion.at(t));
        if k + 1 == frames {
            break;
        }
        for s in 1..=bp.substeps {
            let ts = t + s as f32 * h;
            sim.substep(h, &[motion.at(ts - lag)]);
        }
        if !sim.is_finite() {
            return Err(Error::Diverged {
                object: scene.kind.name().to_string(),
                recording: index as usize,
                frame: k + 1,
            });
        }
    }
    let mut obs_rng = stream(scene.seed, &[tag::OBSERVATION, index]);
    let (observed, visible) = scene
        .observation
        .apply(&truth, n, &grippers, STEP_S, &mut obs_rng);
    Ok(Recording {
        observed,
        visible,
        grippers,
        fine,
    })
}
