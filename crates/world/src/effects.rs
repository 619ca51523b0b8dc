//! The switchable effects: names, physical parameters, per-object defaults, parsing.
//!
//! Each effect is an `Option` in [`Effects`]: `None` means the effect is off and the world uses
//! its plain behaviour (documented per field). The formulas are in `docs/world.md`; the solver
//! that applies them is in `sim.rs`.

use serde::{Deserialize, Serialize};

use crate::{Error, ObjectKind};

/// The name of a switchable effect (the names used by `--effects`, `truth.json` and the
/// diagnosis).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum EffectKind {
    /// Quadratic, area-weighted, anisotropic air drag.
    Drag,
    /// Spatially varying stiffness.
    StiffnessHeterogeneity,
    /// Strain stiffening in tension, softness in compression.
    NonlinearElasticity,
    /// Bending resistance (curvature energy).
    Bending,
    /// Stick-slip ground friction (static > kinetic coefficient).
    Friction,
    /// Permanent set: rest lengths flow beyond a yield strain.
    Plasticity,
    /// The recorded gripper leads the true one by a fixed lag.
    ActuationDelay,
    /// Held particles attached through a compliant, slipping link.
    GraspSlip,
    /// Non-uniform mass.
    MassDistribution,
    /// Attraction towards a fixed point (out of the diagnosis library).
    Magnet,
    /// The lab turns about a vertical axis and records in its own frame: Coriolis and
    /// centrifugal accelerations (out of the diagnosis library).
    RotatingFrame,
    /// A fan's round air jet across the workspace, acting through the drag law (out of the
    /// diagnosis library).
    Fan,
}

impl EffectKind {
    /// All effects, the nine library effects first.
    pub const ALL: [EffectKind; 12] = [
        EffectKind::Drag,
        EffectKind::StiffnessHeterogeneity,
        EffectKind::NonlinearElasticity,
        EffectKind::Bending,
        EffectKind::Friction,
        EffectKind::Plasticity,
        EffectKind::ActuationDelay,
        EffectKind::GraspSlip,
        EffectKind::MassDistribution,
        EffectKind::Magnet,
        EffectKind::RotatingFrame,
        EffectKind::Fan,
    ];

    /// The effect's name.
    pub fn name(self) -> &'static str {
        match self {
            EffectKind::Drag => "drag",
            EffectKind::StiffnessHeterogeneity => "stiffness-heterogeneity",
            EffectKind::NonlinearElasticity => "nonlinear-elasticity",
            EffectKind::Bending => "bending",
            EffectKind::Friction => "friction",
            EffectKind::Plasticity => "plasticity",
            EffectKind::ActuationDelay => "actuation-delay",
            EffectKind::GraspSlip => "grasp-slip",
            EffectKind::MassDistribution => "mass-distribution",
            EffectKind::Magnet => "magnet",
            EffectKind::RotatingFrame => "rotating-frame",
            EffectKind::Fan => "fan",
        }
    }

    /// Whether the effect belongs to the diagnosis library (all but [`EffectKind::Magnet`],
    /// [`EffectKind::RotatingFrame`] and [`EffectKind::Fan`]).
    pub fn in_library(self) -> bool {
        !matches!(
            self,
            EffectKind::Magnet | EffectKind::RotatingFrame | EffectKind::Fan
        )
    }
}

impl std::fmt::Display for EffectKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for EffectKind {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Error> {
        EffectKind::ALL
            .into_iter()
            .find(|e| e.name() == s)
            .ok_or_else(|| Error::UnknownEffect(s.to_string()))
    }
}

