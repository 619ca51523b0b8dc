//! Building the fine particle model of each object: geometry, links, bending stencils, drag
//! shapes, material fields, colours and the grasp region.

mod objects;
mod shapes;

use glam::Vec3;
use rand::Rng;

pub(crate) use objects::{blueprint, centroid as centroid_of, place};

/// How the drag law sees a particle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum DragShape {
    /// No drag (interior of a solid).
    None,
    /// Part of a sheet: area and normal come from the deformed triangles around it.
    Sheet,
    /// Part of a rod whose local tangent is `x[b] − x[a]`; `area` = diameter × length share, m².
    Rod { a: u32, b: u32, area: f32 },
    /// Surface particle of a solid: isotropic drag on `area` m² (projected share).
    Blob { area: f32 },
}

/// A link between two particles (rest length from the rest configuration).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct LinkSpec {
    pub i: u32,
    pub j: u32,
    /// Axial rigidity EA of the link, N: its stiffness is EA / L.
    pub ea: f32,
}

/// A bending stencil (i, j, k) with j in the middle; compliance = `scale` / rigidity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct StencilSpec {
    pub i: u32,
    pub j: u32,
    pub k: u32,
    /// h³ for rods and solids, h² for sheets (whose rigidity is per metre of width).
    pub scale: f32,
}

/// Fine resolution of the model.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Resolution {
    /// The full-size fine model (several times more particles than tracked).
    Full,
    /// A coarser model (≈ 2.5× fewer particles, half the substeps) for fixtures and tests.
    Coarse,
}

impl Resolution {
    /// Multiplier on the fine particle spacing.
    pub(crate) fn spacing_factor(self) -> f32 {
        match self {
            Resolution::Full => 1.0,
            Resolution::Coarse => 1.4,
        }
    }
}

/// The fine model of one object in its rest configuration.
#[derive(Clone, Debug, Default)]
pub(crate) struct Blueprint {
    /// Rest positions, m (stress-free).
    pub rest: Vec<Vec3>,
    /// Total mass, kg.
    pub total_mass: f32,
    /// Stiffness field s ∈ [0, 1] per particle (used by stiffness-heterogeneity).
    pub stiff_field: Vec<f32>,
    /// Mass field s_m ∈ [0, 1] per particle (used by mass-distribution).
    pub mass_field: Vec<f32>,
    pub links: Vec<LinkSpec>,
    pub stencils: Vec<StencilSpec>,
    /// Sheet triangles (for drag normals), counter-clockwise.
    pub faces: Vec<[u32; 3]>,
    pub drag: Vec<DragShape>,
    /// Whether a tracker could see the particle (surface of the object).
    pub surface: Vec<bool>,
    pub colors: Vec<[f32; 3]>,
    /// Particles grasped by the gripper (empty for pushed objects).
    pub held: Vec<u32>,
    /// Where the gripper is in the rest configuration, m.
    pub grasp_point: Vec3,
    /// Contact radius of particles against the ground, m.
    pub contact_radius: f32,
    /// Ground friction coefficient when the friction effect is off.
    pub base_friction: f32,
    /// Kelvin–Voigt retardation time of the links, s (material damping).
    pub damping_time_s: f32,
    /// XPBD substeps per 0.1 s model step.
    pub substeps: usize,
    /// The first `stiff_links` links form a stiff group...
    pub stiff_links: usize,
    /// ...swept this many extra times per substep (a rigid part needs more Gauss–Seidel sweeps).
    pub stiff_iterations: usize,
    /// Gauss–Seidel sweeps over all links per substep (0 reads as 1, the world's default;
    /// [`crate::GenConfig::link_sweeps`]).
    pub link_sweeps: usize,
    /// Nominal fine spacing, m.
    pub spacing: f32,
}

impl Blueprint {
    /// Adds a particle; returns its index.
    pub(crate) fn add(&mut self, p: Vec3, surface: bool, drag: DragShape, color: [f32; 3]) -> u32 {
        self.rest.push(p);
        self.surface.push(surface);
        self.drag.push(drag);
        self.colors.push(color);
        self.stiff_field.push(0.5);
        self.mass_field.push(0.5);
        (self.rest.len() - 1) as u32
    }

    pub(crate) fn link(&mut self, i: u32, j: u32, ea: f32) {
        self.links.push(LinkSpec { i, j, ea });
    }

    pub(crate) fn stencil(&mut self, i: u32, j: u32, k: u32, scale: f32) {
        self.stencils.push(StencilSpec { i, j, k, scale });
    }

    pub(crate) fn len(&self) -> usize {
        self.rest.len()
    }
}

/// A smooth random field over `points`, scaled to [0, 1]: a sum of four plane waves of the given
/// wavelength (m) in random directions.
pub(crate) fn smooth_field(points: &[Vec3], wavelength: f32, rng: &mut impl Rng) -> Vec<f32> {
    let k = std::f32::consts::TAU / wavelength;
    let waves: Vec<(Vec3, f32)> = (0..4)
        .map(|_| {
            let dir = random_unit(rng);
            (dir * k, rng.random_range(0.0..std::f32::consts::TAU))
        })
        .collect();
    let raw: Vec<f32> = points
        .iter()
        .map(|p| waves.iter().map(|(kv, ph)| (kv.dot(*p) + ph).cos()).sum())
        .collect();
    let lo = raw.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = raw.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let span = (hi - lo).max(1e-6);
    raw.iter().map(|r| (r - lo) / span).collect()
}

/// A uniformly distributed unit vector.
pub(crate) fn random_unit(rng: &mut impl Rng) -> Vec3 {
    loop {
        let v = Vec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let l = v.length();
        if (1e-3..=1.0).contains(&l) {
            return v / l;
        }
    }
}

/// `base` with a small random brightness variation (a textured look for splatting).
pub(crate) fn jitter(base: [f32; 3], amount: f32, rng: &mut impl Rng) -> [f32; 3] {
    let s = 1.0 + rng.random_range(-amount..amount);
    base.map(|c| (c * s).clamp(0.0, 1.0))
}
