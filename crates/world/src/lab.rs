//! Direct access to the reference-world simulator, for experiments and tests: build an object,
//! set its state, grasp and release particles, step, and read energies.

use glam::Vec3;

use crate::build::{Blueprint, Resolution, blueprint};
use crate::record::{PUSH_RADIUS, STEP_S, grasp_mode};
use crate::sim::Sim;
use crate::{Effects, Error, ObjectKind};

/// One object in the reference world, in its rest configuration (see [`Lab::positions`]), with
/// gravity −9.81 m/s² along z, **no ground** until [`Lab::set_ground`], and no grippers.
///
/// ```
/// use world::{Effects, Lab, ObjectKind, Resolution};
/// use glam::Vec3;
/// let mut lab = Lab::new(ObjectKind::Flag, &Effects::none(), Resolution::Coarse, 0)?;
/// lab.set_gravity(Vec3::ZERO);
/// lab.set_velocities(Vec3::new(0.0, 1.0, 0.0));
/// let before = lab.kinetic_energy();
/// lab.step();
/// // Without drag, nothing removes energy from a free flag moving rigidly.
/// assert!((lab.kinetic_energy() - before).abs() < 1e-3 * before);
/// # Ok::<(), world::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct Lab {
    sim: Sim,
    bp: Blueprint,
    effects: Effects,
    grippers: Vec<Vec3>,
    targets: Vec<Vec3>,
}

impl Lab {
    /// Builds `object` with `effects` at `resolution`; `seed` fixes its material fields.
    pub fn new(
        object: ObjectKind,
        effects: &Effects,
        resolution: Resolution,
        seed: u64,
    ) -> Result<Lab, Error> {
        effects.validate()?;
        let bp = blueprint(object, resolution, seed);
        let push = object.is_push().then_some(PUSH_RADIUS);
        let mut sim = Sim::new(&bp, effects, bp.rest.clone(), push);
        sim.ground = None;
        Ok(Lab {
            sim,
            bp,
            effects: effects.clone(),
            grippers: Vec::new(),
            targets: Vec::new(),
        })
    }

    /// Fine particle positions, m.
    pub fn positions(&self) -> &[Vec3] {
        &self.sim.x
    }

    /// Fine particle velocities, m/s.
    pub fn velocities(&self) -> &[Vec3] {
        &self.sim.v
    }

    /// Fine particle masses, kg.
    pub fn masses(&self) -> &[f32] {
        &self.sim.mass
    }

    /// The particles the object's gripper holds in generated data.
    pub fn grasp_region(&self) -> &[u32] {
        &self.bp.held
    }

    /// XPBD substeps per 0.1 s step.
    pub fn substeps(&self) -> usize {
        self.bp.substeps
    }

    /// Sets every particle's velocity, m/s.
    pub fn set_velocities(&mut self, v: Vec3) {
        self.sim.v.fill(v);
    }

    /// Sets gravity, m/s².
    pub fn set_gravity(&mut self, g: Vec3) {
        self.sim.gravity = g;
    }

    /// Puts the ground plane at height `z` (m), or removes it.
    pub fn set_ground(&mut self, z: Option<f32>) {
        self.sim.ground = z;
    }

    /// Moves every particle by `d` (m); only valid before any grasp.
    pub fn translate(&mut self, d: Vec3) {
        for x in &mut self.sim.x {
            *x += d;
        }
    }

    /// Adds a gripper at `at` (m) holding `particles` (rigidly, or through the compliant link of
    /// grasp-slip when that effect is on); returns its index. Errors on an index out of range.
    pub fn grasp(&mut self, particles: &[u32], at: Vec3) -> Result<usize, Error> {
        if let Some(p) = particles.iter().find(|p| **p as usize >= self.sim.x.len()) {
            return Err(Error::Config(format!(
                "particle {p} out of range ({} particles)",
                self.sim.x.len()
            )));
        }
        let g = self.grippers.len();
        let mode = grasp_mode(&self.effects, particles.len());
        self.sim.attach(particles, g as u32, at, mode);
        self.grippers.push(at);
        self.targets.push(at);
        Ok(g)
    }

    /// Lets go of everything gripper `gripper` holds (it stays in the scene).
    pub fn release(&mut self, gripper: usize) {
        self.sim.release(gripper as u32);
    }

    /// Sets where gripper `gripper` will be at the end of the next [`Lab::step`] (m); it moves
    /// there in a straight line at constant speed.
    pub fn move_gripper(&mut self, gripper: usize, to: Vec3) -> Result<(), Error> {
        let n = self.targets.len();
        let t = self.targets.get_mut(gripper).ok_or_else(|| {
            Error::Config(format!("gripper {gripper} out of range ({n} grippers)"))
        })?;
        *t = to;
        Ok(())
    }

    /// Advances one 0.1 s model step.
    pub fn step(&mut self) {
        let s = self.bp.substeps;
        let h = STEP_S / s as f32;
        let mut g = self.grippers.clone();
        for k in 1..=s {
            let a = k as f32 / s as f32;
            for (gi, (from, to)) in g.iter_mut().zip(self.grippers.iter().zip(&self.targets)) {
                *gi = from.lerp(*to, a);
            }
            self.sim.substep(h, &g);
        }
        self.grippers.clone_from(&self.targets);
    }

    /// Total kinetic energy, J.
    pub fn kinetic_energy(&self) -> f32 {
        self.sim.kinetic_energy()
    }
}
