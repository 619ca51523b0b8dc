use std::num::NonZeroUsize;
use std::sync::Arc;

use dataset::{Dataset, DatasetMeta, Episode, MaterialNeighbours, MaterialPairs, Split, Structure};
use glam::Vec3;
use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use springs::{Actions, Backbone, BackboneOptions, SimConfig, SpringParams, State, Substep};

use crate::{SceneError, Window};

/// Default [`SceneConfig::fill_spacing_factor`], chosen on the teddy and sloth fixtures
/// (docs/pipelines.md).
const FILL_FACTOR: f32 = 1.5;

/// With material springs, a pair of tracked points whose mean distance over the training
/// recordings exceeds this multiple of the spring radius gets no spring: material neighbours
/// within the radius at the start frame stay about that close (a strain of 100 % would be
/// needed to reach the bound), parts that only touch there are usually tens of radii apart.
pub const MATERIAL_PAIR_FACTOR: f32 = 2.0;

/// How to turn tracked points into a simulated object.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneConfig {
    /// Hidden particles inserted between consecutive markers of a `chain` dataset. DEFORM's
    /// markers are ~10 cm apart; 4 hidden particles give ~2 cm spacing, close to the rope
    /// fixtures' tracked spacing, so one threshold range suits both.
    pub chain_hidden_per_gap: usize,
    /// Fill `volume` datasets with interior particles (the paper's internal points).
    pub fill_volume: bool,
    /// Interior grid spacing as a multiple of the tracked surface's median spacing. The
    /// interior carries the shape and the mass; it need not be as fine as the tracked surface,
    /// and each halving of it multiplies the interior particle count by 8.
    pub fill_spacing_factor: f32,
    /// Substep selection used by [`Scene::sim_config`].
    pub substep: Substep,
    /// Start tracked points that are occluded at the start frame where their surroundings have
    /// carried them since they were last seen ([`dataset::carried_frame`]), not at the stale
    /// position a tracker holds for a lost point. Applies to every frame up to the start that a
    /// model reads ([`Scene::start_frame`]): the start state and the residual network's history.
    /// On by default since 2026-11-28 (docs/pipelines.md, "Occluded points at the start").
    pub carry_occluded: bool,
    /// Where to start tracked points not seen at any frame up to the start (neither visible nor
    /// carried): at the centroid of their material neighbours
    /// ([`dataset::MaterialNeighbours::place_unseen`], learned from the dataset's training
    /// split), instead of the tracker's stale report. `None` keeps the stored positions. Callers
    /// that have the dataset set it with [`SceneConfig::with_neighbours_of`] (every `cargo
    /// xtask` pipeline does, since 2026-11-28: docs/pipelines.md, "Occluded points at the
    /// start").
    pub unseen: Option<Arc<MaterialNeighbours>>,
    /// Material springs: when set, [`Scene::backbone`] joins two tracked points only if their
    /// mean distance over the training recordings is at most [`MATERIAL_PAIR_FACTOR`] times the
    /// spring radius, so parts of the object that merely touch at the start frame (a rope
    /// lying across its own loop) are not glued together. `None` (the default) builds the
    /// reference's springs: every pair within the radius. Set it with
    /// [`SceneConfig::with_material_pairs_of`] (docs/pipelines.md, "Material springs").
    pub material_pairs: Option<Arc<MaterialPairs>>,
    /// For an `attach` dataset: join its grippers' particles by this rule instead of the
    /// dataset's own `controller_springs` (a run whose fit searched the rule, `fit
    /// --fit-controller`). `None` (the default) uses the dataset's.
    pub controller_springs: Option<dataset::ControllerSprings>,
}

impl SceneConfig {
    /// This configuration with [`SceneConfig::material_pairs`] learned from `data`'s training
    /// split; an error when the split is empty, its episodes disagree on the particle count or
    /// they track more than [`dataset::MAX_PAIR_POINTS`] points.
    pub fn with_material_pairs_of(mut self, data: &Dataset) -> Result<Self, SceneError> {
        let episodes = data
            .split_indices(Split::Train)
            .into_iter()
            .map(|i| data.load_episode(i))
            .collect::<Result<Vec<_>, _>>()?;
        let pairs = MaterialPairs::learn(&episodes).ok_or_else(|| SceneError::MaterialPairs {
            dataset: data.root.display().to_string(),
        })?;
        self.material_pairs = Some(Arc::new(pairs));
        Ok(self)
    }

    /// This configuration with [`SceneConfig::unseen`] learned from `data`'s training split
    /// (left `None` when the split is empty or its episodes disagree on the particle count).
    pub fn with_neighbours_of(mut self, data: &Dataset) -> Result<Self, SceneError> {
        let episodes = data
            .split_indices(Split::Train)
            .into_iter()
            .map(|i| data.load_episode(i))
            .collect::<Result<Vec<_>, _>>()?;
        self.unseen = MaterialNeighbours::learn(&episodes).map(Arc::new);
        Ok(self)
    }
}