/// Quadratic air drag. Per particle, with relative air velocity `u = v − wind` split into a
/// component across the surface `u⊥` and one along it `u∥`:
/// `F = −½ ρ (C⊥ A⊥ |u⊥| u⊥ + C∥ A∥ |u∥| u∥)`.
/// Sheets: `A⊥` is the particle's share of the deformed area and "across" is the local normal;
/// rods: "along" is the local tangent, `A⊥` = diameter × length share and `A∥` = π × `A⊥`
/// (wetted area); solids: isotropic, with a quarter of the surface share (mean projected area).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Drag {
    /// Air density ρ, kg/m³.
    pub air_density_kg_m3: f32,
    /// Drag coefficient across the surface, C⊥ (dimensionless).
    pub normal_coefficient: f32,
    /// Drag coefficient along the surface, C∥ (dimensionless; skin friction).
    pub tangential_coefficient: f32,
    /// Steady wind velocity, m/s.
    pub wind_m_s: [f32; 3],
}

impl Drag {
    /// The object's default drag in still air (sea-level density, no wind).
    pub fn still_air(object: ObjectKind) -> Self {
        use ObjectKind::*;
        let (normal, tangential) = match object {
            Rope => (1.2, 0.02),
            Paper => (1.2, 0.02),
            Flag => (1.0, 0.05),
            Sloth | Teddy => (1.0, 1.0),
            Duster => (1.2, 0.05),
        };
        Drag {
            air_density_kg_m3: 1.2,
            normal_coefficient: normal,
            tangential_coefficient: tangential,
            wind_m_s: [0.0; 3],
        }
    }
}

/// Spatially varying stiffness: every link and bending stencil is scaled by
/// `contrast^(s − ½)`, where `s ∈ [0, 1]` is the object's stiffness field at the element
/// (e.g. 1 on the duster's stem, 0 on its feathers). Off: uniform stiffness (the geometric
/// mean).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StiffnessHeterogeneity {
    /// Ratio between the stiffest (`s = 1`) and softest (`s = 0`) material, ≥ 1.
    pub contrast: f32,
}

/// Nonlinear elasticity of every link. With strain `ε = (l − L) / L`, the link force is
/// `f = k L (ε + ε³ / (3 ε_s²))` in tension (tangent stiffness `k (1 + ε²/ε_s²)`) and
/// `f = ρ k L ε` in compression. Off: linear, `f = k L ε`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NonlinearElasticity {
    /// Stiffening strain ε_s: at this tensile strain the tangent stiffness has doubled.
    pub stiffening_strain: f32,
    /// Compression ratio ρ ∈ (0, 1]: stiffness in compression relative to small-strain tension.
    pub compression_ratio: f32,
}

/// Bending resistance: a curvature energy on every stencil of three consecutive particles
/// `(i, j, k)` along the object's lines, `E = B |x_i − 2 x_j + x_k|² / (2 h³)` (h: spacing).
/// Off: no bending energy beyond what the links' geometry gives.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bending {
    /// Bending rigidity B: N·m² for rods (rope, feather strands) and for each lattice line of a
    /// solid; N·m (per metre of width) for sheets (paper, flag).
    pub rigidity: f32,
}

/// Stick-slip ground friction: a particle in contact sticks while its tangential slide would be
/// below `μ_s` times its normal penetration correction, otherwise slides with kinetic
/// coefficient `μ_k`. Off: Coulomb friction with `μ_s = μ_k` = the object's base coefficient.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Friction {
    /// Static coefficient μ_s.
    pub static_coefficient: f32,
    /// Kinetic coefficient μ_k (≤ μ_s).
    pub kinetic_coefficient: f32,
}

/// Plasticity of links: where `|ε| > ε_y` the rest length flows towards the length that would
/// put the strain back at the yield surface, `dL/dt = (l / (1 ± ε_y) − L) / τ`, and never leaves
/// `L0 (1 ± ε_max)`. Off: rest lengths never change.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Plasticity {
    /// Yield strain ε_y.
    pub yield_strain: f32,
    /// Flow time constant τ, s.
    pub flow_time_s: f32,
    /// Largest permanent strain ε_max.
    pub max_plastic_strain: f32,
}

/// Actuation delay: the true gripper position at time t is the recorded one at `t − lag`, so the
/// recorded gripper leads the true one. Off: no lag.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ActuationDelay {
    /// Lag, s.
    pub lag_s: f32,
}

