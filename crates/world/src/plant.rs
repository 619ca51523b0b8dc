//! The reference world as the system under control: one grasped object on the table, stepped
//! one 0.1 s command at a time, observed through a fixed set of tracked particles. A planner
//! treats it as "the real system": it sees only [`Plant::observe`] and moves the gripper.

use glam::{Quat, Vec3};

use crate::build::{Blueprint, Resolution, blueprint};
use crate::obstacles::BoxObstacle;
use crate::record::{STEP_S, grasp_mode};
use crate::rng::{stream, tag};
use crate::sim::Sim;
use crate::{Effects, Error, ObjectKind};

/// Velocity damping rate while settling, 1/s (as before a recording).
const SETTLE_RATE: f32 = 8.0;

/// How a [`Plant`] starts.
#[derive(Clone, Debug, PartialEq)]
pub struct PlantConfig {
    /// The object (a grasped one: every object but the teddy).
    pub object: ObjectKind,
    /// Effects that are on.
    pub effects: Effects,
    /// Fine model resolution.
    pub resolution: Resolution,
    /// Seed of the material fields and of the tracked-particle choice.
    pub seed: u64,
    /// Tracked particles reported by [`Plant::observe`].
    pub tracked: usize,
    /// Rotation of the rest pose about the vertical axis through the grasp point, rad.
    pub yaw_rad: f32,
    /// Where the grasp point goes on the table (x, y), m; z is ignored (the object lies on the
    /// table).
    pub grasp_at_m: Vec3,
    /// Box obstacles in the scene.
    pub obstacles: Vec<BoxObstacle>,
}

impl PlantConfig {
    /// `object` with its default effects at coarse resolution, seed 0, 150 tracked particles,
    /// unrotated with its grasp point at the origin, no obstacles.
    pub fn new(object: ObjectKind) -> Self {
        PlantConfig {
            object,
            effects: Effects::defaults(object),
            resolution: Resolution::Coarse,
            seed: 0,
            tracked: 150,
            yaw_rad: 0.0,
            grasp_at_m: Vec3::ZERO,
            obstacles: Vec::new(),
        }
    }
}

/// One object of the reference world under closed-loop control.
///
/// The object starts in its rest shape lying on the table (ground at z = 0), rotated and moved
/// as its [`PlantConfig`] says, held by one gripper at its grasp region. Each [`Plant::step`]
/// moves the gripper in a straight line to a commanded point over 0.1 s.
///
/// ```
/// use glam::Vec3;
/// use world::{ObjectKind, Plant, PlantConfig};
/// let mut cfg = PlantConfig::new(ObjectKind::Rope);
/// cfg.tracked = 40;
/// let mut plant = Plant::new(&cfg)?;
/// let start = plant.gripper();
/// for k in 1..=3 {
///     plant.step(start + Vec3::new(0.0, 0.0, 0.05 * k as f32))?;
/// }
/// let lifted = plant.observe();
/// assert_eq!(lifted.len(), 40);
/// assert!(lifted.iter().any(|p| p.z > 0.1)); // the held end came up with the gripper
/// # Ok::<(), world::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct Plant {
    sim: Sim,
    object: ObjectKind,
    tracked: Vec<u32>,
    held: Vec<i32>,
    gripper: Vec3,
    steps: usize,
    substeps: usize,
}

impl Plant {
    /// Builds the object, lays it on the table and closes the gripper on its grasp region.
    /// Errors for the pushed teddy, for more tracked particles than surface particles, and for
    /// obstacles that overlap the object at the start.
    pub fn new(cfg: &PlantConfig) -> Result<Plant, Error> {
        if cfg.object.is_push() {
            return Err(Error::Config(format!(
                "a plant needs a grasped object; {} is pushed",
                cfg.object
            )));
        }
        if !(cfg.yaw_rad.is_finite() && cfg.grasp_at_m.is_finite()) {
            return Err(Error::Config("plant pose must be finite".into()));
        }
        cfg.effects.validate()?;
        let bp = blueprint(cfg.object, cfg.resolution, cfg.seed);
        let tracked = select_tracked(&bp, cfg.tracked, cfg.seed)?;
        let lowest = bp.rest.iter().map(|p| p.z).fold(f32::INFINITY, f32::min);
        let rot = Quat::from_rotation_z(cfg.yaw_rad);
        let g = bp.grasp_point;
        let lift = bp.contact_radius - lowest;
        let place = |p: Vec3| {
            let q = rot * (p - Vec3::new(g.x, g.y, 0.0));
            Vec3::new(q.x + cfg.grasp_at_m.x, q.y + cfg.grasp_at_m.y, q.z + lift)
        };
        let x: Vec<Vec3> = bp.rest.iter().map(|p| place(*p)).collect();
        let gripper = place(g);
        let mut sim = Sim::new(&bp, &cfg.effects, x, None);
        if let Some((i, _)) = sim
            .x
            .iter()
            .enumerate()
            .find(|(_, p)| cfg.obstacles.iter().any(|b| b.contains(**p)))
        {
            return Err(Error::Config(format!(
                "particle {i} starts inside an obstacle at {}",
                sim.x[i]
            )));
        }
        sim.obstacles.clone_from(&cfg.obstacles);
        sim.attach(
            &bp.held,
            0,
            gripper,
            grasp_mode(&cfg.effects, bp.held.len()),
        );
        let held_set: std::collections::HashSet<u32> = bp.held.iter().copied().collect();
        let held = tracked
            .iter()
            .map(|i| if held_set.contains(i) { 0 } else { -1 })
            .collect();
        Ok(Plant {
            sim,
            object: cfg.object,
            tracked,
            held,
            gripper,
            steps: 0,
            substeps: bp.substeps,
        })
    }