impl Default for SceneConfig {
    fn default() -> Self {
        SceneConfig {
            chain_hidden_per_gap: 4,
            fill_volume: true,
            fill_spacing_factor: FILL_FACTOR,
            substep: Substep::AUTO,
            carry_occluded: true,
            unseen: None,
            material_pairs: None,
            controller_springs: None,
        }
    }
}

/// A simulated object at the start of an evaluation window, with the actions that drive it and
/// the truth it is scored against.
///
/// Particle order: the episode's `tracked` particles first (same indices as in the episode),
/// then hidden or interior particles, which the metrics never see.
#[derive(Clone, Debug)]
pub struct Scene {
    /// The window this scene covers.
    pub window: Window,
    /// Number of tracked particles (the first ones).
    pub tracked: usize,
    /// Gripper index per simulated particle, −1 for free.
    pub held: Vec<i32>,
    /// State of every simulated particle at the start frame (m, m/s).
    pub init: State,
    /// Gripper positions and closed flags for frames `start ..= start + steps`.
    pub actions: Actions,
    /// Tracked positions at frames `start + 1 ..= start + steps`, m.
    pub truth: Vec<Vec<Vec3>>,
    /// Whether each tracked particle was seen at those frames.
    pub visible: Vec<Vec<bool>>,
    config: SimConfig,
    carry_occluded: bool,
    unseen: Option<Arc<MaterialNeighbours>>,
    material_pairs: Option<Arc<MaterialPairs>>,
    /// For a `chain` dataset with hidden particles: every particle in order along the cable.
    chain: Option<Arc<[u32]>>,
    /// For an `attach` dataset with `controller_springs`: the grippers' particles and their
    /// own spring rule.
    anchors: Option<springs::AnchorSprings>,
}

/// The particles of a densified chain in order along it: marker i, then the `per_gap`
/// particles [`densify_chain`] put after the markers for gap i, then marker i + 1, ...
fn chain_order(markers: usize, per_gap: usize) -> Arc<[u32]> {
    let mut order = Vec::with_capacity(markers + per_gap * markers.saturating_sub(1));
    for i in 0..markers {
        order.push(i as u32);
        if i + 1 < markers {
            order.extend((0..per_gap).map(|k| (markers + i * per_gap + k) as u32));
        }
    }
    order.into()
}

impl Scene {
    /// Builds the scene of `episode` over `window`.
    pub fn new(
        meta: &DatasetMeta,
        episode: &Episode,
        window: Window,
        config: &SceneConfig,
    ) -> Result<Self, SceneError> {
        let last = window.start + window.steps;
        if window.start == 0 || last >= episode.frames() {
            return Err(SceneError::TooShort {
                frames: episode.frames(),
                needed: last + 1,
                protocol: "this",
            });
        }
        let fps = meta.fps;
        let mut held = episode.held_or_default(meta.manipulation, meta.gripper_radius);
        if let Some(table) = &config.unseen
            && table.particles() != episode.particles()
        {
            return Err(SceneError::NeighboursMismatch {
                table: table.particles(),
                particles: episode.particles(),
            });
        }
        if let Some(table) = &config.material_pairs
            && table.particles() != episode.particles()
        {
            return Err(SceneError::NeighboursMismatch {
                table: table.particles(),
                particles: episode.particles(),
            });
        }
        let read = |t| {
            read_frame(
                episode,
                t,
                &held,
                config.carry_occluded,
                config.unseen.as_deref(),
            )
        };
        let x0 = read(window.start);
        let xm = read(window.start - 1);
        let v0: Vec<Vec3> = x0.iter().zip(&xm).map(|(a, b)| (*a - *b) * fps).collect();
        let mut x = x0;
        let mut v = v0;
        let mut chain = None;
        match meta.structure {
            Structure::Chain if config.chain_hidden_per_gap > 0 => {
                chain = Some(chain_order(x.len(), config.chain_hidden_per_gap));
                let (hx, hv) = densify_chain(&x, &v, config.chain_hidden_per_gap);
                held.extend(std::iter::repeat_n(-1, hx.len()));
                x.extend(hx);
                v.extend(hv);
            }
            Structure::Volume if config.fill_volume => {
                let median = median_spacing(&x);
                if median.is_nan() || median <= 0.0 {
                    return Err(SceneError::CollapsedVolume {
                        frame: window.start,
                    });
                }
                let spacing = config.fill_spacing_factor * median;
                let interior = springs::fill_interior(&x, spacing)?;
                let iv = interior
                    .iter()
                    .map(|p| mean_velocity_near(&x, &v, *p, 4))
                    .collect::<Vec<_>>();
                held.extend(std::iter::repeat_n(-1, interior.len()));
                x.extend(interior);
                v.extend(iv);
            }
            _ => {}
        }
        let mut anchors = None;
        if meta.manipulation == dataset::Manipulation::Attach {
            // Each gripper becomes a particle held by it, at its position: the backbone joins
            // it to the object particles near it by the dataset's controller rule, or else as
            // any two particles.
            let first = x.len() as u32;
            let rule = config.controller_springs.or(meta.controller_springs);
            anchors = rule.map(|rule| springs::AnchorSprings {
                particles: (first..first + episode.grippers() as u32).collect(),
                radius_m: rule.radius_m,
                max_springs: rule.max_springs,
            });
            let (now, before) = (
                episode.gripper_frame(window.start),
                episode.gripper_frame(window.start - 1),
            );
            for (g, (p, q)) in now.iter().zip(before).enumerate() {
                x.push(*p);
                v.push((*p - *q) * fps);
                held.push(g as i32);
            }
        }
        let frames = window.start..=last;
        let positions = frames
            .clone()
            .map(|t| episode.gripper_frame(t).to_vec())
            .collect();
        let closed = frames
            .map(|t| {
                (0..episode.grippers())
                    .map(|g| episode.closed(t, g))
                    .collect()
            })
            .collect();
        let actions = Actions::new(positions, closed)?;
        let truth_frames = window.start + 1..=last;
        let truth = truth_frames
            .clone()
            .map(|t| episode.frame(t).to_vec())
            .collect();
        let visible = truth_frames
            .map(|t| {
                (0..episode.particles())
                    .map(|i| episode.visible(t, i))
                    .collect()
            })
            .collect();
        let sim = SimConfig {
            step_dt: meta.step_dt(),
            gravity: Vec3::from_array(meta.gravity),
            ground_z: meta.ground_z,
            manipulation: match meta.manipulation {
                // Attached grippers are held particles, which follow their gripper as under a grasp.
                dataset::Manipulation::Grasp | dataset::Manipulation::Attach => {
                    springs::Manipulation::Grasp
                }
                dataset::Manipulation::Push => springs::Manipulation::Push,
            },
            gripper_radius: meta.gripper_radius,
            substep: config.substep,
            ..SimConfig::default()
        };
        Ok(Scene {
            window,
            tracked: episode.particles(),
            held,
            init: State { x, v },
            actions,
            truth,
            visible,
            config: sim,
            carry_occluded: config.carry_occluded,
            unseen: config.unseen.clone(),
            material_pairs: config.material_pairs.clone(),
            chain,
            anchors,
        })
    }

