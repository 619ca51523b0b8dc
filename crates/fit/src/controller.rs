//! The rule joining an `attach` dataset's controller points to the object, searched with the
//! backbone's parameters as PhysTwin's first stage does, from one or more starts.

use std::path::Path;

use cmaes::{Parameter, Parameters};
use rayon::prelude::*;
use scene::Scene;
use serde::{Deserialize, Serialize};
use springs::{BackboneOptions, ParamBounds, SpringParams};

use crate::{BackboneFamily, Family, FitConfig, FitError, FitOutcome, Generation, fit, scene_loss};

/// PhysTwin's range of the controller points' reach, m (its stage 1 searches 0.01–0.08 m).
pub const CONTROLLER_RADIUS_RANGE_M: [f32; 2] = [0.01, 0.08];

/// PhysTwin's range of the controller points' spring count (its stage 1 searches 10–80).
pub const CONTROLLER_SPRINGS_RANGE: [u32; 2] = [10, 80];

/// The paper's five parameters and the rule that joins an `attach` dataset's controller points
/// to the object (their reach and spring count, [`springs::AnchorSprings`]), searched together
/// as PhysTwin's first stage does. The rule applies to each scene's own anchors
/// ([`Scene::anchors`]); a scene without anchors is rolled out as [`BackboneFamily`] would.
/// The search starts at the paper's box centre for the five and at `start` for the rule.
///
/// ```
/// # use fit::{ControllerFamily, Family};
/// let start = dataset::ControllerSprings::PHYSTWIN;
/// let family = ControllerFamily::new(springs::REFERENCE_BOUNDS, start).unwrap();
/// assert_eq!(family.parameters().dim(), 7);
/// assert_eq!(ControllerFamily::rule(&family.x0()), start);
/// ```
#[derive(Debug, Clone)]
pub struct ControllerFamily {
    backbone: BackboneFamily,
    parameters: Parameters,
    start: dataset::ControllerSprings,
}

impl ControllerFamily {
    /// The family over `bounds` and PhysTwin's ranges of the rule, starting at `start` (held
    /// inside those ranges).
    pub fn new(
        bounds: ParamBounds,
        start: dataset::ControllerSprings,
    ) -> Result<Self, cmaes::Error> {
        let backbone = BackboneFamily::new(bounds)?;
        let mut all = backbone.parameters().params().to_vec();
        let [r0, r1] = CONTROLLER_RADIUS_RANGE_M;
        let [n0, n1] = CONTROLLER_SPRINGS_RANGE;
        all.push(Parameter::linear(
            "controller_radius_m",
            f64::from(r0),
            f64::from(r1),
        ));
        all.push(
            Parameter::linear("controller_max_springs", f64::from(n0), f64::from(n1)).integer(),
        );
        let start = dataset::ControllerSprings {
            radius_m: start.radius_m.clamp(r0, r1),
            max_springs: start.max_springs.clamp(n0, n1),
        };
        Ok(ControllerFamily {
            backbone,
            parameters: Parameters::new(all)?,
            start,
        })
    }

    /// The controller rule in a real parameter vector of this family (entries 5 and 6).
    pub fn rule(real: &[f64]) -> dataset::ControllerSprings {
        dataset::ControllerSprings {
            radius_m: real[5] as f32,
            max_springs: real[6].round() as u32,
        }
    }
}

impl Family for ControllerFamily {
    fn name(&self) -> String {
        "spring-mass+controller".to_string()
    }

    fn parameters(&self) -> &Parameters {
        &self.parameters
    }

    fn x0(&self) -> Vec<f64> {
        let mut x = self.backbone.x0();
        x.push(f64::from(self.start.radius_m));
        x.push(f64::from(self.start.max_springs));
        x
    }

    fn build(&self, real: &[f64]) -> (SpringParams, BackboneOptions) {
        (BackboneFamily::params(real), BackboneOptions::default())
    }