/// Grasp slip: each held particle is tied to its anchor on the gripper by a zero-length spring
/// of stiffness `k / n` (n held particles); when the spring force exceeds `F_s / n` the anchor
/// slides towards the particle until it equals `F_s / n` (the object slips in the fingers).
/// Off: held particles follow the gripper rigidly. No influence on pushed objects.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GraspSlip {
    /// Total link stiffness k of the grasp, N/m.
    pub stiffness_n_m: f32,
    /// Total force F_s at which the grasp slips, N.
    pub slip_force_n: f32,
}

/// Non-uniform mass: particle masses are proportional to `contrast^s_m`, where `s_m ∈ [0, 1]`
/// is the object's mass field (e.g. bean-filled body vs fluffy limbs), rescaled to keep the total
/// mass. Off: every particle has the same mass.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MassDistribution {
    /// Ratio between the densest and lightest material, ≥ 1.
    pub contrast: f32,
}

/// Out of the diagnosis library: every particle is pulled towards a fixed point `c` with
/// acceleration `a = a0 r0² / (r0² + d²)` (d: distance to c; a Lorentzian falloff), along
/// `(c − x)/d`. No spring-mass candidate models a field like this.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Magnet {
    /// The attracting point c, m.
    pub center_m: [f32; 3],
    /// Acceleration at the centre a0, m/s².
    pub peak_acceleration_m_s2: f32,
    /// Falloff radius r0, m: at this distance the pull has halved.
    pub falloff_radius_m: f32,
}

/// Out of the diagnosis library: the lab (table, robot and cameras) turns steadily about a
/// vertical axis and everything is recorded in its own frame, a turntable or a turning mobile
/// base. Every free particle feels the Coriolis acceleration `−2 Ω ẑ × v` (sideways to its
/// velocity, doing no work) and the centrifugal `Ω² ρ` (ρ: its horizontal offset from the
/// axis). No candidate models a force that depends on the velocity's direction like this,
/// and until session 57 the diagnosis' probe was a position field only: a second `unknown`
/// test, independent of the probe's form (added after the magnet, whose pull resembles the
/// probe's). Since then the probe has a velocity term shaped after this effect's misses, and
/// [`Fan`] is the test that did not shape it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RotatingFrame {
    /// Angular velocity Ω about +z, rad/s (positive: anticlockwise seen from above).
    pub angular_velocity_rad_s: f32,
    /// Where the axis meets the table, (x, y) in m.
    pub axis_m: [f32; 2],
}

/// Out of the diagnosis library: a fan's round air jet blowing across the workspace. The
/// jet's air velocity at a point a distance `s` downstream of the nozzle (along `d`) and `r`
/// off its axis is `U(s) d exp(−r² / 2R(s)²)`, with the free jet's linear spread
/// `R(s) = R0 + spread · s` and `U(s) = U0 R0 / R(s)` (a round jet's axial momentum kept);
/// nothing upstream of the nozzle. It acts through the world's drag law with the object's
/// drag coefficients ([`Drag`]), as the jet's contribution alone: `F_drag(v − w) − F_drag(v)`,
/// zero outside the jet, so still-air drag stays the `drag` effect's. Added in session 57,
/// its form and parameters written down before any diagnosis of it ran, as a test of
/// `unknown` that did not shape the diagnosis' probe (the magnet and the rotating frame did).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Fan {
    /// Nozzle position p, m.
    pub nozzle_m: [f32; 3],
    /// Jet direction d (unit length).
    pub direction: [f32; 3],
    /// Air speed on the axis at the nozzle U0, m/s.
    pub speed_m_s: f32,
    /// Jet radius at the nozzle R0, m.
    pub radius_m: f32,
    /// Growth of the radius per metre downstream (about 0.1 for a free round jet).
    pub spread: f32,
    /// The air the jet drags the object with (density, coefficients; its wind is unused).
    pub air: Drag,
}