    /// Tracked positions of `episode` (this scene's) at frame `t` as this scene reads its
    /// start: carried through occlusion when [`SceneConfig::carry_occluded`] was set, as stored
    /// otherwise. Use it for any frame up to the start (e.g. a network's history), so that it
    /// agrees with [`Scene::init`].
    pub fn start_frame(&self, episode: &dataset::Episode, t: usize) -> Vec<Vec3> {
        let held = &self.held[..self.tracked.min(self.held.len())];
        read_frame(
            episode,
            t,
            held,
            self.carry_occluded,
            self.unseen.as_deref(),
        )
    }

    /// The simulator settings this scene's dataset implies (step, gravity, ground, grippers).
    pub fn sim_config(&self) -> SimConfig {
        self.config
    }

    /// The particles joined to the object by a controller rule of their own, and that rule:
    /// an `attach` scene's grippers when its dataset (or [`SceneConfig::controller_springs`])
    /// gives one; `None` otherwise.
    pub fn anchors(&self) -> Option<&springs::AnchorSprings> {
        self.anchors.as_ref()
    }

    /// Number of simulated particles (tracked + hidden/interior).
    pub fn particles(&self) -> usize {
        self.init.x.len()
    }

    /// The widest gap around a free particle at the start frame, m: the largest distance from
    /// a free (not held) particle to its nearest other particle. A spring threshold below it
    /// leaves that particle without a spring, falling freely. 0 when no free particle has a
    /// neighbour.
    pub fn widest_free_gap_m(&self) -> f32 {
        widest_free_gap(&self.init.x, &self.held)
    }

    /// How many springs the reference construction (every pair within the threshold, the
    /// paper's) builds at this scene's start between tracked points that `pairs` says are not
    /// material neighbours: their mean distance over the training recordings exceeds
    /// [`MATERIAL_PAIR_FACTOR`] times the threshold. Such springs glue parts that only touch at
    /// the start frame for the whole rollout (docs/pipelines.md, "Material springs").
    /// Whatever [`SceneConfig::material_pairs`] this scene was built with is ignored.
    pub fn glued_springs(
        &self,
        params: &SpringParams,
        pairs: &MaterialPairs,
    ) -> Result<usize, SceneError> {
        let options = BackboneOptions {
            pair_filter: Some(Arc::new(EveryPair)),
            ..BackboneOptions::default()
        };
        let bb = self.backbone(params, &self.sim_config(), options)?;
        let limit = MATERIAL_PAIR_FACTOR * params.threshold;
        Ok(bb
            .springs()
            .iter()
            .filter(|&&[a, b]| {
                let (a, b) = (a as usize, b as usize);
                a < self.tracked
                    && b < self.tracked
                    && pairs.mean_distance(a, b).is_some_and(|d| d > limit)
            })
            .count())
    }

