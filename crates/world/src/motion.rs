//! Gripper trajectories: smooth, varied, random, in the style of each object's manipulation.
//!
//! A trajectory is a quintic Hermite spline through random waypoints (positions and velocities
//! given, zero acceleration at every waypoint: continuous acceleration, robot-like) plus optional
//! waving: sinusoids with smoothly varying amplitude. Everything is constant before t = 0, and
//! starts from rest.

use glam::Vec3;
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::{Error, ObjectKind};

/// How the gripper moves in the recordings of grasped objects.
///
/// The pushed teddy is poked in every style (its pokes are planned online from its position).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MotionStyle {
    /// Everyday manipulation in the style of each object: smooth drifts, waving, lifts and
    /// lowers (`docs/world.md`, "Gripper motions").
    #[default]
    Everyday,
    /// Motions chosen to excite the effects a diagnosis looks for: fast sweeps followed by
    /// holds (drag, inertia, delay, damping, permanent set), the object lowered onto the table
    /// and slid slowly over it (friction, stick-slip), and quick vertical jerks (stretch,
    /// nonlinear elasticity, plasticity, mass distribution).
    Probing,
    /// Motions in the style of a sampling-based planner's executed paths (`crates/plan`'s MPPI):
    /// from the object's rest pose (the rope laid straight in half the recordings), moves of
    /// 0.3–1.2 s at 5–35 cm/s in random directions, mostly dragging over the table, sometimes
    /// lifting into the air or lowering back while moving, with short holds. Training data for
    /// models that plan.
    Planning,
}

impl MotionStyle {
    /// Every style, in the order the command line lists them.
    pub const ALL: [MotionStyle; 3] = [
        MotionStyle::Everyday,
        MotionStyle::Probing,
        MotionStyle::Planning,
    ];

    /// Whether this is the default style (for serde's `skip_serializing_if`).
    pub fn is_everyday(&self) -> bool {
        *self == MotionStyle::Everyday
    }

    /// The style's command-line name.
    pub fn name(self) -> &'static str {
        match self {
            MotionStyle::Everyday => "everyday",
            MotionStyle::Probing => "probing",
            MotionStyle::Planning => "planning",
        }
    }
}

impl std::fmt::Display for MotionStyle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for MotionStyle {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Error> {
        MotionStyle::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                Error::Config(format!(
                    "unknown motion style `{s}` (expected everyday, probing or planning)"
                ))
            })
    }
}

#[derive(Clone, Copy, Debug)]
struct Knot {
    t: f32,
    p: Vec3,
    v: Vec3,
}

#[derive(Clone, Debug)]
struct Wave {
    dir: Vec3,
    freq_hz: f32,
    phase: f32,
    /// Amplitude knots (time s, amplitude m), interpolated with a quintic smoothstep.
    envelope: Vec<(f32, f32)>,
}

/// A gripper trajectory, defined for all times (constant outside its knots).
#[derive(Clone, Debug)]
pub(crate) struct Motion {
    knots: Vec<Knot>,
    waves: Vec<Wave>,
    min_z: f32,
}

fn smoothstep5(s: f32) -> f32 {
    s * s * s * (10.0 + s * (-15.0 + 6.0 * s))
}

impl Motion {
    fn new(start: Vec3, min_z: f32) -> Motion {
        Motion {
            knots: vec![Knot {
                t: 0.0,
                p: start,
                v: Vec3::ZERO,
            }],
            waves: Vec::new(),
            min_z,
        }
    }

    /// A gripper that stays at `p`.
    pub(crate) fn default_at(p: Vec3) -> Motion {
        Motion::new(p, f32::NEG_INFINITY)
    }

    /// Gripper position at time `t` (s).
    pub(crate) fn at(&self, t: f32) -> Vec3 {
        let mut p = self.spline(t);
        for w in &self.waves {
            let a = envelope(&w.envelope, t);
            if a != 0.0 {
                p += w.dir * (a * (std::f32::consts::TAU * w.freq_hz * t + w.phase).sin());
            }
        }
        p.z = p.z.max(self.min_z);
        p
    }