impl Fan {
    /// The jet's air velocity at `x` (m), m/s.
    pub fn wind_at(&self, x: [f32; 3]) -> [f32; 3] {
        let d = self.direction;
        let rel = [
            x[0] - self.nozzle_m[0],
            x[1] - self.nozzle_m[1],
            x[2] - self.nozzle_m[2],
        ];
        let s = rel[0] * d[0] + rel[1] * d[1] + rel[2] * d[2];
        if s <= 0.0 {
            return [0.0; 3];
        }
        let off = [rel[0] - s * d[0], rel[1] - s * d[1], rel[2] - s * d[2]];
        let r2 = off[0] * off[0] + off[1] * off[1] + off[2] * off[2];
        let radius = self.radius_m + self.spread * s;
        let speed = self.speed_m_s * self.radius_m / radius * (-r2 / (2.0 * radius * radius)).exp();
        d.map(|c| c * speed)
    }
}

/// The fan's default air speed at the nozzle, m/s (a desk fan at its highest setting).
const DEFAULT_FAN_SPEED_M_S: f32 = 4.0;

/// The fastest jet the world accepts, m/s.
const MAX_FAN_SPEED_M_S: f32 = 30.0;

/// The frame's default rate, rad/s (about 14 turns a minute: a slow turntable).
const DEFAULT_FRAME_RATE_RAD_S: f32 = 1.5;

/// The default axis, (x, y) in m: beside the workspace rather than through it, so the
/// centrifugal part is not symmetric about the object.
const DEFAULT_FRAME_AXIS_M: [f32; 2] = [-0.3, -0.3];

/// Largest |Ω| the world accepts, rad/s: at 0.35 m from the axis the centrifugal
/// acceleration is then 5 g.
pub const MAX_FRAME_RATE_RAD_S: f32 = 12.0;

/// Which effects are on, with their parameters (`None`: off).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct Effects {
    /// See [`Drag`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drag: Option<Drag>,
    /// See [`StiffnessHeterogeneity`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stiffness_heterogeneity: Option<StiffnessHeterogeneity>,
    /// See [`NonlinearElasticity`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nonlinear_elasticity: Option<NonlinearElasticity>,
    /// See [`Bending`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bending: Option<Bending>,
    /// See [`Friction`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub friction: Option<Friction>,
    /// See [`Plasticity`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plasticity: Option<Plasticity>,
    /// See [`ActuationDelay`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub actuation_delay: Option<ActuationDelay>,
    /// See [`GraspSlip`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grasp_slip: Option<GraspSlip>,
    /// See [`MassDistribution`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mass_distribution: Option<MassDistribution>,
    /// See [`Magnet`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub magnet: Option<Magnet>,
    /// See [`RotatingFrame`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotating_frame: Option<RotatingFrame>,
    /// See [`Fan`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fan: Option<Fan>,
}

/// The effects each object has on by default, and why (see `docs/world.md`).
pub fn default_kinds(object: ObjectKind) -> &'static [EffectKind] {
    use EffectKind::*;
    match object {
        // Ropes keep bends (bending rigidity, kinks) and catch on the table (stick-slip).
        ObjectKind::Rope => &[Bending, Friction, Plasticity],
        // Paper resists bending strongly and is light for its area: air matters.
        ObjectKind::Paper => &[Bending, Drag],
        // A waved flag is dominated by air; the arm lags its commands.
        ObjectKind::Flag => &[Drag, ActuationDelay],
        // Plush: stiffening fabric over soft stuffing, beans in the body, soft limbs, soft grip.
        ObjectKind::Sloth => &[
            NonlinearElasticity,
            MassDistribution,
            StiffnessHeterogeneity,
            GraspSlip,
        ],
        // The paper's heterogeneous object: rigid stem, soft feathers that catch the air.
        ObjectKind::Duster => &[StiffnessHeterogeneity, Drag, Bending],
        // Stiffer plush with a bean-filled bottom, sitting on a grippy table.
        ObjectKind::Teddy => &[NonlinearElasticity, MassDistribution, Friction],
    }
}

impl Effects {
    /// Every effect off.
    pub fn none() -> Self {
        Effects::default()
    }

    /// The object's default effects ([`default_kinds`]) with its default parameters.
    pub fn defaults(object: ObjectKind) -> Self {
        let mut e = Effects::none();
        for &k in default_kinds(object) {
            e.enable(k, object);
        }
        e
    }