    /// The backbone for this scene: springs from the start frame (between material neighbours
    /// only, when the scene's configuration has [`SceneConfig::material_pairs`] and `options`
    /// no filter of its own); `options` carries per-particle masses and effects (none by
    /// default). A chain scene hands its order along the cable to the effects
    /// ([`BackboneOptions::chain`]) unless `options` has one; an `attach` scene whose dataset
    /// gives `controller_springs` joins its grippers' particles by that rule
    /// ([`BackboneOptions::anchors`]) unless `options` has one.
    pub fn backbone(
        &self,
        params: &SpringParams,
        config: &SimConfig,
        mut options: BackboneOptions,
    ) -> Result<Backbone, SceneError> {
        if options.pair_filter.is_none()
            && let Some(pairs) = &self.material_pairs
        {
            options.pair_filter = Some(Arc::new(MaterialSprings {
                pairs: pairs.clone(),
            }));
        }
        if options.chain.is_none() {
            options.chain = self.chain.clone();
        }
        if options.anchors.is_none() {
            options.anchors = self.anchors.clone();
        }
        Ok(Backbone::with_options(
            &self.init.x,
            &self.held,
            *params,
            *config,
            options,
        )?)
    }

    /// The part of this scene that starts `offset` steps after its start and runs `steps`
    /// steps, from `init` (a state of every simulated particle, e.g. a model's own rollout
    /// state at that frame). Particles, held map and settings stay those of `self`.
    pub fn segment(&self, offset: usize, steps: usize, init: State) -> Result<Scene, SceneError> {
        let end = offset + steps;
        if steps == 0 || end > self.window.steps {
            return Err(SceneError::TooShort {
                frames: self.window.steps + 1,
                needed: end + 1,
                protocol: "segment",
            });
        }
        let n = self.particles();
        for (what, got) in [
            ("segment positions", init.x.len()),
            ("segment velocities", init.v.len()),
        ] {
            if got != n {
                return Err(springs::SimError::LengthMismatch {
                    what,
                    expected: n,
                    got,
                }
                .into());
            }
        }
        let frames = (offset..=end).filter_map(|t| self.actions.frame(t));
        let (positions, closed) = frames
            .map(|f| (f.positions.to_vec(), f.closed.to_vec()))
            .unzip();
        Ok(Scene {
            window: Window {
                start: self.window.start + offset,
                steps,
            },
            tracked: self.tracked,
            held: self.held.clone(),
            init,
            actions: Actions::new(positions, closed)?,
            truth: self.truth[offset..end].to_vec(),
            visible: self.visible[offset..end].to_vec(),
            config: self.config,
            carry_occluded: self.carry_occluded,
            unseen: self.unseen.clone(),
            material_pairs: self.material_pairs.clone(),
            chain: self.chain.clone(),
            anchors: self.anchors.clone(),
        })
    }

    /// Rolls the backbone out over the window; returns the tracked particles' positions after
    /// each step (`steps` entries), m.
    pub fn rollout(
        &self,
        params: &SpringParams,
        config: &SimConfig,
        options: BackboneOptions,
    ) -> Result<Vec<Vec<Vec3>>, SceneError> {
        let backbone = self.backbone(params, config, options)?;
        let rollout = backbone.rollout(&self.init, &self.actions)?;
        Ok(rollout
            .positions
            .into_iter()
            .skip(1)
            .map(|mut p| {
                p.truncate(self.tracked);
                p
            })
            .collect())
    }
}

/// The reference construction's rule: every pair within the threshold.
#[derive(Debug)]
struct EveryPair;

impl springs::PairFilter for EveryPair {
    fn keep(&self, _: usize, _: usize, _: f32) -> bool {
        true
    }
}

/// The spring filter of [`SceneConfig::material_pairs`]: tracked points far apart on average
/// are not material neighbours. Hidden and interior particles (beyond the table) and pairs
/// seen together too rarely keep the reference rule.
#[derive(Debug)]
struct MaterialSprings {
    pairs: Arc<MaterialPairs>,
}

impl springs::PairFilter for MaterialSprings {
    fn keep(&self, a: usize, b: usize, threshold: f32) -> bool {
        self.pairs
            .mean_distance(a, b)
            .is_none_or(|d| d <= MATERIAL_PAIR_FACTOR * threshold)
    }
}

/// `per_gap` particles evenly spaced on each segment between consecutive markers, with
/// velocities interpolated the same way.
fn densify_chain(x: &[Vec3], v: &[Vec3], per_gap: usize) -> (Vec<Vec3>, Vec<Vec3>) {
    let mut hx = Vec::with_capacity(per_gap * x.len());
    let mut hv = Vec::with_capacity(per_gap * x.len());
    for i in 0..x.len().saturating_sub(1) {
        for k in 1..=per_gap {
            let s = k as f32 / (per_gap + 1) as f32;
            hx.push(x[i].lerp(x[i + 1], s));
            hv.push(v[i].lerp(v[i + 1], s));
        }
    }
    (hx, hv)
}

/// Median distance from each point to its nearest neighbour, m (the interior fill spacing).
///
/// The immutable tree, because kiddo's mutable one panics once more than a bucket's worth of
/// points share one position (a tracker that reports many points at one place).
fn median_spacing(x: &[Vec3]) -> f32 {
    let mut d = nearest_distances(x);
    d.sort_by(f32::total_cmp);
    d.get(d.len() / 2).copied().unwrap_or(0.0)
}