    fn spline(&self, t: f32) -> Vec3 {
        let k = &self.knots;
        if t <= k[0].t {
            return k[0].p;
        }
        let last = k[k.len() - 1];
        if t >= last.t {
            return last.p;
        }
        let i = k.partition_point(|q| q.t <= t) - 1;
        let (a, b) = (k[i], k[i + 1]);
        let dt = b.t - a.t;
        let s = (t - a.t) / dt;
        let (s2, s3) = (s * s, s * s * s);
        let (s4, s5) = (s3 * s, s3 * s2);
        // Quintic Hermite basis with zero end accelerations.
        let h00 = 1.0 - 10.0 * s3 + 15.0 * s4 - 6.0 * s5;
        let h10 = s - 6.0 * s3 + 8.0 * s4 - 3.0 * s5;
        let h01 = 10.0 * s3 - 15.0 * s4 + 6.0 * s5;
        let h11 = -4.0 * s3 + 7.0 * s4 - 3.0 * s5;
        a.p * h00 + a.v * (h10 * dt) + b.p * h01 + b.v * (h11 * dt)
    }

    /// The time of the last waypoint, s.
    pub(crate) fn end_time(&self) -> f32 {
        self.knots[self.knots.len() - 1].t
    }

    fn last(&self) -> Vec3 {
        self.knots[self.knots.len() - 1].p
    }

    fn push(&mut self, dt: f32, p: Vec3) {
        let t = self.end_time() + dt;
        self.knots.push(Knot {
            t,
            p,
            v: Vec3::ZERO,
        });
    }

    /// Catmull–Rom velocities scaled by a random factor in [0, 1] (0: the arm stops there);
    /// vertical velocity is zeroed near the floor so the path does not dip into it.
    fn set_velocities(&mut self, rng: &mut impl Rng, from: usize) {
        let n = self.knots.len();
        for i in from.max(1)..n.saturating_sub(1) {
            let (a, b) = (self.knots[i - 1], self.knots[i + 1]);
            let mut v = (b.p - a.p) / (b.t - a.t) * rng.random_range(0.0..1.0f32);
            if self.knots[i].p.z < self.min_z + 0.02 {
                v.z = 0.0;
            }
            self.knots[i].v = v;
        }
    }

    fn add_waves(
        &mut self,
        rng: &mut impl Rng,
        count: usize,
        freq: (f32, f32),
        max_amp: f32,
        start: f32,
        vertical: f32,
    ) {
        let end = self.end_time();
        for _ in 0..count {
            let az = rng.random_range(0.0..std::f32::consts::TAU);
            let dir =
                Vec3::new(az.cos(), az.sin(), rng.random_range(-vertical..=vertical)).normalize();
            let mut envelope = vec![(0.0, 0.0), (start, 0.0)];
            let mut t = start;
            while t < end {
                t += rng.random_range(1.0..2.5);
                envelope.push((t, rng.random_range(0.0..max_amp)));
            }
            self.waves.push(Wave {
                dir,
                freq_hz: rng.random_range(freq.0..freq.1),
                phase: rng.random_range(0.0..std::f32::consts::TAU),
                envelope,
            });
        }
    }
}

fn envelope(knots: &[(f32, f32)], t: f32) -> f32 {
    if t <= knots[0].0 {
        return knots[0].1;
    }
    for w in knots.windows(2) {
        let ((t0, a0), (t1, a1)) = (w[0], w[1]);
        if t <= t1 {
            return a0 + (a1 - a0) * smoothstep5((t - t0) / (t1 - t0));
        }
    }
    knots[knots.len() - 1].1
}

fn clamp_disk(p: Vec3, centre: Vec3, radius: f32) -> Vec3 {
    let d = Vec3::new(p.x - centre.x, p.y - centre.y, 0.0);
    let l = d.length();
    if l <= radius {
        p
    } else {
        let q = centre + d * (radius / l);
        Vec3::new(q.x, q.y, p.z)
    }
}

