//! The reference-world solver: extended position-based dynamics (XPBD) with small substeps and
//! one Gauss–Seidel sweep per substep. Deliberately unlike the backbone (explicit springs with
//! penalty contact): constraints are projected, contact and friction act on positions, the grasp
//! is an attachment, and all material effects enter as constraint compliance or rest-length
//! changes.

use glam::Vec3;

use crate::build::{Blueprint, DragShape};
use crate::effects::{Drag, Effects, Fan, Magnet, NonlinearElasticity, Plasticity, RotatingFrame};

#[derive(Clone, Copy, Debug)]
struct Link {
    i: u32,
    j: u32,
    rest: f32,
    rest0: f32,
    /// Compliance at zero strain, m/N (= L / EA).
    compliance: f32,
    /// Accumulated Lagrange multiplier of the current substep.
    lambda: f32,
}

#[derive(Clone, Copy, Debug)]
struct Stencil {
    i: u32,
    j: u32,
    k: u32,
    compliance: f32,
}

/// A particle tied to a gripper.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Attachment {
    pub particle: u32,
    pub gripper: u32,
    /// Anchor position relative to the gripper, m.
    pub offset: Vec3,
}

/// How attachments act.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum GraspMode {
    /// Held particles follow the gripper exactly.
    Kinematic,
    /// Zero-length spring of compliance `compliance` (m/N) per particle, slipping above
    /// `max_force` N per particle.
    Compliant { compliance: f32, max_force: f32 },
}

/// The full simulation state of one object.
#[derive(Clone, Debug)]
pub(crate) struct Sim {
    pub x: Vec<Vec3>,
    pub v: Vec<Vec3>,
    x0: Vec<Vec3>,
    pub mass: Vec<f32>,
    inv_mass: Vec<f32>,
    /// Inverse mass used by the solver (0 for kinematically held particles).
    w: Vec<f32>,
    /// Links in Gauss–Seidel order: the stiff group `[0, stiff_end)` first (swept
    /// `stiff_iterations` extra times per substep), each group sorted by colour so consecutive
    /// links share no particle (the CPU can overlap them).
    links: Vec<Link>,
    stiff_end: usize,
    stiff_iterations: usize,
    /// Sweeps over all links per substep (≥ 1).
    link_sweeps: usize,
    stencils: Vec<Stencil>,
    faces: Vec<[u32; 3]>,
    drag_shape: Vec<DragShape>,
    area_vec: Vec<Vec3>,
    pub gravity: Vec3,
    pub ground: Option<f32>,
    contact: f32,
    mu_static: f32,
    mu_kinetic: f32,
    damping_time: f32,
    nonlinear: Option<NonlinearElasticity>,
    plastic: Option<Plasticity>,
    drag: Option<Drag>,
    magnet: Option<Magnet>,
    frame: Option<RotatingFrame>,
    fan: Option<Fan>,
    attachments: Vec<Attachment>,
    grasp: GraspMode,
    /// Pushing-sphere radius when grippers poke instead of grasp, m.
    push_radius: Option<f32>,
    /// Extra velocity damping rate, 1/s (only while settling before a recording).
    pub settle_rate: f32,
    /// Box obstacles (none in generated datasets).
    pub obstacles: Vec<crate::obstacles::BoxObstacle>,
}

