//! Scene builders shared by the tests and benches (each includes only what it uses).
#![allow(dead_code)]

use glam::Vec3;

/// SplitMix64: a tiny seeded generator, so every random scene is reproducible.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit()
    }
    pub fn vec3(&mut self, half: f32) -> Vec3 {
        Vec3::new(
            self.range(-half, half),
            self.range(-half, half),
            self.range(-half, half),
        )
    }
}

/// `nx * ny * nz` particles on a cubic lattice of `spacing` (m) starting at `origin`.
pub fn lattice(nx: usize, ny: usize, nz: usize, spacing: f32, origin: Vec3) -> Vec<Vec3> {
    let mut out = Vec::with_capacity(nx * ny * nz);
    for i in 0..nx {
        for j in 0..ny {
            for k in 0..nz {
                out.push(origin + spacing * Vec3::new(i as f32, j as f32, k as f32));
            }
        }
    }
    out
}

/// A rope along x: `n` particles over `length` (m) inside a cylinder of `radius` (m) whose axis
/// is at height `z0` (m). Deterministic (golden-angle spiral).
pub fn rope(n: usize, length: f32, radius: f32, z0: f32) -> Vec<Vec3> {
    (0..n)
        .map(|k| {
            let t = k as f32 / (n - 1) as f32;
            let angle = k as f32 * 2.399_963;
            let r = radius * ((k as f32 * 0.618_034).fract()).sqrt();
            Vec3::new(t * length, r * angle.cos(), z0 + r * angle.sin())
        })
        .collect()
}

/// `n` uniform random points in a cube of half-size `half` (m) centred at `centre`.
pub fn blob(rng: &mut Rng, n: usize, half: f32, centre: Vec3) -> Vec<Vec3> {
    (0..n).map(|_| centre + rng.vec3(half)).collect()
}