    /// Only `kind`, with the object's default parameters for it.
    pub fn only(object: ObjectKind, kind: EffectKind) -> Self {
        let mut e = Effects::none();
        e.enable(kind, object);
        e
    }

    /// The world's default parameters of `kind` on `object` with the strength scaled by `s`
    /// (1: the defaults; the `diagnose-bench` ladder, `docs/gap.md`). Strength per effect: drag
    /// coefficients × s; stiffness and mass contrasts ^ s; stiffening strain ÷ s and
    /// compression ratio ^ s; bending rigidity × s; static-minus-kinetic friction × s; yield
    /// strain and flow time ÷ s; actuation lag × s; grasp stiffness and slip force ÷ s; magnet
    /// acceleration × s; the frame's rate × √s (its centrifugal acceleration × s); the fan's
    /// speed × √s (its force × s). Clamped to the world's ranges.
    pub fn only_scaled(object: ObjectKind, kind: EffectKind, s: f32) -> Self {
        let mut e = Effects::only(object, kind);
        if let Some(d) = &mut e.drag {
            d.normal_coefficient *= s;
            d.tangential_coefficient *= s;
        }
        if let Some(h) = &mut e.stiffness_heterogeneity {
            h.contrast = h.contrast.powf(s).min(1e8);
        }
        if let Some(n) = &mut e.nonlinear_elasticity {
            n.stiffening_strain /= s;
            n.compression_ratio = n.compression_ratio.powf(s).max(1e-3);
        }
        if let Some(b) = &mut e.bending {
            b.rigidity *= s;
        }
        if let Some(f) = &mut e.friction {
            f.static_coefficient =
                f.kinetic_coefficient + s * (f.static_coefficient - f.kinetic_coefficient);
        }
        if let Some(p) = &mut e.plasticity {
            p.yield_strain /= s;
            p.flow_time_s /= s;
        }
        if let Some(a) = &mut e.actuation_delay {
            a.lag_s = (a.lag_s * s).min(2.0);
        }
        if let Some(g) = &mut e.grasp_slip {
            g.stiffness_n_m /= s;
            g.slip_force_n /= s;
        }
        if let Some(m) = &mut e.mass_distribution {
            m.contrast = m.contrast.powf(s).min(1e4);
        }
        if let Some(m) = &mut e.magnet {
            m.peak_acceleration_m_s2 = (m.peak_acceleration_m_s2 * s).min(100.0);
        }
        if let Some(r) = &mut e.rotating_frame {
            r.angular_velocity_rad_s = (r.angular_velocity_rad_s * s.max(0.0).sqrt())
                .clamp(-MAX_FRAME_RATE_RAD_S, MAX_FRAME_RATE_RAD_S);
        }
        if let Some(f) = &mut e.fan {
            f.speed_m_s = (f.speed_m_s * s.max(0.0).sqrt()).min(MAX_FAN_SPEED_M_S);
        }
        e
    }

    /// Parses `none`, `default`, or a comma-separated list of effect names (each switched on
    /// with the object's default parameters).
    ///
    /// ```
    /// use world::{EffectKind, Effects, ObjectKind};
    /// let e = Effects::parse("drag,bending", ObjectKind::Flag)?;
    /// assert_eq!(e.enabled(), vec![EffectKind::Drag, EffectKind::Bending]);
    /// assert!(Effects::parse("wind", ObjectKind::Flag).is_err());
    /// # Ok::<(), world::Error>(())
    /// ```
    pub fn parse(spec: &str, object: ObjectKind) -> Result<Self, Error> {
        match spec.trim() {
            "none" | "" => Ok(Effects::none()),
            "default" => Ok(Effects::defaults(object)),
            list => {
                let mut e = Effects::none();
                for name in list.split(',') {
                    e.enable(name.trim().parse()?, object);
                }
                Ok(e)
            }
        }
    }