impl Sim {
    /// A model of `bp` with `effects`, at positions `x` and at rest.
    pub(crate) fn new(bp: &Blueprint, effects: &Effects, x: Vec<Vec3>, push: Option<f32>) -> Sim {
        let n = bp.len();
        let mass: Vec<f32> = match &effects.mass_distribution {
            Some(m) => {
                let raw: Vec<f32> = bp.mass_field.iter().map(|s| m.contrast.powf(*s)).collect();
                let sum: f32 = raw.iter().sum();
                raw.iter().map(|r| bp.total_mass * r / sum).collect()
            }
            None => vec![bp.total_mass / n as f32; n],
        };
        let inv_mass: Vec<f32> = mass.iter().map(|m| 1.0 / m).collect();
        // Heterogeneity scales stiffness by contrast^(s − ½): compliance by its inverse.
        let stiff = |a: &[u32]| -> f32 {
            match &effects.stiffness_heterogeneity {
                Some(h) => {
                    let s =
                        a.iter().map(|i| bp.stiff_field[*i as usize]).sum::<f32>() / a.len() as f32;
                    h.contrast.powf(s - 0.5)
                }
                None => 1.0,
            }
        };
        let make = |l: &crate::build::LinkSpec| {
            let rest = bp.rest[l.i as usize].distance(bp.rest[l.j as usize]);
            Link {
                i: l.i,
                j: l.j,
                rest,
                rest0: rest,
                compliance: rest / (l.ea * stiff(&[l.i, l.j])),
                lambda: 0.0,
            }
        };
        let stiff_end = bp.stiff_links.min(bp.links.len());
        let mut links = Vec::with_capacity(bp.links.len());
        for group in [&bp.links[..stiff_end], &bp.links[stiff_end..]] {
            let order = color_order(group.iter().map(|l| [l.i, l.j]), n);
            links.extend(order.iter().map(|&k| make(&group[k])));
        }
        let stencils = match &effects.bending {
            Some(b) => color_order(bp.stencils.iter().map(|s| [s.i, s.j, s.k]), n)
                .into_iter()
                .map(|k| &bp.stencils[k])
                .map(|s| Stencil {
                    i: s.i,
                    j: s.j,
                    k: s.k,
                    compliance: s.scale / (b.rigidity * stiff(&[s.i, s.j, s.k])),
                })
                .collect(),
            None => Vec::new(),
        };
        let (mu_static, mu_kinetic) = match &effects.friction {
            Some(f) => (f.static_coefficient, f.kinetic_coefficient),
            None => (bp.base_friction, bp.base_friction),
        };
        Sim {
            v: vec![Vec3::ZERO; n],
            x0: x.clone(),
            x,
            w: inv_mass.clone(),
            mass,
            inv_mass,
            links,
            stiff_end,
            stiff_iterations: bp.stiff_iterations,
            link_sweeps: bp.link_sweeps.max(1),
            stencils,
            faces: bp.faces.clone(),
            drag_shape: bp.drag.clone(),
            area_vec: vec![Vec3::ZERO; n],
            gravity: Vec3::new(0.0, 0.0, -9.81),
            ground: Some(0.0),
            contact: bp.contact_radius,
            mu_static,
            mu_kinetic,
            damping_time: bp.damping_time_s,
            nonlinear: effects.nonlinear_elasticity,
            plastic: effects.plasticity,
            drag: effects.drag,
            magnet: effects.magnet,
            frame: effects.rotating_frame,
            fan: effects.fan,
            attachments: Vec::new(),
            grasp: GraspMode::Kinematic,
            push_radius: push,
            settle_rate: 0.0,
            obstacles: Vec::new(),
        }
    }

    /// Attaches `particles` to gripper `gripper` at its current position `at`.
    pub(crate) fn attach(&mut self, particles: &[u32], gripper: u32, at: Vec3, mode: GraspMode) {
        self.grasp = mode;
        for &p in particles {
            self.attachments.push(Attachment {
                particle: p,
                gripper,
                offset: self.x[p as usize] - at,
            });
            if mode == GraspMode::Kinematic {
                self.w[p as usize] = 0.0;
            }
        }
    }

    /// Releases every particle held by `gripper`.
    pub(crate) fn release(&mut self, gripper: u32) {
        for a in self.attachments.iter().filter(|a| a.gripper == gripper) {
            self.w[a.particle as usize] = self.inv_mass[a.particle as usize];
        }
        self.attachments.retain(|a| a.gripper != gripper);
    }

    /// Total kinetic energy, J.
    pub(crate) fn kinetic_energy(&self) -> f32 {
        (self.mass.iter().zip(&self.v))
            .map(|(m, v)| 0.5 * m * v.length_squared())
            .sum()
    }

    /// Whether every position is finite.
    pub(crate) fn is_finite(&self) -> bool {
        self.x.iter().all(|p| p.is_finite())
    }