    /// Lets the object come to rest for `seconds` with the gripper still, under extra velocity
    /// damping (not counted as steps).
    pub fn settle(&mut self, seconds: f32) -> Result<(), Error> {
        let h = STEP_S / self.substeps as f32;
        self.sim.settle_rate = SETTLE_RATE;
        let g = [self.gripper];
        for _ in 0..(seconds.max(0.0) / h).round() as usize {
            self.sim.substep(h, &g);
        }
        self.sim.settle_rate = 0.0;
        self.check()
    }

    /// Advances one 0.1 s step, the gripper moving in a straight line from where it is to `to`
    /// (m). Errors on a non-finite target or if the simulation diverges.
    pub fn step(&mut self, to: Vec3) -> Result<(), Error> {
        if !to.is_finite() {
            return Err(Error::Config(format!("gripper target {to} is not finite")));
        }
        let s = self.substeps;
        let h = STEP_S / s as f32;
        for k in 1..=s {
            let g = [self.gripper.lerp(to, k as f32 / s as f32)];
            self.sim.substep(h, &g);
        }
        self.gripper = to;
        self.steps += 1;
        self.check()
    }

    fn check(&self) -> Result<(), Error> {
        if self.sim.is_finite() {
            Ok(())
        } else {
            Err(Error::Diverged {
                object: self.object.name().to_string(),
                recording: 0,
                frame: self.steps,
            })
        }
    }

    /// Positions of the tracked particles (exact, no observation noise), m.
    pub fn observe(&self) -> Vec<Vec3> {
        self.tracked
            .iter()
            .map(|&i| self.sim.x[i as usize])
            .collect()
    }

    /// Per tracked particle: 0 when the gripper holds it, −1 otherwise.
    pub fn held(&self) -> &[i32] {
        &self.held
    }

    /// Fine-model indices of the tracked particles.
    pub fn tracked_indices(&self) -> &[u32] {
        &self.tracked
    }

    /// All fine particles' positions, m.
    pub fn positions(&self) -> &[Vec3] {
        &self.sim.x
    }

    /// Where the gripper is, m.
    pub fn gripper(&self) -> Vec3 {
        self.gripper
    }

    /// The box obstacles.
    pub fn obstacles(&self) -> &[BoxObstacle] {
        &self.sim.obstacles
    }

    /// Steps taken so far.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// The object.
    pub fn object(&self) -> ObjectKind {
        self.object
    }
}