    /// Switches `kind` on with the object's default parameters.
    pub fn enable(&mut self, kind: EffectKind, object: ObjectKind) {
        use ObjectKind::*;
        let o = object;
        match kind {
            EffectKind::Drag => self.drag = Some(Drag::still_air(o)),
            EffectKind::StiffnessHeterogeneity => {
                let contrast = match o {
                    Rope | Flag | Teddy => 4.0,
                    Paper => 3.0,
                    Sloth => 8.0,
                    Duster => 1.0e4,
                };
                self.stiffness_heterogeneity = Some(StiffnessHeterogeneity { contrast });
            }
            EffectKind::NonlinearElasticity => {
                let (stiffening_strain, compression_ratio) = match o {
                    Rope => (0.05, 0.1),
                    Paper => (0.005, 0.05),
                    Flag => (0.02, 0.05),
                    Sloth => (0.1, 0.3),
                    Duster => (0.05, 0.2),
                    Teddy => (0.08, 0.5),
                };
                self.nonlinear_elasticity = Some(NonlinearElasticity {
                    stiffening_strain,
                    compression_ratio,
                });
            }
            EffectKind::Bending => {
                let rigidity = match o {
                    Rope => 2.0e-3,
                    Paper => 3.0e-4,
                    Flag => 2.0e-5,
                    Sloth => 5.0e-5,
                    Duster => 2.0e-5,
                    Teddy => 2.0e-4,
                };
                self.bending = Some(Bending { rigidity });
            }
            EffectKind::Friction => {
                let (s, k) = match o {
                    Rope => (0.9, 0.45),
                    Teddy => (1.0, 0.5),
                    _ => (0.8, 0.4),
                };
                self.friction = Some(Friction {
                    static_coefficient: s,
                    kinetic_coefficient: k,
                });
            }
            EffectKind::Plasticity => {
                let (yield_strain, flow_time_s, max_plastic_strain) = match o {
                    Rope => (0.05, 0.3, 0.5),
                    Paper => (0.01, 0.2, 0.2),
                    Flag => (0.02, 0.3, 0.3),
                    Sloth => (0.1, 0.5, 0.4),
                    Duster => (0.05, 0.3, 0.3),
                    Teddy => (0.08, 0.5, 0.3),
                };
                self.plasticity = Some(Plasticity {
                    yield_strain,
                    flow_time_s,
                    max_plastic_strain,
                });
            }
            EffectKind::ActuationDelay => {
                self.actuation_delay = Some(ActuationDelay { lag_s: 0.2 });
            }
            EffectKind::GraspSlip => {
                let (stiffness_n_m, slip_force_n) = match o {
                    Rope => (200.0, 3.0),
                    Paper => (50.0, 0.5),
                    Flag => (300.0, 4.0),
                    Sloth => (150.0, 5.0),
                    Duster => (3000.0, 20.0),
                    Teddy => (150.0, 5.0),
                };
                self.grasp_slip = Some(GraspSlip {
                    stiffness_n_m,
                    slip_force_n,
                });
            }
            EffectKind::MassDistribution => {
                let contrast = match o {
                    Rope => 2.0,
                    Paper => 1.5,
                    Flag | Teddy => 3.0,
                    Sloth => 4.0,
                    Duster => 8.0,
                };
                self.mass_distribution = Some(MassDistribution { contrast });
            }
            EffectKind::Magnet => {
                let center_m = match o {
                    Rope => [0.25, 0.2, 0.0],
                    Paper => [0.0, 0.15, 0.3],
                    Flag => [0.0, 0.2, 0.35],
                    Sloth => [0.15, 0.15, 0.1],
                    Duster => [0.15, 0.0, 0.4],
                    Teddy => [0.0, 0.2, 0.1],
                };
                self.magnet = Some(Magnet {
                    center_m,
                    peak_acceleration_m_s2: 4.0,
                    falloff_radius_m: 0.12,
                });
            }
            EffectKind::RotatingFrame => {
                self.rotating_frame = Some(RotatingFrame {
                    angular_velocity_rad_s: DEFAULT_FRAME_RATE_RAD_S,
                    axis_m: DEFAULT_FRAME_AXIS_M,
                });
            }
            EffectKind::Fan => {
                // Beside the workspace, blowing along +x at the height the object spends
                // most time at (the magnet centres' heights; the rope's just above the table).
                let height = match o {
                    Rope => 0.03,
                    Paper => 0.3,
                    Flag => 0.35,
                    Sloth | Teddy => 0.1,
                    Duster => 0.4,
                };
                self.fan = Some(Fan {
                    nozzle_m: [-0.6, 0.0, height],
                    direction: [1.0, 0.0, 0.0],
                    speed_m_s: DEFAULT_FAN_SPEED_M_S,
                    radius_m: 0.08,
                    spread: 0.1,
                    air: Drag::still_air(o),
                });
            }
        }
    }