    /// Advances by one substep of `h` seconds with grippers at `grippers` at its end.
    pub(crate) fn substep(&mut self, h: f32, grippers: &[Vec3]) {
        self.apply_external(h);
        if self.drag.is_some() || self.fan.is_some() {
            self.update_areas();
        }
        if self.drag.is_some() {
            self.apply_drag(h);
        }
        if self.fan.is_some() {
            self.apply_fan(h);
        }
        self.x0.copy_from_slice(&self.x);
        for (x, (v, w)) in self.x.iter_mut().zip(self.v.iter().zip(&self.w)) {
            if *w > 0.0 {
                *x += *v * h;
            }
        }
        if self.grasp == GraspMode::Kinematic {
            for a in &self.attachments {
                self.x[a.particle as usize] = grippers[a.gripper as usize] + a.offset;
            }
        }
        for l in &mut self.links {
            l.lambda = 0.0;
        }
        for _ in 0..self.stiff_iterations {
            self.solve_links(h, 0, self.stiff_end);
        }
        for _ in 0..self.link_sweeps {
            self.solve_links(h, 0, self.links.len());
        }
        self.solve_stencils(h);
        if let GraspMode::Compliant {
            compliance,
            max_force,
        } = self.grasp
        {
            self.solve_grasp(h, grippers, compliance, max_force);
        }
        if let Some(r) = self.push_radius {
            self.solve_push(grippers, r);
        }
        if let Some(z) = self.ground {
            self.solve_ground(z);
        }
        if !self.obstacles.is_empty() {
            crate::obstacles::solve_boxes(
                &self.obstacles,
                &mut self.x,
                &self.x0,
                &self.w,
                self.contact,
                self.mu_static,
                self.mu_kinetic,
            );
        }
        let inv_h = 1.0 / h;
        for ((v, x), x0) in self.v.iter_mut().zip(&self.x).zip(&self.x0) {
            *v = (*x - *x0) * inv_h;
        }
        if let Some(p) = self.plastic {
            self.flow(h, &p);
        }
    }

    fn apply_external(&mut self, h: f32) {
        let settle = (-self.settle_rate * h).exp();
        // The Coriolis acceleration −2Ω ẑ × v turns the horizontal velocity by −2Ωh per
        // substep without changing its length: applied as that exact rotation, it does no work.
        let turn = self.frame.map(|f| {
            let (s, c) = (-2.0 * f.angular_velocity_rad_s * h).sin_cos();
            (
                c,
                s,
                f.angular_velocity_rad_s.powi(2),
                Vec3::new(f.axis_m[0], f.axis_m[1], 0.0),
            )
        });
        for i in 0..self.x.len() {
            if self.w[i] == 0.0 {
                continue;
            }
            let mut a = self.gravity;
            if let Some(m) = &self.magnet {
                let d = Vec3::from(m.center_m) - self.x[i];
                let dist = d.length();
                if dist > 1e-6 {
                    let r2 = m.falloff_radius_m * m.falloff_radius_m;
                    a += d / dist * (m.peak_acceleration_m_s2 * r2 / (r2 + dist * dist));
                }
            }
            if let Some((c, s, omega2, axis)) = turn {
                let rho = Vec3::new(self.x[i].x, self.x[i].y, 0.0) - axis;
                a += rho * omega2;
                let v = self.v[i];
                self.v[i] = Vec3::new(c * v.x - s * v.y, s * v.x + c * v.y, v.z);
            }
            self.v[i] = (self.v[i] + a * h) * settle;
        }
    }

    /// Each sheet particle's share of the deformed area, as an area-weighted normal
    /// (`area_vec`), for the drag law.
    fn update_areas(&mut self) {
        if !self.faces.is_empty() {
            self.area_vec.fill(Vec3::ZERO);
            for f in &self.faces {
                let [a, b, c] = f.map(|i| self.x[i as usize]);
                let share = (b - a).cross(c - a) / 6.0;
                for i in f {
                    self.area_vec[*i as usize] += share;
                }
            }
        }
    }

    /// Quadratic drag, integrated per component with the implicit update
    /// `u' = u / (1 + h k |u|)` (exact decay direction, unconditionally stable).
    fn apply_drag(&mut self, h: f32) {
        let Some(d) = self.drag else { return };
        let wind = Vec3::from(d.wind_m_s);
        for i in 0..self.x.len() {
            if self.w[i] == 0.0 {
                continue;
            }
            if let Some(new_u) = self.dragged(i, self.v[i] - wind, &d, h) {
                self.v[i] = wind + new_u;
            }
        }
    }

