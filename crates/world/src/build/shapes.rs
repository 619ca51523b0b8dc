//! Generic fine discretisations: a tube (rope, duster stem), a sheet (paper, flag) and a cubic
//! lattice filling a solid (toys).

use std::collections::HashMap;

use glam::{IVec3, Vec3};

use super::{Blueprint, DragShape};

/// Parameters of a tube: a centre chain with a ring of surface particles around every node.
pub(crate) struct TubeSpec {
    /// Centre of the first node, m.
    pub origin: Vec3,
    /// Unit axis direction.
    pub axis: Vec3,
    /// Number of centre nodes.
    pub nodes: usize,
    /// Node spacing, m.
    pub spacing: f32,
    /// Tube radius, m.
    pub radius: f32,
    /// Surface particles per ring.
    pub ring: usize,
    /// EA of the centre chain links, N (carries tension).
    pub ea_core: f32,
    /// EA of radial and circumferential links, N (keeps the cross-section round).
    pub ea_section: f32,
    /// EA of the axial and diagonal surface links, N (their softness sets the base bending
    /// rigidity ≈ 2 · ea_surface · ring · radius² / 2).
    pub ea_surface: f32,
    /// Extra spans (in nodes, each ≥ 2) of long surface and centre links with `ea_surface`: they
    /// let a stiff tube's bending resistance reach far in one Gauss–Seidel sweep.
    pub long_spans: &'static [usize],
}

/// Indices of a built tube.
pub(crate) struct Tube {
    pub centre: Vec<u32>,
}

/// Adds a tube; colours come from `color(node, ring_index)`.
pub(crate) fn add_tube(
    bp: &mut Blueprint,
    spec: &TubeSpec,
    mut color: impl FnMut(usize, usize) -> [f32; 3],
) -> Tube {
    let axis = spec.axis.normalize();
    let u = axis.any_orthonormal_vector();
    let w = axis.cross(u);
    let (n, k, h) = (spec.nodes, spec.ring, spec.spacing);
    // Drag: the tube's projected area (2 r h per node) shared by the node's particles.
    let area = 2.0 * spec.radius * h / (k + 1) as f32;
    let mut centre = Vec::with_capacity(n);
    let mut rings = Vec::with_capacity(n);
    for a in 0..n {
        let c = spec.origin + axis * (a as f32 * h);
        let (prev, next) = (a.saturating_sub(1), (a + 1).min(n - 1));
        // Tangent neighbours are centre indices; they are assigned once all exist (below).
        let rod = DragShape::Rod {
            a: prev as u32,
            b: next as u32,
            area,
        };
        centre.push(bp.add(c, false, rod, color(a, usize::MAX)));
        // Alternate rings are rotated by half a step so surface particles interleave.
        let twist = if a % 2 == 1 {
            std::f32::consts::PI / k as f32
        } else {
            0.0
        };
        let ring: Vec<u32> = (0..k)
            .map(|j| {
                let t = twist + std::f32::consts::TAU * j as f32 / k as f32;
                let p = c + spec.radius * (t.cos() * u + t.sin() * w);
                bp.add(p, true, rod, color(a, j))
            })
            .collect();
        rings.push(ring);
    }
    // Rod tangents were given as node numbers: map them to particle indices.
    for ring_or_centre in centre.iter().chain(rings.iter().flatten()) {
        if let DragShape::Rod { a, b, area } = bp.drag[*ring_or_centre as usize] {
            bp.drag[*ring_or_centre as usize] = DragShape::Rod {
                a: centre[a as usize],
                b: centre[b as usize],
                area,
            };
        }
    }
    for a in 0..n {
        let c = centre[a];
        for j in 0..k {
            bp.link(c, rings[a][j], spec.ea_section);
            bp.link(rings[a][j], rings[a][(j + 1) % k], spec.ea_section);
        }
        if a + 1 < n {
            bp.link(c, centre[a + 1], spec.ea_core);
            for j in 0..k {
                // With the half-step twist, ring a's particle j sits between particles j and
                // j−1 (odd a: j and j+1) of the next ring: link both.
                let other = if a % 2 == 0 {
                    (j + k - 1) % k
                } else {
                    (j + 1) % k
                };
                bp.link(rings[a][j], rings[a + 1][j], spec.ea_surface);
                bp.link(rings[a][j], rings[a + 1][other], spec.ea_surface);
            }
        }
    }
    for &span in spec.long_spans {
        for a in 0..n.saturating_sub(span) {
            bp.link(centre[a], centre[a + span], spec.ea_surface);
            for j in 0..k {
                // Same angle when the span is even; otherwise the nearer of the two neighbours.
                let other = if span % 2 == 1 && a % 2 == 1 {
                    (j + 1) % k
                } else {
                    j
                };
                bp.link(rings[a][j], rings[a + span][other], spec.ea_surface);
            }
        }
    }
    Tube { centre }
}

/// Adds the centre-line bending stencils of a tube (scale h³).
pub(crate) fn tube_stencils(bp: &mut Blueprint, tube: &Tube, spacing: f32) {
    for a in 1..tube.centre.len().saturating_sub(1) {
        bp.stencil(
            tube.centre[a - 1],
            tube.centre[a],
            tube.centre[a + 1],
            spacing.powi(3),
        );
    }
}