/// An open-loop trajectory for a grasped object starting at `start` (the gripper's position after
/// settling), lasting at least `duration` seconds. `centre` is the middle of the workspace.
pub(crate) fn grasp_motion(
    kind: ObjectKind,
    start: Vec3,
    centre: Vec3,
    duration: f32,
    rng: &mut impl Rng,
) -> Motion {
    let mut m;
    match kind {
        ObjectKind::Rope => {
            // Drag across the table, lift, move in the air, lower; sometimes pause.
            let low = start.z;
            m = Motion::new(start, low);
            let mut lifted = false;
            while m.end_time() < duration {
                let p = m.last();
                if rng.random_bool(0.12) {
                    m.push(rng.random_range(0.3..0.8), p);
                    continue;
                }
                let r = rng.random_range(0.0..1.0f32);
                let az = rng.random_range(0.0..std::f32::consts::TAU);
                let dir = Vec3::new(az.cos(), az.sin(), 0.0);
                let (dt, q) = if !lifted && r < 0.6 {
                    let q = p + dir * rng.random_range(0.08..0.3);
                    let q = Vec3::new(q.x, q.y, low + rng.random_range(0.0..0.01));
                    (rng.random_range(0.8..1.8), q)
                } else if !lifted {
                    lifted = true;
                    let q = p + dir * rng.random_range(0.0..0.08);
                    (
                        rng.random_range(1.0..2.0),
                        Vec3::new(q.x, q.y, rng.random_range(0.15..0.4)),
                    )
                } else if r < 0.5 {
                    let q = p + dir * rng.random_range(0.0..0.15);
                    (
                        rng.random_range(0.8..1.8),
                        Vec3::new(q.x, q.y, rng.random_range(0.12..0.4)),
                    )
                } else {
                    lifted = false;
                    let q = p + dir * rng.random_range(0.0..0.1);
                    (
                        rng.random_range(1.0..2.0),
                        Vec3::new(q.x, q.y, low + rng.random_range(0.0..0.04)),
                    )
                };
                m.push(dt, clamp_disk(q, centre, 0.35));
            }
            m.set_velocities(rng, 0);
        }
        ObjectKind::Paper | ObjectKind::Flag | ObjectKind::Duster => {
            // Hold in the air: drift between random poses around home while waving.
            let (reach, freq, amp) = match kind {
                ObjectKind::Paper => (0.12, (0.6, 1.8), 0.06),
                ObjectKind::Flag => (0.15, (0.7, 2.0), 0.10),
                _ => (0.12, (0.8, 2.2), 0.08),
            };
            m = Motion::new(start, 0.1);
            while m.end_time() < duration {
                let q = start
                    + Vec3::new(
                        rng.random_range(-reach..reach),
                        rng.random_range(-reach..reach),
                        rng.random_range(-0.06..0.06),
                    );
                m.push(rng.random_range(0.7..1.6), q);
            }
            m.set_velocities(rng, 0);
            let start = rng.random_range(0.3..1.0);
            m.add_waves(rng, 2, freq, amp, start, 0.2);
        }
        ObjectKind::Sloth | ObjectKind::Teddy => {
            // Lift off the table, swing in the air, now and then lower it to touch down.
            let low = start.z;
            m = Motion::new(start, low - 0.005);
            m.push(rng.random_range(0.2..0.6), start);
            let up = Vec3::new(start.x, start.y, low + rng.random_range(0.15..0.3));
            m.push(rng.random_range(1.0..1.5), up);
            while m.end_time() < duration {
                let q = if rng.random_bool(0.2) {
                    let p = m.last();
                    Vec3::new(p.x, p.y, low + rng.random_range(0.0..0.04))
                } else {
                    let q = centre
                        + Vec3::new(
                            rng.random_range(-0.15..0.15),
                            rng.random_range(-0.15..0.15),
                            0.0,
                        );
                    Vec3::new(q.x, q.y, low + rng.random_range(0.12..0.32))
                };
                m.push(rng.random_range(0.8..1.6), q);
            }
            m.set_velocities(rng, 2);
            m.add_waves(rng, 2, (0.5, 1.2), 0.07, 2.0, 0.1);
        }
    }
    m
}

/// Heights and reach of a grasped object's probing motions, m.
struct ProbeFrame {
    /// Gripper height at which the object lies on (rope, toys) or drapes over (hanging
    /// objects) the table.
    contact_z: f32,
    /// Range of gripper heights with the object in the air.
    air_z: (f32, f32),
    /// Horizontal reach around `centre`.
    reach: f32,
}

fn probe_frame(kind: ObjectKind, start: Vec3, hang: f32) -> ProbeFrame {
    match kind {
        // Lying on the table: the gripper's rest height is the contact height.
        ObjectKind::Rope => ProbeFrame {
            contact_z: start.z,
            air_z: (0.15, 0.4),
            reach: 0.35,
        },
        ObjectKind::Sloth | ObjectKind::Teddy => ProbeFrame {
            contact_z: start.z,
            air_z: (start.z + 0.12, start.z + 0.3),
            reach: 0.2,
        },
        // Hanging: lowering the gripper to 60 % of the hanging length lays the lower 40 % of
        // the sheet on the table.
        ObjectKind::Paper | ObjectKind::Flag | ObjectKind::Duster => ProbeFrame {
            contact_z: (0.6 * hang).max(0.03),
            air_z: (start.z - 0.06, start.z + 0.1),
            reach: 0.2,
        },
    }
}