/// `count` surface particles spread evenly by farthest-point sampling in the rest pose, starting
/// from a random held particle and taking `count / 25` (at least one) of the held ones first, so
/// that a model built on them is held too.
fn select_tracked(bp: &Blueprint, count: usize, seed: u64) -> Result<Vec<u32>, Error> {
    let surface: Vec<u32> = (0..bp.len() as u32)
        .filter(|&i| bp.surface[i as usize])
        .collect();
    if count == 0 || count > surface.len() {
        return Err(Error::Config(format!(
            "{count} tracked particles requested; this object has {} surface particles",
            surface.len()
        )));
    }
    let held: std::collections::HashSet<u32> = bp.held.iter().copied().collect();
    let is_held: Vec<bool> = surface.iter().map(|i| held.contains(i)).collect();
    let n_held = is_held.iter().filter(|h| **h).count();
    // A sub-stream of the tracked-choice stream of its own (7), not the datasets' one.
    let mut rng = stream(seed, &[tag::TRACKED, 7]);
    let mut dist = vec![f32::INFINITY; surface.len()];
    let mut chosen = vec![false; surface.len()];
    let mut picked = Vec::with_capacity(count);
    let take = |k: usize, dist: &mut [f32], chosen: &mut [bool], picked: &mut Vec<u32>| {
        chosen[k] = true;
        picked.push(surface[k]);
        let p = bp.rest[surface[k] as usize];
        for (d, &i) in dist.iter_mut().zip(&surface) {
            *d = d.min(p.distance_squared(bp.rest[i as usize]));
        }
    };
    let pool: Vec<usize> = if n_held > 0 {
        (0..surface.len()).filter(|&k| is_held[k]).collect()
    } else {
        (0..surface.len()).collect()
    };
    let first = pool[rand::Rng::random_range(&mut rng, 0..pool.len())];
    take(first, &mut dist, &mut chosen, &mut picked);
    let want_held = (count / 25).max(1).min(n_held);
    // Farthest unchosen candidate (ties to the lower index, for determinism).
    let farthest = |dist: &[f32], chosen: &[bool], only_held: bool| {
        (0..dist.len())
            .filter(|&k| !chosen[k] && (!only_held || is_held[k]))
            .max_by(|&a, &b| dist[a].total_cmp(&dist[b]).then(b.cmp(&a)))
    };
    while picked.len() < want_held {
        let Some(k) = farthest(&dist, &chosen, true) else {
            break;
        };
        take(k, &mut dist, &mut chosen, &mut picked);
    }
    while picked.len() < count {
        let Some(k) = farthest(&dist, &chosen, false) else {
            break;
        };
        take(k, &mut dist, &mut chosen, &mut picked);
    }
    picked.sort_unstable();
    Ok(picked)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tracked_choice_is_seeded_and_includes_held_particles() {
        let mut cfg = PlantConfig::new(ObjectKind::Rope);
        cfg.tracked = 60;
        let a = Plant::new(&cfg).unwrap();
        let b = Plant::new(&cfg).unwrap();
        assert_eq!(a.tracked_indices(), b.tracked_indices());
        assert_eq!(a.tracked_indices().len(), 60);
        let held = a.held().iter().filter(|h| **h == 0).count();
        assert!((2..=5).contains(&held), "{held} held tracked particles");
        cfg.tracked = 100_000;
        assert!(Plant::new(&cfg).is_err());
    }

    #[test]
    fn rope_lies_on_the_table_where_asked() {
        let mut cfg = PlantConfig::new(ObjectKind::Rope);
        cfg.yaw_rad = std::f32::consts::FRAC_PI_2;
        cfg.grasp_at_m = Vec3::new(0.1, -0.2, 5.0);
        let plant = Plant::new(&cfg).unwrap();
        let g = plant.gripper();
        assert!((g.x - 0.1).abs() < 1e-5 && (g.y + 0.2).abs() < 1e-5 && g.z < 0.02);
        let x = plant.observe();
        let lowest = x.iter().map(|p| p.z).fold(f32::INFINITY, f32::min);
        assert!(lowest > 0.0 && lowest < 0.01);
        // Rotated by 90°: the rope now runs along +y from the grasp point.
        let far = x.iter().map(|p| p.y).fold(f32::NEG_INFINITY, f32::max);
        assert!((far - (-0.2 + 0.88)).abs() < 0.03, "far end at y = {far}");
    }

    #[test]
    fn rope_dragged_across_a_block_stays_out_of_it() {
        // A 4 cm tall block across the rope's path; the gripper passes 8 cm above the table,
        // so the trailing rope is dragged over the block.
        let block =
            BoxObstacle::new(Vec3::new(-0.3, 0.2, -0.05), Vec3::new(0.3, 0.25, 0.04)).unwrap();
        let mut cfg = PlantConfig::new(ObjectKind::Rope);
        cfg.tracked = 60;
        cfg.grasp_at_m = Vec3::new(0.0, 0.0, 0.0);
        cfg.yaw_rad = -std::f32::consts::FRAC_PI_2;
        cfg.obstacles = vec![block];
        let mut plant = Plant::new(&cfg).unwrap();
        let g0 = plant.gripper();
        let mut over = false;
        for k in 1..=20 {
            plant
                .step(g0 + Vec3::new(0.0, 0.03 * k as f32, 0.07))
                .unwrap();
            // The held end rides 7 cm above the table, above the block: no exceptions needed.
            let inside = plant
                .positions()
                .iter()
                .filter(|p| block.contains(**p))
                .count();
            assert_eq!(
                inside, 0,
                "step {k}: {inside} free particles inside the block"
            );
            over |= plant.observe().iter().any(|p| p.y > 0.25 && p.z < 0.03);
        }
        assert!(over, "the rope should have been dragged past the block");
        // An obstacle overlapping the start pose is refused.
        cfg.obstacles = vec![BoxObstacle::new(Vec3::splat(-0.1), Vec3::splat(0.1)).unwrap()];
        assert!(Plant::new(&cfg).is_err());
    }
}
