//! From a tracked episode to a simulated scene, and back to scores.
//!
//! The physics crate knows particles and actions; the dataset crate knows files. This crate
//! joins them the way every pipeline (fit, eval, train, diagnose, plan) needs:
//!
//! - [`Protocol`] says where a rollout starts and how many steps it predicts
//!   (the paper's 37-step window, or DEFORM's 498 steps).
//! - [`Scene::new`] builds the simulated object at the start frame: the tracked particles first,
//!   then hidden particles between the markers of a `chain`, or interior particles filling a
//!   `volume` ([`SceneConfig`]); which particles are held; the initial velocities by finite
//!   difference, with points occluded at the start carried from their last sighting
//!   ([`Scene::start_frame`]) and points not seen at all yet placed among their material
//!   neighbours ([`SceneConfig::with_neighbours_of`]); the gripper actions over the window; the
//!   ground truth it will be scored on.
//! - [`Scene::backbone`] builds the spring-mass model from the start frame, with the
//!   reference's springs or, with [`SceneConfig::with_material_pairs_of`], springs between
//!   material neighbours only (not between parts that merely touch at the start frame).
//! - [`Scene::rollout`] runs the backbone with given parameters and returns the tracked
//!   particles' predicted positions per step; [`score_steps`] and [`position_mse`] score them
//!   against the truth, counting only particles the tracker saw.
//!
//! ```no_run
//! # fn main() -> Result<(), scene::SceneError> {
//! use scene::{Protocol, Scene, SceneConfig};
//! let data = dataset::Dataset::open("fixtures/rope")?;
//! let episode = data.load_episode(0)?;
//! let window = Protocol::Paper.window(episode.frames())?;
//! let scene = Scene::new(&data.meta, &episode, window, &SceneConfig::default())?;
//! let pred = scene.rollout(&springs::SpringParams::reference_rope(), &scene.sim_config(), Default::default())?;
//! let errors = scene::score_steps(&scene, &pred, false)?;
//! // `None` at a step whose frame the tracker saw nothing in.
//! if let Some(Some(last)) = errors.last() {
//!     println!("MDE after the last step: {:.2} cm", 100.0 * last.mde);
//! }
//! # Ok(()) }
//! ```

mod build;
mod error;
mod score;
mod window;

pub use build::{MATERIAL_PAIR_FACTOR, Scene, SceneConfig};
pub use error::SceneError;
pub use score::{
    StepErrors, deform_l1, mean_over_steps, position_mse, score_steps, sum_over_steps,
};
pub use window::{Protocol, Window};