/// [`Scene::widest_free_gap_m`] of particles at `x` held as `held`.
fn widest_free_gap(x: &[Vec3], held: &[i32]) -> f32 {
    nearest_distances(x)
        .into_iter()
        .zip(held)
        .filter(|(_, h)| **h < 0)
        .map(|(d, _)| d)
        .fold(0.0, f32::max)
}

/// Distance from each point to its nearest other point, m; empty for fewer than two points.
fn nearest_distances(x: &[Vec3]) -> Vec<f32> {
    if x.len() < 2 {
        return Vec::new();
    }
    let pts: Vec<[f32; 3]> = x.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f32, u32, 3, 32> = ImmutableKdTree::new_from_slice(&pts);
    // The point itself and its nearest other point.
    let two = NonZeroUsize::new(2).expect("2 is non-zero");
    pts.iter()
        .map(|p| {
            let n = tree.nearest_n::<SquaredEuclidean>(p, two);
            n.get(1).map_or(0.0, |n| n.distance.sqrt())
        })
        .collect()
}

/// Mean velocity of the `k` tracked particles nearest to `p`.
fn mean_velocity_near(x: &[Vec3], v: &[Vec3], p: Vec3, k: usize) -> Vec3 {
    let mut d: Vec<(f32, usize)> = x
        .iter()
        .enumerate()
        .map(|(i, q)| (q.distance_squared(p), i))
        .collect();
    let k = k.min(d.len());
    if k == 0 {
        return Vec3::ZERO;
    }
    d.select_nth_unstable_by(k - 1, |a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    d[..k].iter().map(|(_, i)| v[*i]).sum::<Vec3>() / k as f32
}

/// Frame `t` of `episode`, carried through occlusion or as stored, then with the points not seen
/// up to `t` placed by their material neighbours when `unseen` is given.
fn read_frame(
    episode: &Episode,
    t: usize,
    held: &[i32],
    carry: bool,
    unseen: Option<&MaterialNeighbours>,
) -> Vec<Vec3> {
    let mut frame = if carry {
        dataset::carried_frame(episode, t, held)
    } else {
        episode.frame(t).to_vec()
    };
    if let Some(table) = unseen {
        table.place_unseen(episode, t, &mut frame);
    }
    frame
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two held particles rising with their gripper 1 cm per frame; the tracker loses
    /// particle 1 after frame 1 and keeps its frame-1 position.
    fn lifted_pair() -> (DatasetMeta, Episode) {
        let meta = DatasetMeta::new("pair", 10.0, dataset::Manipulation::Grasp);
        let rise = |t: usize| 0.01 * t as f32 * Vec3::Z;
        let mut positions = Vec::new();
        for t in 0..6 {
            positions.push(Vec3::new(0.0, 0.0, 0.1) + rise(t));
            positions.push(Vec3::new(0.02, 0.0, 0.1) + rise(t.min(1)));
        }
        let grippers = (0..6)
            .map(|t| Vec3::new(0.01, 0.0, 0.1) + rise(t))
            .collect();
        let mut visible = vec![1u8; 12];
        for t in 2..6 {
            visible[2 * t + 1] = 0;
        }
        let episode = Episode::new(6, 2, 1, positions, grippers)
            .and_then(|e| e.with_visible(visible))
            .and_then(|e| e.with_held(vec![0, 0]))
            .unwrap();
        (meta, episode)
    }

    #[test]
    fn an_occluded_held_point_starts_where_its_gripper_took_it() {
        let (meta, episode) = lifted_pair();
        let window = Window { start: 4, steps: 1 };
        let carried = Scene::new(&meta, &episode, window, &SceneConfig::default()).unwrap();
        let expected = Vec3::new(0.02, 0.0, 0.14);
        assert!(
            (carried.init.x[1] - expected).length() < 1e-6,
            "{:?}",
            carried.init.x[1]
        );
        assert!(
            (carried.init.v[1] - 0.1 * Vec3::Z).length() < 1e-5,
            "{:?}",
            carried.init.v[1]
        );
        assert_eq!(
            carried.start_frame(&episode, 3)[1],
            Vec3::new(0.02, 0.0, 0.13)
        );
        let stored = SceneConfig {
            carry_occluded: false,
            ..SceneConfig::default()
        };
        let stale = Scene::new(&meta, &episode, window, &stored).unwrap();
        assert_eq!(stale.init.x[1], Vec3::new(0.02, 0.0, 0.11));
        assert_eq!(stale.init.v[1], Vec3::ZERO);
        assert_eq!(stale.start_frame(&episode, 3), episode.frame(3).to_vec());
    }

    /// A row of four points 1 cm apart, 10 cm up with no ground, and one gripper 5 mm beside
    /// its first point rising 1 cm per frame, under `manipulation`.
    fn lifted_row(manipulation: dataset::Manipulation) -> Scene {
        lifted_row_joined(manipulation, None)
    }

    /// [`lifted_row`] with the dataset's `controller_springs`.
    fn lifted_row_joined(
        manipulation: dataset::Manipulation,
        controller_springs: Option<dataset::ControllerSprings>,
    ) -> Scene {
        let mut meta = DatasetMeta::new("row", 10.0, manipulation);
        meta.ground_z = None;
        meta.gripper_radius = 0.0;
        meta.controller_springs = controller_springs;
        let positions = (0..12)
            .flat_map(|_| (0..4).map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.1)))
            .collect();
        let grippers = (0..12)
            .map(|t| Vec3::new(-0.005, 0.0, 0.1 + 0.01 * t as f32))
            .collect();
        let episode = Episode::new(12, 4, 1, positions, grippers).unwrap();
        let window = Window {
            start: 1,
            steps: 10,
        };
        Scene::new(&meta, &episode, window, &SceneConfig::default()).unwrap()
    }

    #[test]
    fn an_attached_gripper_is_a_held_particle_that_pulls_through_springs() {
        let attached = lifted_row(dataset::Manipulation::Attach);
        assert_eq!((attached.tracked, attached.init.x.len()), (4, 5));
        assert_eq!(attached.held, [-1, -1, -1, -1, 0]);
        assert_eq!(attached.init.x[4], Vec3::new(-0.005, 0.0, 0.11));
        assert!((attached.init.v[4] - 0.1 * Vec3::Z).length() < 1e-5);
        let params = springs::SpringParams::reference_rope();
        let rise = |scene: &Scene| {
            let pred = scene
                .rollout(&params, &scene.sim_config(), Default::default())
                .unwrap();
            pred.last().unwrap()[0].z - scene.init.x[0].z
        };
        // Attached, the row's first point follows the gripper up; with nothing held (a grasp of
        // radius 0) it falls.
        assert!(rise(&attached) > 0.05, "{}", rise(&attached));
        let loose = lifted_row(dataset::Manipulation::Grasp);
        assert_eq!(loose.init.x.len(), 4);
        assert!(rise(&loose) < 0.0, "{}", rise(&loose));
    }

    #[test]
    fn controller_springs_join_the_gripper_by_their_own_radius_and_count() {
        // The row's points are 1 cm apart; a 1.2 cm threshold joins neighbours only.
        let params = springs::SpringParams {
            threshold: 0.012,
            ..springs::SpringParams::reference_rope()
        };
        let gripper_springs = |scene: &Scene| -> Vec<[u32; 2]> {
            let bb = scene
                .backbone(&params, &scene.sim_config(), Default::default())
                .unwrap();
            let mut joined: Vec<[u32; 2]> = (bb.springs().iter().copied())
                .filter(|s| s.contains(&4))
                .collect();
            // The backbone orders its springs by colour; compare them as a set.
            joined.sort_unstable();
            joined
        };
        let attach = |rule| lifted_row_joined(dataset::Manipulation::Attach, rule);
        // At the start the gripper is 1.1, 1.8, 2.7 and 3.6 cm from the row's points. Without
        // a rule of its own it is joined by the object's threshold: to point 0 alone.
        assert_eq!(gripper_springs(&attach(None)), [[0, 4]]);
        // PhysTwin's 4 cm reach joins all four; a count of two the nearest two.
        let phystwin = attach(Some(dataset::ControllerSprings::PHYSTWIN));
        assert_eq!(gripper_springs(&phystwin), [[0, 4], [1, 4], [2, 4], [3, 4]]);
        let two = attach(Some(dataset::ControllerSprings {
            radius_m: 0.04,
            max_springs: 2,
        }));
        assert_eq!(gripper_springs(&two), [[0, 4], [1, 4]]);
        // The rule is kept by a segment of the scene.
        let seg = two.segment(2, 3, two.init.clone()).unwrap();
        assert_eq!(gripper_springs(&seg), [[0, 4], [1, 4]]);
    }

    #[test]
    fn a_volume_collapsed_to_one_point_is_refused_by_name() {
        let mut meta = DatasetMeta::new("blob", 10.0, dataset::Manipulation::Grasp);
        meta.structure = Structure::Volume;
        let episode = Episode::new(
            3,
            8,
            1,
            vec![Vec3::new(0.1, 0.1, 0.1); 24],
            vec![Vec3::splat(0.5); 3],
        )
        .unwrap();
        let window = Window { start: 1, steps: 1 };
        let err = Scene::new(&meta, &episode, window, &SceneConfig::default()).unwrap_err();
        assert!(
            matches!(err, SceneError::CollapsedVolume { frame: 1 }),
            "{err}"
        );
        // Spread out, the same points fill.
        let spread = (0..24).map(|k| Vec3::new(0.02 * (k % 8) as f32, 0.02 * (k % 2) as f32, 0.1));
        let episode = Episode::new(3, 8, 1, spread.collect(), vec![Vec3::splat(0.5); 3]).unwrap();
        assert!(Scene::new(&meta, &episode, window, &SceneConfig::default()).is_ok());
    }

    /// Three points in a row 1 cm apart rising 1 cm per frame, over `frames` frames; point 2 is
    /// lost in `lost` frames and stored 30 cm away there.
    fn rising_row(frames: usize, lost: std::ops::Range<usize>) -> Episode {
        let mut positions = Vec::new();
        let mut visible = Vec::new();
        for t in 0..frames {
            for i in 0..3 {
                let seen = i != 2 || !lost.contains(&t);
                let p = Vec3::new(0.01 * i as f32, 0.0, 0.1 + 0.01 * t as f32);
                positions.push(if seen { p } else { Vec3::new(0.3, 0.0, 0.1) });
                visible.push(u8::from(seen));
            }
        }
        Episode::new(
            frames,
            3,
            1,
            positions,
            vec![Vec3::new(0.0, 0.5, 0.5); frames],
        )
        .and_then(|e| e.with_visible(visible))
        .and_then(|e| e.with_held(vec![-1; 3]))
        .unwrap()
    }

    #[test]
    fn a_point_never_seen_starts_among_its_material_neighbours() {
        let meta = DatasetMeta::new("row", 10.0, dataset::Manipulation::Grasp);
        let table = MaterialNeighbours::learn([&rising_row(8, 0..0)]).unwrap();
        let config = SceneConfig {
            fill_volume: false,
            unseen: Some(Arc::new(table)),
            ..SceneConfig::default()
        };
        let episode = rising_row(6, 0..3);
        let window = Window { start: 2, steps: 2 };
        let scene = Scene::new(&meta, &episode, window, &config).unwrap();
        // Points 1 and 0 are its neighbours; their centroid, moving with them.
        let want = Vec3::new(0.005, 0.0, 0.12);
        assert!(
            (scene.init.x[2] - want).length() < 1e-6,
            "{:?}",
            scene.init.x[2]
        );
        assert!((scene.init.v[2] - 0.1 * Vec3::Z).length() < 1e-5);
        assert!((scene.start_frame(&episode, 1)[2] - want + 0.01 * Vec3::Z).length() < 1e-6);
        // Without the table the stale report stays, and the point starts at rest.
        let stale = SceneConfig {
            unseen: None,
            ..config.clone()
        };
        let scene = Scene::new(&meta, &episode, window, &stale).unwrap();
        assert_eq!(scene.init.x[2], Vec3::new(0.3, 0.0, 0.1));
        assert_eq!(scene.init.v[2], Vec3::ZERO);
        // A table for other points is refused.
        let four = Episode::new(1, 4, 1, vec![Vec3::ZERO; 4], vec![Vec3::ZERO]).unwrap();
        let wrong = SceneConfig {
            unseen: MaterialNeighbours::learn([&four]).map(Arc::new),
            ..config
        };
        assert!(matches!(
            Scene::new(&meta, &episode, window, &wrong),
            Err(SceneError::NeighboursMismatch {
                table: 4,
                particles: 3
            })
        ));
    }

    /// Ten points 1 cm apart: straight (`fold = false`) or bent into a hairpin whose two legs
    /// lie 5 mm apart (point 9 beside point 0), for `frames` frames.
    fn row_of_ten(frames: usize, fold: bool) -> Episode {
        let at = |i: usize| {
            if fold && i >= 5 {
                Vec3::new(0.01 * (9 - i) as f32, 0.005, 0.0)
            } else {
                Vec3::new(0.01 * i as f32, 0.0, 0.0)
            }
        };
        let positions = (0..frames).flat_map(|_| (0..10).map(at)).collect();
        Episode::new(
            frames,
            10,
            1,
            positions,
            vec![Vec3::new(0.0, 0.0, 0.5); frames],
        )
        .unwrap()
    }

    #[test]
    fn material_springs_do_not_glue_parts_that_only_touch_at_the_start() {
        let meta = DatasetMeta::new("row", 10.0, dataset::Manipulation::Grasp);
        let pairs = MaterialPairs::learn([&row_of_ten(4, false), &row_of_ten(4, false)]).unwrap();
        let reference = SceneConfig {
            fill_volume: false,
            ..SceneConfig::default()
        };
        let material = SceneConfig {
            material_pairs: Some(Arc::new(pairs)),
            ..reference.clone()
        };
        let folded = row_of_ten(3, true);
        let window = Window { start: 1, steps: 1 };
        let params = SpringParams {
            threshold: 0.015,
            max_springs: 20,
            ..SpringParams::reference_rope()
        };
        let springs = |config: &SceneConfig| {
            let scene = Scene::new(&meta, &folded, window, config).unwrap();
            let bb = scene
                .backbone(&params, &scene.sim_config(), BackboneOptions::default())
                .unwrap();
            let mut s = bb.springs().to_vec();
            s.sort();
            s
        };
        let along: Vec<[u32; 2]> = (0..9).map(|i| [i, i + 1]).collect();
        let glued = springs(&reference);
        // The reference joins the legs across the 5 mm gap (point 0 to 9, 1 to 8, ...).
        assert!(
            glued.contains(&[0, 9]) && glued.contains(&[3, 6]),
            "{glued:?}"
        );
        // Material springs join only pairs at most 2 x 1.5 cm apart along the row (at the bend,
        // 3 and 6 lie 1.1 cm apart and are 3 cm apart along it): every neighbour along it, no
        // leg to the other.
        let kept = springs(&material);
        // What the reference construction glues, counted against the table: every leg-to-leg
        // spring, whichever construction the scene itself was built with.
        let table = material.material_pairs.as_deref().unwrap();
        let legs = glued.iter().filter(|[a, b]| b - a > 3).count();
        assert!(legs > 0);
        for config in [&reference, &material] {
            let scene = Scene::new(&meta, &folded, window, config).unwrap();
            assert_eq!(scene.glued_springs(&params, table).unwrap(), legs);
        }
        let straight = Scene::new(&meta, &row_of_ten(3, false), window, &reference).unwrap();
        assert_eq!(straight.glued_springs(&params, table).unwrap(), 0);
        assert!(along.iter().all(|s| kept.contains(s)), "{kept:?}");
        assert!(kept.iter().all(|[a, b]| b - a <= 3), "{kept:?}");
        assert!(kept.contains(&[3, 6]), "{kept:?}");
        // A filter of the caller's own wins over the table.
        let scene = Scene::new(&meta, &folded, window, &material).unwrap();
        let options = BackboneOptions {
            pair_filter: Some(Arc::new(EveryPair)),
            ..BackboneOptions::default()
        };
        let own = scene
            .backbone(&params, &scene.sim_config(), options)
            .unwrap();
        assert_eq!(own.springs().len(), glued.len());
        // A table for other points is refused.
        let four = Episode::new(4, 4, 1, vec![Vec3::X; 16], vec![Vec3::ZERO; 4]).unwrap();
        let wrong = SceneConfig {
            material_pairs: MaterialPairs::learn([&four]).map(Arc::new),
            ..material
        };
        assert!(matches!(
            Scene::new(&meta, &folded, window, &wrong),
            Err(SceneError::NeighboursMismatch {
                table: 4,
                particles: 10
            })
        ));
    }

    #[test]
    fn chain_hidden_particles_lie_between_markers() {
        let x = [Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0)];
        let v = [Vec3::Z, Vec3::Z, Vec3::ZERO];
        let (hx, hv) = densify_chain(&x, &v, 3);
        assert_eq!(hx.len(), 6);
        assert!((hx[1] - Vec3::new(0.5, 0.0, 0.0)).length() < 1e-6);
        assert!((hx[4] - Vec3::new(1.0, 0.5, 0.0)).length() < 1e-6);
        assert!((hv[4] - Vec3::Z * 0.5).length() < 1e-6);
    }

    #[test]
    fn the_chain_order_walks_the_densified_cable_end_to_end() {
        let x = [Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0)];
        let v = [Vec3::ZERO; 3];
        let (hx, _) = densify_chain(&x, &v, 3);
        let all: Vec<Vec3> = x.iter().copied().chain(hx).collect();
        let order = chain_order(3, 3);
        assert_eq!(order.len(), all.len());
        assert_eq!((order[0], order[4], order[8]), (0, 1, 2));
        // Every step along the order is one hidden spacing (a quarter of a unit segment).
        for w in order.windows(2) {
            let d = all[w[0] as usize].distance(all[w[1] as usize]);
            assert!((d - 0.25).abs() < 1e-6, "{w:?}: {d}");
        }
    }

    #[test]
    fn median_spacing_of_a_line() {
        let x: Vec<Vec3> = (0..10).map(|i| Vec3::X * (i as f32 * 0.02)).collect();
        assert!((median_spacing(&x) - 0.02).abs() < 1e-6);
    }

    #[test]
    fn median_spacing_survives_many_points_at_one_place() {
        // 40 coincident reports, more than one tree bucket holds, beside a 2 cm line.
        let mut x = vec![Vec3::new(0.3, 0.1, 0.2); 40];
        x.extend((0..60).map(|i| Vec3::X * (i as f32 * 0.02)));
        assert!((median_spacing(&x) - 0.02).abs() < 1e-6);
        assert_eq!(median_spacing(&x[..1]), 0.0);
    }

    #[test]
    fn the_widest_free_gap_ignores_held_particles_and_counts_them_as_neighbours() {
        // A 2 cm line, a free point 7 cm beyond its end, and a held point 9 cm beyond that.
        let mut x: Vec<Vec3> = (0..5).map(|i| Vec3::X * (i as f32 * 0.02)).collect();
        x.push(Vec3::X * 0.15);
        x.push(Vec3::X * 0.24);
        let mut held = vec![-1; 7];
        held[6] = 0;
        assert!((widest_free_gap(&x, &held) - 0.07).abs() < 1e-6);
        // Held, the lone point no longer counts: the line's 2 cm is the widest gap left.
        held[5] = 0;
        assert!((widest_free_gap(&x, &held) - 0.02).abs() < 1e-6);
        assert_eq!(widest_free_gap(&x[..1], &held[..1]), 0.0);
    }
}
