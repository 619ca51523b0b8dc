//! What the planning examples share: a run's two learned models on a task's world rope, and the
//! state a planner meets part of the way to the task's target.

use std::path::Path;
use std::sync::Arc;

use glam::Vec3;
use plan::{ModelState, Pgrd, SpringMass, Task, TaskConfig, TaskKind};

pub type Error = Box<dyn std::error::Error>;

/// A run directory's models on one task: `backbone.json` (with the library effects a diagnosed
/// run carries, `diagnose --write-run`) and `residual.safetensors`.
pub struct Setup {
    pub kind: TaskKind,
    /// The task on the world rope at full resolution with 250 observed points, as in
    /// `docs/RESULTS.md`.
    pub task: Task,
    params: springs::SpringParams,
    effects: Vec<gap::BaseEffect>,
    /// Effects placed along the object use the task's start shape as their material frame.
    frame: gap::MaterialFrame,
    net: Arc<residual::ResidualNet>,
}

impl Setup {
    /// From the command line `<run-dir> <task> [fractions]`: the setup and the fractions of the
    /// way (comma-separated, `default` when not given).
    pub fn from_args(usage: &str, default: &str) -> Result<(Setup, Vec<f32>), Error> {
        let args: Vec<String> = std::env::args().collect();
        if args.len() < 3 {
            return Err(
                format!("usage: {usage} <run-dir> <task> [fractions, comma-separated]").into(),
            );
        }
        let fractions = args
            .get(3)
            .map_or(default, String::as_str)
            .split(',')
            .map(str::parse)
            .collect::<Result<_, _>>()?;
        Ok((
            Setup::new(Path::new(&args[1]), args[2].parse()?)?,
            fractions,
        ))
    }

    fn new(run: &Path, kind: TaskKind) -> Result<Setup, Error> {
        let backbone: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(run.join("backbone.json"))?)?;
        let params = serde_json::from_value(backbone["params"].clone())?;
        let effects = match backbone.get("effects") {
            Some(e) => serde_json::from_value(e.clone())?,
            None => Vec::new(),
        };
        let net = Arc::new(residual::ResidualNet::load(
            &run.join("residual.safetensors"),
        )?);
        let cfg = TaskConfig {
            tracked: 250,
            resolution: world::Resolution::Full,
            ..TaskConfig::new()
        };
        let task = Task::build(kind, &cfg)?;
        let frame = gap::MaterialFrame::of_shape(&task.start.observe())?;
        Ok(Setup {
            kind,
            task,
            params,
            effects,
            frame,
            net,
        })
    }

    fn backbone(&self) -> Result<springs::Backbone, Error> {
        let options = gap::backbone_options(&self.effects, &self.frame);
        Ok(self.task.backbone_with(self.params, options)?)
    }

    /// The backbone alone.
    pub fn spring_mass(&self) -> Result<SpringMass, Error> {
        Ok(SpringMass::new(self.backbone()?))
    }

    /// The backbone with the run's network.
    pub fn pgrd(&self) -> Result<Pgrd, Error> {
        Ok(Pgrd::new(self.backbone()?, self.net.clone()))
    }

    /// The state a planner meets part of the way: the world driven straight from the task's
    /// start towards the target's gripper position, at up to 3 cm per step, stopped at
    /// `fraction` of the way and held for three steps. Returns the world there, the models'
    /// state (the last four observations) and the gripper's position.
    pub fn part_way(&self, fraction: f32) -> Result<(world::Plant, ModelState, Vec3), Error> {
        let mut w = self.task.start.clone();
        let g0 = w.gripper();
        let at = g0 + (self.task.target_gripper - g0) * fraction;
        let n = ((at - g0).length() / 0.03).ceil().max(1.0) as usize;
        let mut frames = vec![w.observe()];
        for k in 1..=n {
            w.step(g0 + (at - g0) * (k as f32 / n as f32))?;
            frames.push(w.observe());
        }
        for _ in 0..3 {
            w.step(at)?;
            frames.push(w.observe());
        }
        let state = ModelState::from_frames(&frames[frames.len() - 4..], 0.1)?;
        Ok((w, state, at))
    }

    /// The candidates' mean step from `at`: straight on towards the target's gripper position,
    /// at most 2 cm per step, so that one horizon gets there or stops short.
    pub fn mean_step(&self, at: Vec3) -> Vec3 {
        let left = self.task.target_gripper - at;
        let h = self.kind.mppi().horizon as f32;
        left.normalize_or_zero() * (left.length() / h).min(0.02)
    }
}