/// A random horizontal offset of length in `lo..hi`, m.
fn horizontal(rng: &mut impl Rng, lo: f32, hi: f32) -> Vec3 {
    let az = rng.random_range(0.0..std::f32::consts::TAU);
    Vec3::new(az.cos(), az.sin(), 0.0) * rng.random_range(lo..hi)
}

/// A probing trajectory for a grasped object (see [`MotionStyle::Probing`]): `start` is the
/// gripper after settling, `hang` how far the object reaches below it (m), `centre` the middle
/// of the workspace. Waypoints have zero velocity, so every move ends in a clean stop.
pub(crate) fn probing_motion(
    kind: ObjectKind,
    start: Vec3,
    hang: f32,
    centre: Vec3,
    duration: f32,
    rng: &mut impl Rng,
) -> Motion {
    let f = probe_frame(kind, start, hang);
    let mut m = Motion::new(start, f.contact_z.min(start.z) - 0.005);
    m.push(rng.random_range(0.2..0.5), start);
    while m.end_time() < duration {
        let p = m.last();
        let in_air = p.z >= f.air_z.0 - 1e-3;
        let r = rng.random_range(0.0..1.0f32);
        if r < 0.4 {
            // Fast sweep through the air (15–30 cm in 0.3–0.5 s: peak speed 0.6–1.9 m/s), then
            // hold still.
            if !in_air {
                let up = Vec3::new(p.x, p.y, rng.random_range(f.air_z.0..f.air_z.1));
                m.push(rng.random_range(0.6..1.0), up);
            }
            let p = m.last();
            let q = p + horizontal(rng, 0.15, 0.3);
            let q = Vec3::new(q.x, q.y, rng.random_range(f.air_z.0..f.air_z.1));
            m.push(rng.random_range(0.3..0.5), clamp_disk(q, centre, f.reach));
            m.push(rng.random_range(0.5..1.2), m.last());
        } else if r < 0.75 {
            // Lower onto the table and slide slowly (0.1–0.3 m/s), then rest there.
            let down = Vec3::new(p.x, p.y, f.contact_z + rng.random_range(0.0..0.01));
            if (p.z - down.z).abs() > 0.01 {
                m.push(rng.random_range(0.6..1.0), down);
                m.push(rng.random_range(0.2..0.4), down);
            }
            let q = clamp_disk(down + horizontal(rng, 0.12, 0.3), centre, f.reach);
            m.push(rng.random_range(0.8..1.6), q);
            m.push(rng.random_range(0.3..0.6), q);
        } else {
            // Quick vertical jerk in the air and back, then hold.
            if !in_air {
                let up = Vec3::new(p.x, p.y, rng.random_range(f.air_z.0..f.air_z.1));
                m.push(rng.random_range(0.6..1.0), up);
            }
            let p = m.last();
            m.push(
                rng.random_range(0.25..0.4),
                p + Vec3::Z * rng.random_range(0.08..0.15),
            );
            m.push(rng.random_range(0.25..0.4), p);
            m.push(rng.random_range(0.6..1.0), p);
        }
    }
    m
}

/// A planner-style trajectory for a grasped object (see [`MotionStyle::Planning`]): `start` is
/// the gripper after settling, `hang` how far the object reaches below it (m). The gripper stays
/// within a disk around its start (a planning task's workspace).
pub(crate) fn planning_motion(
    kind: ObjectKind,
    start: Vec3,
    hang: f32,
    duration: f32,
    rng: &mut impl Rng,
) -> Motion {
    let f = probe_frame(kind, start, hang);
    let mut m = Motion::new(start, f.contact_z.min(start.z) - 0.005);
    m.push(rng.random_range(0.1..0.4), start);
    planning_moves(&mut m, kind, &f, start, duration, rng);
    m.set_velocities(rng, 1);
    m
}