    /// The fan's jet: the velocity change the drag law gives in the jet's air minus the one
    /// it gives in still air (`Fan`), so that the jet adds only its own push.
    fn apply_fan(&mut self, h: f32) {
        let Some(f) = self.fan else { return };
        for i in 0..self.x.len() {
            if self.w[i] == 0.0 {
                continue;
            }
            let wind = Vec3::from(f.wind_at(self.x[i].to_array()));
            if wind == Vec3::ZERO {
                continue;
            }
            let v = self.v[i];
            let (Some(in_jet), Some(still)) = (
                self.dragged(i, v - wind, &f.air, h),
                self.dragged(i, v, &f.air, h),
            ) else {
                continue;
            };
            self.v[i] = v + (wind + in_jet) - still;
        }
    }

    /// Particle `i`'s velocity relative to the air, `u`, after one substep `h` of the drag
    /// law `d` (`None`: the particle has no drag area).
    fn dragged(&self, i: usize, u: Vec3, d: &Drag, h: f32) -> Option<Vec3> {
        let half_rho = 0.5 * d.air_density_kg_m3;
        let decay = |u: Vec3, k: f32| u / (1.0 + h * k * u.length());
        let m = self.mass[i];
        Some(match self.drag_shape[i] {
            DragShape::None => return None,
            DragShape::Sheet => {
                let av = self.area_vec[i];
                let area = av.length();
                if area < 1e-12 {
                    return None;
                }
                let n = av / area;
                let un = n * u.dot(n);
                // Skin friction acts on both faces of the sheet.
                decay(un, half_rho * d.normal_coefficient * area / m)
                    + decay(u - un, half_rho * d.tangential_coefficient * 2.0 * area / m)
            }
            DragShape::Rod { a, b, area } => {
                let t = (self.x[b as usize] - self.x[a as usize]).normalize_or_zero();
                let ut = t * u.dot(t);
                decay(u - ut, half_rho * d.normal_coefficient * area / m)
                    + decay(
                        ut,
                        half_rho * d.tangential_coefficient * std::f32::consts::PI * area / m,
                    )
            }
            DragShape::Blob { area } => decay(u, half_rho * d.normal_coefficient * area / m),
        })
    }

    fn solve_links(&mut self, h: f32, start: usize, end: usize) {
        let inv_h2 = 1.0 / (h * h);
        let gamma = self.damping_time / h;
        for l in &mut self.links[start..end] {
            let (i, j) = (l.i as usize, l.j as usize);
            let (wi, wj) = (self.w[i], self.w[j]);
            let ws = wi + wj;
            if ws == 0.0 {
                continue;
            }
            let d = self.x[i] - self.x[j];
            let len = d.length();
            if len < 1e-9 {
                continue;
            }
            let n = d / len;
            let c = len - l.rest;
            let mut alpha = l.compliance;
            if let Some(nl) = &self.nonlinear {
                let eps = c / l.rest;
                // Secant stiffness of the nonlinear law, relative to the linear one.
                let factor = if eps >= 0.0 {
                    1.0 + eps * eps / (3.0 * nl.stiffening_strain * nl.stiffening_strain)
                } else {
                    nl.compression_ratio
                };
                alpha /= factor;
            }
            let at = alpha * inv_h2;
            let rel = n.dot((self.x[i] - self.x0[i]) - (self.x[j] - self.x0[j]));
            let dl = -(c + at * l.lambda + gamma * rel) / ((1.0 + gamma) * ws + at);
            l.lambda += dl;
            self.x[i] += n * (wi * dl);
            self.x[j] -= n * (wj * dl);
        }
    }

    fn solve_stencils(&mut self, h: f32) {
        let inv_h2 = 1.0 / (h * h);
        for s in &self.stencils {
            let (i, j, k) = (s.i as usize, s.j as usize, s.k as usize);
            let (wi, wj, wk) = (self.w[i], self.w[j], self.w[k]);
            let ws = wi + wk + 4.0 * wj;
            if ws == 0.0 {
                continue;
            }
            let v = self.x[i] + self.x[k] - 2.0 * self.x[j];
            let c = v.length();
            if c < 1e-9 {
                continue;
            }
            let n = v / c;
            let dl = -c / (ws + s.compliance * inv_h2);
            self.x[i] += n * (wi * dl);
            self.x[k] += n * (wk * dl);
            self.x[j] -= n * (2.0 * wj * dl);
        }
    }