    /// Switches `kind` off.
    pub fn disable(&mut self, kind: EffectKind) {
        match kind {
            EffectKind::Drag => self.drag = None,
            EffectKind::StiffnessHeterogeneity => self.stiffness_heterogeneity = None,
            EffectKind::NonlinearElasticity => self.nonlinear_elasticity = None,
            EffectKind::Bending => self.bending = None,
            EffectKind::Friction => self.friction = None,
            EffectKind::Plasticity => self.plasticity = None,
            EffectKind::ActuationDelay => self.actuation_delay = None,
            EffectKind::GraspSlip => self.grasp_slip = None,
            EffectKind::MassDistribution => self.mass_distribution = None,
            EffectKind::Magnet => self.magnet = None,
            EffectKind::RotatingFrame => self.rotating_frame = None,
            EffectKind::Fan => self.fan = None,
        }
    }

    /// Whether `kind` is on.
    pub fn is_enabled(&self, kind: EffectKind) -> bool {
        match kind {
            EffectKind::Drag => self.drag.is_some(),
            EffectKind::StiffnessHeterogeneity => self.stiffness_heterogeneity.is_some(),
            EffectKind::NonlinearElasticity => self.nonlinear_elasticity.is_some(),
            EffectKind::Bending => self.bending.is_some(),
            EffectKind::Friction => self.friction.is_some(),
            EffectKind::Plasticity => self.plasticity.is_some(),
            EffectKind::ActuationDelay => self.actuation_delay.is_some(),
            EffectKind::GraspSlip => self.grasp_slip.is_some(),
            EffectKind::MassDistribution => self.mass_distribution.is_some(),
            EffectKind::Magnet => self.magnet.is_some(),
            EffectKind::RotatingFrame => self.rotating_frame.is_some(),
            EffectKind::Fan => self.fan.is_some(),
        }
    }

    /// The effects that are on, in [`EffectKind::ALL`] order.
    pub fn enabled(&self) -> Vec<EffectKind> {
        EffectKind::ALL
            .into_iter()
            .filter(|k| self.is_enabled(*k))
            .collect()
    }