/// A branch of the planning trajectory `trunk` (made by [`planning_motion`] with the same
/// `kind`, `start` and `hang`): identical to it up to a waypoint, then fresh random moves until
/// `duration`. The waypoint is the trunk's first one at or after `after` seconds, or, when that
/// one is not before `before`, its last one before `before` (never the start). It keeps the
/// trunk's velocity, so the two trajectories agree exactly up to it. Returns the branch and
/// that waypoint's time, s (`None` when the trunk has no waypoint in (0, `before`)).
pub(crate) fn planning_branch(
    trunk: &Motion,
    kind: ObjectKind,
    start: Vec3,
    hang: f32,
    (after, before): (f32, f32),
    duration: f32,
    rng: &mut impl Rng,
) -> Option<(Motion, f32)> {
    let knots = &trunk.knots;
    let k = knots
        .iter()
        .position(|q| q.t >= after && q.t < before)
        .or_else(|| knots.iter().rposition(|q| q.t > 0.0 && q.t < before))?;
    let f = probe_frame(kind, start, hang);
    let mut m = trunk.clone();
    m.knots.truncate(k + 1);
    planning_moves(&mut m, kind, &f, start, duration, rng);
    m.set_velocities(rng, k + 1);
    Some((m, knots[k].t))
}

/// Appends planner-style moves to `m` until it covers `duration` seconds (velocities unset).
fn planning_moves(
    m: &mut Motion,
    kind: ObjectKind,
    f: &ProbeFrame,
    start: Vec3,
    duration: f32,
    rng: &mut impl Rng,
) {
    // The rope tasks move the gripper up to 45 cm (rerouting farther, in many moves).
    let reach = if kind == ObjectKind::Rope { 0.6 } else { 0.3 };
    while m.end_time() < duration {
        let p = m.last();
        if rng.random_bool(0.1) {
            m.push(rng.random_range(0.2..0.6), p);
            continue;
        }
        let in_air = p.z >= f.air_z.0 - 1e-3;
        let dt = rng.random_range(0.3..1.2f32);
        let speed = rng.random_range(0.05..0.35f32);
        let r = rng.random_range(0.0..1.0f32);
        let z = if in_air && r < 0.5 {
            // Lower onto the table while moving.
            f.contact_z + rng.random_range(0.0..0.02)
        } else if in_air {
            (p.z + rng.random_range(-0.1..0.1)).clamp(f.air_z.0, f.air_z.1)
        } else if r < 0.15 {
            // Lift while moving.
            rng.random_range(f.air_z.0..f.air_z.1)
        } else {
            // Drag over the table.
            f.contact_z + rng.random_range(0.0..0.015)
        };
        let dz = (z - p.z).abs();
        let along = (speed * dt).powi(2) - dz * dz;
        let az = rng.random_range(0.0..std::f32::consts::TAU);
        let q = p + Vec3::new(az.cos(), az.sin(), 0.0) * along.max(0.0).sqrt();
        let q = clamp_disk(Vec3::new(q.x, q.y, z), start, reach);
        // A long vertical move takes at least what 15 cm/s allows.
        m.push(dt.max(dz / speed.max(0.15)), q);
    }
}

/// Online planner of pokes for a pushed object: every poke is aimed at the object's current
/// position, so the finger keeps finding it even after it slid or toppled.
#[derive(Clone, Debug)]
pub(crate) struct PokePlanner {
    /// Pushing-sphere radius, m.
    pub radius: f32,
    /// Lattice spacing of the object, m (to find its surface along a ray).
    pub spacing: f32,
}

impl PokePlanner {
    /// The finger's start: beside the object, at a safe distance.
    pub(crate) fn start(&self, x: &[Vec3], rng: &mut impl Rng) -> (Motion, Vec3) {
        let c = crate::build::centroid_of(x);
        let az = rng.random_range(0.0..std::f32::consts::TAU);
        let d = Vec3::new(az.cos(), az.sin(), 0.0);
        let s = self.surface_distance(x, c, d, 0.08);
        let p = Vec3::new(c.x, c.y, 0.0) + d * (s + self.radius + 0.05) + Vec3::Z * 0.08;
        (Motion::new(p, self.radius), p)
    }

