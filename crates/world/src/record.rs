//! One continuous recording: place the object, settle it, drive the gripper, sample the tracked
//! particles at 10 fps, observe them.

use glam::Vec3;
use rand::Rng;

use crate::build::{Blueprint, place};
use crate::effects::Effects;
use crate::motion::{
    Motion, MotionStyle, PokePlanner, grasp_motion, planning_branch, planning_motion,
    probing_motion,
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

/// Where branches leave the trunk: the first waypoint after this fraction of the recording.
const BRANCH_AFTER: f32 = 0.4;

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
    /// The last frame this branch shares with the trunk, whose gripper path it leaves after
    /// that frame (the trunk itself: `None`).
    pub branch_frame: Option<usize>,
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
///
/// With `branches = b > 1` (planning motions of a grasped object, checked by
/// [`GenConfig::validate`](crate::GenConfig::validate)) it returns `b` recordings of the same
/// object from the same start: the first follows the recording's own gripper path (the trunk),
/// every other one shares the trunk's path and state up to the trunk's first waypoint after
/// 40 % of the recording (an earlier one when that leaves fewer than two frames) and then
/// takes fresh random moves. They share the tracker's random draws, so their observations
/// agree exactly before the branch point.
pub(crate) fn record(
    scene: &Scene<'_>,
    index: u64,
    frames: usize,
    branches: usize,
) -> Result<Vec<Recording>, Error> {
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
    // How far the settled object reaches below the gripper, m.
    let hang = (g0.z - sim.x.iter().map(|p| p.z).fold(f32::INFINITY, f32::min)).max(0.0);
    if planner.is_none() {
        let c = crate::build::centroid_of(&sim.x);
        let centre = match scene.kind {
            ObjectKind::Rope => Vec3::new(c.x, c.y, 0.0),
            _ => Vec3::new(g0.x, g0.y, 0.0),
        };
        motion = match scene.motion {
            MotionStyle::Everyday => {
                grasp_motion(scene.kind, g0, centre, duration, &mut motion_rng)
            }
            MotionStyle::Probing => {
                probing_motion(scene.kind, g0, hang, centre, duration, &mut motion_rng)
            }
            MotionStyle::Planning => {
                planning_motion(scene.kind, g0, hang, duration, &mut motion_rng)
            }
        };
    }

    // The branches' paths, and the frame up to which they all agree with the trunk's.
    let mut paths = vec![(motion, None)];
    let mut shared = frames;
    if branches > 1 {
        let after = BRANCH_AFTER * frames as f32 * STEP_S;
        // At least two stored steps after the branch point.
        let before = frames.saturating_sub(2) as f32 * STEP_S;
        for b in 1..branches {
            let mut rng = stream(scene.seed, &[tag::MOTION, index, b as u64]);
            let (m, t) = planning_branch(
                &paths[0].0,
                scene.kind,
                g0,
                hang,
                (after, before),
                duration,
                &mut rng,
            )
            .ok_or_else(|| {
                Error::Config(format!(
                    "recording {index} is too short to branch ({frames} frames)"
                ))
            })?;
            // Frames up to floor(t / step) are simulated with times <= t, where the paths agree.
            shared = ((t / STEP_S).floor() as usize).min(frames);
            paths.push((m, Some(shared)));
        }
    }

    let n = scene.tracked.len();
    let m_fine = scene.gaussian_particles.len();
    let mut trunk = Track::default();
    let mut out = Vec::with_capacity(paths.len());
    let run = |sim: &mut Sim,
               motion: &mut Motion,
               range: std::ops::Range<usize>,
               track: &mut Track,
               rng: &mut rand_chacha::ChaCha8Rng|
     -> Result<(), Error> {
        for k in range {
            let t = k as f32 * STEP_S;
            if let Some(p) = &planner {
                p.extend(motion, &sim.x, t + lag + 2.0, rng);
            }
            track
                .truth
                .extend(scene.tracked.iter().map(|&i| sim.x[i as usize]));
            track
                .fine
                .extend(scene.gaussian_particles.iter().map(|&i| sim.x[i as usize]));
            track.grippers.push(motion.at(t));
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
        Ok(())
    };
    let mut trunk_motion = paths[0].0.clone();
    run(
        &mut sim,
        &mut trunk_motion,
        0..shared,
        &mut trunk,
        &mut motion_rng,
    )?;
    let last = paths.len() - 1;
    for (b, (mut path, branch_frame)) in paths.into_iter().enumerate() {
        // The last branch takes over the trunk's state and frames; the others work on copies.
        let mut own;
        let (state, mut track) = if b == last {
            (&mut sim, std::mem::take(&mut trunk))
        } else {
            own = sim.clone();
            (&mut own, trunk.clone())
        };
        run(
            state,
            &mut path,
            shared..frames,
            &mut track,
            &mut motion_rng.clone(),
        )?;
        debug_assert_eq!(track.grippers.len(), frames);
        debug_assert_eq!(track.fine.len(), frames * m_fine);
        let mut obs_rng = stream(scene.seed, &[tag::OBSERVATION, index]);
        let (observed, visible) =
            scene
                .observation
                .apply(&track.truth, n, &track.grippers, STEP_S, &mut obs_rng);
        out.push(Recording {
            observed,
            visible,
            grippers: track.grippers,
            fine: track.fine,
            branch_frame,
        });
    }
    Ok(out)
}

/// What a recording keeps of the simulation, frame by frame.
#[derive(Clone, Default)]
struct Track {
    truth: Vec<Vec3>,
    grippers: Vec<Vec3>,
    fine: Vec<Vec3>,
}