    /// Checks every parameter of the effects that are on against its physical range.
    pub fn validate(&self) -> Result<(), Error> {
        fn check(effect: &'static str, ok: bool, message: &str) -> Result<(), Error> {
            if ok {
                Ok(())
            } else {
                Err(Error::EffectParameter {
                    effect,
                    message: message.to_string(),
                })
            }
        }
        let pos = |v: f32| v.is_finite() && v > 0.0;
        let nonneg = |v: f32| v.is_finite() && v >= 0.0;
        if let Some(d) = &self.drag {
            check(
                "drag",
                pos(d.air_density_kg_m3),
                "air density must be > 0 kg/m³",
            )?;
            check(
                "drag",
                nonneg(d.normal_coefficient) && nonneg(d.tangential_coefficient),
                "drag coefficients must be finite and >= 0",
            )?;
            check(
                "drag",
                d.wind_m_s.iter().all(|w| w.is_finite()),
                "wind must be finite",
            )?;
        }
        if let Some(h) = &self.stiffness_heterogeneity {
            check(
                "stiffness-heterogeneity",
                h.contrast.is_finite() && h.contrast >= 1.0 && h.contrast <= 1e8,
                "contrast must be in [1, 1e8]",
            )?;
        }
        if let Some(n) = &self.nonlinear_elasticity {
            check(
                "nonlinear-elasticity",
                pos(n.stiffening_strain),
                "stiffening strain must be > 0",
            )?;
            check(
                "nonlinear-elasticity",
                pos(n.compression_ratio) && n.compression_ratio <= 1.0,
                "compression ratio must be in (0, 1]",
            )?;
        }
        if let Some(b) = &self.bending {
            check("bending", pos(b.rigidity), "rigidity must be > 0")?;
        }
        if let Some(f) = &self.friction {
            check(
                "friction",
                nonneg(f.kinetic_coefficient) && f.static_coefficient >= f.kinetic_coefficient,
                "coefficients must satisfy 0 <= kinetic <= static",
            )?;
            check(
                "friction",
                f.static_coefficient.is_finite(),
                "static coefficient must be finite",
            )?;
        }
        if let Some(p) = &self.plasticity {
            check(
                "plasticity",
                pos(p.yield_strain),
                "yield strain must be > 0",
            )?;
            check("plasticity", pos(p.flow_time_s), "flow time must be > 0 s")?;
            check(
                "plasticity",
                pos(p.max_plastic_strain) && p.max_plastic_strain < 0.9,
                "max plastic strain must be in (0, 0.9)",
            )?;
        }
        if let Some(d) = &self.actuation_delay {
            check(
                "actuation-delay",
                nonneg(d.lag_s) && d.lag_s <= 2.0,
                "lag must be in [0, 2] s",
            )?;
        }
        if let Some(g) = &self.grasp_slip {
            check(
                "grasp-slip",
                pos(g.stiffness_n_m),
                "stiffness must be > 0 N/m",
            )?;
            check(
                "grasp-slip",
                pos(g.slip_force_n),
                "slip force must be > 0 N",
            )?;
        }
        if let Some(m) = &self.mass_distribution {
            check(
                "mass-distribution",
                m.contrast.is_finite() && m.contrast >= 1.0 && m.contrast <= 1e4,
                "contrast must be in [1, 1e4]",
            )?;
        }
        if let Some(m) = &self.magnet {
            check(
                "magnet",
                m.center_m.iter().all(|c| c.is_finite()),
                "centre must be finite",
            )?;
            check(
                "magnet",
                nonneg(m.peak_acceleration_m_s2) && m.peak_acceleration_m_s2 <= 100.0,
                "peak acceleration must be in [0, 100] m/s²",
            )?;
            check(
                "magnet",
                pos(m.falloff_radius_m),
                "falloff radius must be > 0 m",
            )?;
        }
        if let Some(r) = &self.rotating_frame {
            check(
                "rotating-frame",
                r.angular_velocity_rad_s.is_finite()
                    && r.angular_velocity_rad_s.abs() <= MAX_FRAME_RATE_RAD_S,
                "angular velocity must be in [-12, 12] rad/s",
            )?;
            check(
                "rotating-frame",
                r.axis_m.iter().all(|c| c.is_finite()),
                "axis must be finite",
            )?;
        }
        if let Some(f) = &self.fan {
            let d = f.direction;
            let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            check(
                "fan",
                f.nozzle_m.iter().all(|c| c.is_finite()),
                "nozzle must be finite",
            )?;
            check(
                "fan",
                (norm - 1.0).abs() < 1e-3,
                "direction must be a unit vector",
            )?;
            check(
                "fan",
                nonneg(f.speed_m_s) && f.speed_m_s <= MAX_FAN_SPEED_M_S,
                "speed must be in [0, 30] m/s",
            )?;
            check(
                "fan",
                pos(f.radius_m) && nonneg(f.spread),
                "radius must be > 0 m and spread >= 0",
            )?;
            check(
                "fan",
                pos(f.air.air_density_kg_m3)
                    && nonneg(f.air.normal_coefficient)
                    && nonneg(f.air.tangential_coefficient),
                "air density must be > 0 and drag coefficients >= 0",
            )?;
        }
        Ok(())
    }
}