/// A rectangular sheet of `nu × nv` nodes spaced `h` from `origin` along unit `du`, `dv`.
pub(crate) struct SheetSpec {
    pub origin: Vec3,
    pub du: Vec3,
    pub dv: Vec3,
    pub nu: usize,
    pub nv: usize,
    pub spacing: f32,
    /// EA of the structural (grid) links, N = 2-D stretch modulus × spacing.
    pub ea_struct: f32,
    /// EA of the shear (diagonal) links, N.
    pub ea_shear: f32,
}

/// Adds a sheet; returns node indices `[v][u]`. Bending stencils along rows and columns have
/// scale h² (sheet rigidity is per metre of width, and each line carries a strip of width h).
pub(crate) fn add_sheet(
    bp: &mut Blueprint,
    spec: &SheetSpec,
    mut color: impl FnMut(usize, usize) -> [f32; 3],
) -> Vec<Vec<u32>> {
    let h = spec.spacing;
    let grid: Vec<Vec<u32>> = (0..spec.nv)
        .map(|v| {
            (0..spec.nu)
                .map(|u| {
                    let p = spec.origin + spec.du * (u as f32 * h) + spec.dv * (v as f32 * h);
                    bp.add(p, true, DragShape::Sheet, color(u, v))
                })
                .collect()
        })
        .collect();
    for v in 0..spec.nv {
        for u in 0..spec.nu {
            let a = grid[v][u];
            if u + 1 < spec.nu {
                bp.link(a, grid[v][u + 1], spec.ea_struct);
            }
            if v + 1 < spec.nv {
                bp.link(a, grid[v + 1][u], spec.ea_struct);
            }
            if u + 1 < spec.nu && v + 1 < spec.nv {
                let (b, c, d) = (grid[v][u + 1], grid[v + 1][u], grid[v + 1][u + 1]);
                bp.link(a, d, spec.ea_shear);
                bp.link(b, c, spec.ea_shear);
                bp.faces.push([a, b, d]);
                bp.faces.push([a, d, c]);
            }
            if u >= 1 && u + 1 < spec.nu {
                bp.stencil(grid[v][u - 1], a, grid[v][u + 1], h * h);
            }
            if v >= 1 && v + 1 < spec.nv {
                bp.stencil(grid[v - 1][u], a, grid[v + 1][u], h * h);
            }
        }
    }
    grid
}

/// Fills the solid `{p : inside(p)}` within `[lo, hi]` with a cubic lattice of spacing `h`.
/// Every particle is linked to its 26 neighbours (EA each); bending stencils run along the three
/// lattice axes; particles missing a face neighbour are surface (tracked, with drag area h²/4,
/// the mean projected share of a convex surface element).
pub(crate) fn add_lattice(
    bp: &mut Blueprint,
    lo: Vec3,
    hi: Vec3,
    h: f32,
    ea: f32,
    inside: impl Fn(Vec3) -> bool,
    mut color: impl FnMut(Vec3) -> [f32; 3],
) -> Vec<u32> {
    let dims = ((hi - lo) / h).ceil().as_ivec3() + IVec3::ONE;
    let mut cells: HashMap<IVec3, u32> = HashMap::new();
    let mut order = Vec::new();
    for z in 0..dims.z {
        for y in 0..dims.y {
            for x in 0..dims.x {
                let c = IVec3::new(x, y, z);
                let p = lo + c.as_vec3() * h;
                if inside(p) {
                    order.push((c, p));
                }
            }
        }
    }
    let faces = [
        IVec3::X,
        IVec3::NEG_X,
        IVec3::Y,
        IVec3::NEG_Y,
        IVec3::Z,
        IVec3::NEG_Z,
    ];
    let present: std::collections::HashSet<IVec3> = order.iter().map(|(c, _)| *c).collect();
    let mut ids = Vec::with_capacity(order.len());
    for (c, p) in &order {
        let surface = faces.iter().any(|f| !present.contains(&(*c + *f)));
        let drag = if surface {
            DragShape::Blob { area: h * h / 4.0 }
        } else {
            DragShape::None
        };
        let id = bp.add(*p, surface, drag, color(*p));
        cells.insert(*c, id);
        ids.push(id);
    }
    // The 13 neighbour offsets of one half-space, so each pair is linked once.
    let mut half = Vec::new();
    for dz in -1..=1 {
        for dy in -1..=1 {
            for dx in -1..=1 {
                let d = IVec3::new(dx, dy, dz);
                if (dz, dy, dx) > (0, 0, 0) {
                    half.push(d);
                }
            }
        }
    }
    for (c, _) in &order {
        let a = cells[c];
        for d in &half {
            if let Some(&b) = cells.get(&(*c + *d)) {
                bp.link(a, b, ea);
            }
        }
        for axis in [IVec3::X, IVec3::Y, IVec3::Z] {
            if let (Some(&i), Some(&k)) = (cells.get(&(*c - axis)), cells.get(&(*c + axis))) {
                bp.stencil(i, a, k, h * h * h);
            }
        }
    }
    ids
}