    fn build_for(&self, real: &[f64], scene: &Scene) -> (SpringParams, BackboneOptions) {
        let rule = Self::rule(real);
        let options = BackboneOptions {
            anchors: scene.anchors().map(|a| springs::AnchorSprings {
                particles: a.particles.clone(),
                radius_m: rule.radius_m,
                max_springs: rule.max_springs,
            }),
            ..BackboneOptions::default()
        };
        (BackboneFamily::params(real), options)
    }
}

/// Most starts [`fit_controller`] runs: the declared radius, then halfway from it to the
/// range's lower end, then halfway to its upper end.
pub const MAX_CONTROLLER_STARTS: usize = 3;

/// One start of [`fit_controller`]: where it began and what it found.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControllerStart {
    /// The radius the search started from, m.
    pub start_radius_m: f32,
    /// The rule it found.
    pub found: dataset::ControllerSprings,
    /// Its best candidate's mean loss over every training scene, m² (the choice between
    /// starts).
    pub train_loss_m2: f64,
}

/// What [`fit_controller`] found.
#[derive(Clone, Debug)]
pub struct ControllerFit {
    /// The kept start's outcome.
    pub outcome: FitOutcome,
    /// Index into `starts` of the kept one (the lowest loss; ties to the earlier).
    pub chosen: usize,
    /// Every start, in the order run.
    pub starts: Vec<ControllerStart>,
}

/// The radii [`fit_controller`] starts from: `declared`, then halfway from it to the lower end
/// of [`CONTROLLER_RADIUS_RANGE_M`], then halfway to the upper end; the first `starts` of
/// these (1 to [`MAX_CONTROLLER_STARTS`]).
pub fn controller_start_radii(declared: f32, starts: usize) -> Vec<f32> {
    let [r0, r1] = CONTROLLER_RADIUS_RANGE_M;
    let d = declared.clamp(r0, r1);
    [d, 0.5 * (r0 + d), 0.5 * (d + r1)]
        .into_iter()
        .take(starts.clamp(1, MAX_CONTROLLER_STARTS))
        .collect()
}

/// Fits [`ControllerFamily`] from each of [`controller_start_radii`] (the declared spring
/// count throughout) and keeps the start whose best candidate has the lowest mean loss over
/// every scene. The rule moves the loss in steps (a particle joined or not), so one search
/// can stall at the rule it starts from; more starts find a rule away from it more often
/// (docs/pipelines.md, "The controller rule"). Start `k` checkpoints to `checkpoint` (the
/// first) or to `<stem>.start<k>.json` beside it, so an interrupted run resumes each start.
pub fn fit_controller(
    scenes: &[Scene],
    bounds: ParamBounds,
    declared: dataset::ControllerSprings,
    starts: usize,
    config: &FitConfig,
    checkpoint: Option<&Path>,
    on_generation: &mut dyn FnMut(usize, &Generation),
) -> Result<ControllerFit, FitError> {
    let mut runs = Vec::new();
    for (k, radius) in controller_start_radii(declared.radius_m, starts)
        .into_iter()
        .enumerate()
    {
        let family = ControllerFamily::new(
            bounds,
            dataset::ControllerSprings {
                radius_m: radius,
                ..declared
            },
        )?;
        let path = checkpoint.map(|p| match k {
            0 => p.to_path_buf(),
            _ => p.with_extension(format!("start{k}.json")),
        });
        let outcome = fit(scenes, &family, config, path.as_deref(), &mut |g| {
            on_generation(k, g)
        })?;
        let loss = scenes
            .par_iter()
            .map(|s| scene_loss(&family, &outcome.best, s))
            .collect::<Vec<_>>()
            .iter()
            .sum::<f64>()
            / scenes.len().max(1) as f64;
        runs.push((radius, outcome, loss));
    }
    let chosen = runs
        .iter()
        .enumerate()
        .fold(0, |b, (i, r)| if r.2 < runs[b].2 { i } else { b });
    let starts = runs
        .iter()
        .map(|(radius, outcome, loss)| ControllerStart {
            start_radius_m: *radius,
            found: ControllerFamily::rule(&outcome.best),
            train_loss_m2: *loss,
        })
        .collect();
    Ok(ControllerFit {
        outcome: runs.swap_remove(chosen).1,
        chosen,
        starts,
    })
}