    /// Appends pokes until the trajectory covers `until` seconds, using the object's current
    /// particle positions `x`. Pokes come from the side (moving around the object along an arc
    /// outside it) or, now and then, from above.
    pub(crate) fn extend(&self, m: &mut Motion, x: &[Vec3], until: f32, rng: &mut impl Rng) {
        let first_new = m.knots.len();
        while m.end_time() < until {
            let c = crate::build::centroid_of(x);
            let top = x.iter().map(|p| p.z).fold(f32::NEG_INFINITY, f32::max);
            let depth = rng.random_range(0.01..0.03);
            let p = m.last();
            let here = (p.y - c.y).atan2(p.x - c.x);
            if rng.random_bool(0.15) {
                let xy = Vec3::new(c.x, c.y, 0.0)
                    + Vec3::new(
                        rng.random_range(-0.02..0.02),
                        rng.random_range(-0.02..0.02),
                        0.0,
                    );
                let s = x
                    .iter()
                    .filter(|q| {
                        Vec3::new(q.x - xy.x, q.y - xy.y, 0.0).length() < 1.5 * self.spacing
                    })
                    .map(|q| q.z)
                    .fold(top * 0.5, f32::max);
                let safe = top + self.radius + 0.04;
                m.push(
                    rng.random_range(0.3..0.5),
                    Vec3::new(p.x, p.y, safe.max(p.z)),
                );
                m.push(rng.random_range(0.4..0.7), xy + Vec3::Z * safe);
                m.push(
                    rng.random_range(0.3..0.6),
                    xy + Vec3::Z * (s + self.radius - depth),
                );
                m.push(
                    rng.random_range(0.05..0.2),
                    xy + Vec3::Z * (s + self.radius - depth),
                );
                m.push(rng.random_range(0.3..0.5), xy + Vec3::Z * safe);
                continue;
            }
            let target = here + rng.random_range(-1.6..1.6f32);
            let z = (top * rng.random_range(0.2..0.55)).max(self.radius + 0.005);
            // Around the object in steps of at most 45°, staying 3 cm outside its surface.
            let arc = ((target - here).abs() / 0.785).ceil().max(1.0) as usize;
            for k in 1..=arc {
                let a = here + (target - here) * k as f32 / arc as f32;
                let d = Vec3::new(a.cos(), a.sin(), 0.0);
                let zk = p.z + (z - p.z) * k as f32 / arc as f32;
                let r = self.surface_distance(x, c, d, zk) + self.radius + 0.03;
                m.push(rng.random_range(0.25..0.4), Vec3::new(c.x, c.y, zk) + d * r);
            }
            let d = Vec3::new(target.cos(), target.sin(), 0.0);
            let s = self.surface_distance(x, c, d, z);
            let base = Vec3::new(c.x, c.y, z);
            let press = base + d * (s + self.radius - depth);
            m.push(rng.random_range(0.3..0.6), press);
            m.push(rng.random_range(0.05..0.2), press);
            m.push(
                rng.random_range(0.3..0.5),
                base + d * (s + self.radius + 0.03),
            );
        }
        m.set_velocities(rng, first_new);
    }

    /// Distance from `c` along horizontal `d` to the outermost particle near that ray at height
    /// `z`.
    fn surface_distance(&self, x: &[Vec3], c: Vec3, d: Vec3, z: f32) -> f32 {
        let band = 1.5 * self.spacing;
        x.iter()
            .filter(|p| (p.z - z).abs() < band)
            .filter_map(|p| {
                let r = Vec3::new(p.x - c.x, p.y - c.y, 0.0);
                let along = r.dot(d);
                let lateral = (r - d * along).length();
                (lateral < band).then_some(along)
            })
            .fold(0.0, f32::max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn a_branch_keeps_the_trunk_up_to_its_waypoint_and_falls_back_when_that_is_too_late() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let start = Vec3::new(0.0, 0.0, 0.02);
        let mut trunk = Motion::new(start, 0.0);
        trunk.push(0.3, start);
        trunk.push(0.9, start + Vec3::new(0.1, 0.0, 0.0));
        trunk.push(2.7, start + Vec3::new(0.2, 0.1, 0.0));
        trunk.set_velocities(&mut rng, 1);
        let branch = |window: (f32, f32)| {
            planning_branch(
                &trunk,
                ObjectKind::Rope,
                start,
                0.0,
                window,
                5.0,
                &mut rng.clone(),
            )
        };
        // The first waypoint after 1.0 s is at 1.2 s.
        let (m, t) = branch((1.0, 3.8)).unwrap();
        assert!((t - 1.2).abs() < 1e-6);
        for k in 0..=12 {
            let s = k as f32 * 0.1;
            assert_eq!(m.at(s), trunk.at(s), "t = {s}");
        }
        assert!(m.at(3.0).distance(trunk.at(3.0)) > 1e-3);
        // The first waypoint after 1.5 s (3.9 s) is too late: the last one before 3.8 s.
        let (_, t) = branch((1.5, 3.8)).unwrap();
        assert!((t - 1.2).abs() < 1e-6);
        // Nothing but the start before 0.2 s.
        assert!(branch((0.1, 0.2)).is_none());
    }
}