    fn solve_grasp(&mut self, h: f32, grippers: &[Vec3], compliance: f32, max_force: f32) {
        let at = compliance / (h * h);
        for a in &mut self.attachments {
            let i = a.particle as usize;
            let g = grippers[a.gripper as usize];
            let anchor = g + a.offset;
            let w = self.w[i];
            let d = self.x[i] - anchor;
            self.x[i] -= d * (w / (w + at));
            // The spring force after the correction; above the limit the anchor slides so that
            // the force equals the limit (the object slips in the fingers).
            let d = self.x[i] - anchor;
            let stretch = d.length();
            let limit = max_force * compliance;
            if stretch > limit {
                a.offset += d * (1.0 - limit / stretch);
            }
        }
    }

    fn solve_push(&mut self, grippers: &[Vec3], radius: f32) {
        let r = radius + self.contact;
        for c in grippers {
            for (x, w) in self.x.iter_mut().zip(&self.w) {
                if *w == 0.0 {
                    continue;
                }
                let d = *x - *c;
                let l2 = d.length_squared();
                if l2 < r * r && l2 > 1e-12 {
                    *x = *c + d * (r / l2.sqrt());
                }
            }
        }
    }

    /// Ground contact with position-level static/kinetic friction: a particle pushed out of the
    /// ground by `d` keeps still if its tangential slide in this substep is below `μ_s d`,
    /// otherwise the slide is shortened by `μ_k d`.
    fn solve_ground(&mut self, ground: f32) {
        let floor = ground + self.contact;
        for i in 0..self.x.len() {
            if self.w[i] == 0.0 || self.x[i].z >= floor {
                continue;
            }
            let depth = floor - self.x[i].z;
            self.x[i].z = floor;
            let slide = self.x[i] - self.x0[i];
            let tangential = Vec3::new(slide.x, slide.y, 0.0);
            let len = tangential.length();
            if len < self.mu_static * depth {
                self.x[i] -= tangential;
            } else if len > 0.0 {
                self.x[i] -= tangential * (self.mu_kinetic * depth / len).min(1.0);
            }
        }
    }

    /// Plastic flow of rest lengths: beyond the yield strain, towards the length that puts the
    /// strain back on the yield surface, with time constant τ.
    fn flow(&mut self, h: f32, p: &Plasticity) {
        let rate = (h / p.flow_time_s).min(1.0);
        for l in &mut self.links {
            let len = self.x[l.i as usize].distance(self.x[l.j as usize]);
            let eps = (len - l.rest) / l.rest;
            let target = if eps > p.yield_strain {
                len / (1.0 + p.yield_strain)
            } else if eps < -p.yield_strain {
                len / (1.0 - p.yield_strain)
            } else {
                continue;
            };
            let new_rest = l.rest + rate * (target - l.rest);
            let lo = l.rest0 * (1.0 - p.max_plastic_strain);
            let hi = l.rest0 * (1.0 + p.max_plastic_strain);
            let old = l.rest;
            l.rest = new_rest.clamp(lo, hi);
            // Keep the compliance per unit length: a longer link is proportionally softer.
            l.compliance *= l.rest / old;
        }
    }
}

/// A Gauss–Seidel order of `elems` (each a set of particle indices): greedy colouring so that
/// elements of one colour share no particle, then stable by colour. Deterministic.
fn color_order<const K: usize>(
    elems: impl Iterator<Item = [u32; K]>,
    particles: usize,
) -> Vec<usize> {
    let mut used: Vec<u128> = vec![0; particles];
    let mut colored: Vec<(u32, usize)> = elems
        .enumerate()
        .map(|(k, e)| {
            let taken = e.iter().fold(0u128, |m, &p| m | used[p as usize]);
            let c = (!taken).trailing_zeros().min(127);
            for &p in &e {
                used[p as usize] |= 1u128 << c;
            }
            (c, k)
        })
        .collect();
    colored.sort_by_key(|&(c, k)| (c, k));
    colored.into_iter().map(|(_, k)| k).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A free particle at rest in the turning lab, without gravity or ground, moves in a
    /// straight line in the inertial frame (it was carried along at Ω × r, nothing pushes
    /// it since); recorded in the lab's frame its path is that line turned back by −Ωt. The
    /// solver must reproduce this from the Coriolis and centrifugal terms alone.
    #[test]
    fn a_free_particle_in_the_turning_lab_moves_straight_in_the_inertial_frame() {
        let mut bp = Blueprint {
            total_mass: 0.1,
            ..Blueprint::default()
        };
        let start = Vec3::new(0.2, 0.1, 0.5);
        bp.add(start, true, DragShape::None, [1.0; 3]);
        let (omega, axis) = (2.0_f32, Vec3::new(-0.3, -0.3, 0.0));
        let effects = Effects {
            rotating_frame: Some(RotatingFrame {
                angular_velocity_rad_s: omega,
                axis_m: [axis.x, axis.y],
            }),
            ..Effects::none()
        };
        let mut sim = Sim::new(&bp, &effects, bp.rest.clone(), None);
        (sim.gravity, sim.ground) = (Vec3::ZERO, None);
        let h = 1.0 / 2000.0;
        let r = start - axis;
        // Inertial frame: at t = 0 the frames coincide, the particle moves at Ω ẑ × r.
        let v_inertial = Vec3::new(-omega * r.y, omega * r.x, 0.0);
        let mut worst = 0.0_f32;
        for step in 1..=2000 {
            sim.substep(h, &[]);
            let t = step as f32 * h;
            let p = r + v_inertial * t;
            let (s, c) = (-omega * t).sin_cos();
            let expected = axis + Vec3::new(c * p.x - s * p.y, s * p.x + c * p.y, p.z);
            worst = worst.max(sim.x[0].distance(expected));
        }
        // 1 s, ~0.6 m travelled: first-order splitting errors stay well under a centimetre.
        assert!(worst < 0.005, "off the analytic path by {worst} m");
    }

    /// The fan pushes a particle at rest in its jet along the jet with the drag law's
    /// acceleration `½ ρ C A |w| w / m` (w: the jet's air velocity there), keeps pushing it
    /// downstream along the axis, and leaves one upstream of the nozzle alone.
    #[test]
    fn the_fans_jet_drags_what_is_in_it_and_nothing_else() {
        let mut bp = Blueprint {
            total_mass: 0.02,
            ..Blueprint::default()
        };
        let area = 1e-3;
        bp.add(
            Vec3::new(0.0, 0.0, 0.3),
            true,
            DragShape::Blob { area },
            [1.0; 3],
        );
        bp.add(
            Vec3::new(-0.8, 0.0, 0.3),
            true,
            DragShape::Blob { area },
            [1.0; 3],
        );
        let effects = Effects::only(crate::ObjectKind::Paper, crate::EffectKind::Fan);
        let fan = effects.fan.unwrap();
        let mut sim = Sim::new(&bp, &effects, bp.rest.clone(), None);
        (sim.gravity, sim.ground) = (Vec3::ZERO, None);
        let wind = Vec3::from(fan.wind_at(sim.x[0].to_array()));
        // On the axis 0.6 m downstream: U0 R0 / (R0 + 0.06 m).
        assert!(
            (wind.x - 4.0 * 0.08 / 0.14).abs() < 1e-5 && wind.y == 0.0,
            "{wind}"
        );
        let h = 1e-4;
        sim.substep(h, &[]);
        let k = 0.5 * fan.air.air_density_kg_m3 * fan.air.normal_coefficient * area / sim.mass[0];
        let expected = wind * (k * wind.length() * h);
        assert!(
            (sim.v[0] - expected).length() < 0.01 * expected.length(),
            "{} against {expected}",
            sim.v[0]
        );
        assert_eq!(sim.v[1], Vec3::ZERO);
        for _ in 0..10_000 {
            sim.substep(h, &[]);
        }
        // 1 s: about 0.1 m/s along the axis (the push falls off as the particle leaves).
        let v = sim.v[0];
        assert!(
            v.x > 0.05 && v.x < wind.x && v.y == 0.0 && v.z == 0.0,
            "{v}"
        );
        assert_eq!(sim.x[1], Vec3::new(-0.8, 0.0, 0.3));
    }
}
