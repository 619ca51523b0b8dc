//! Tiled front-to-back compositing.

use rayon::prelude::*;

use crate::fastexp::exp_nonpositive;
use crate::project::{MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE, Splat, project};
use crate::{Camera, Error, Gaussians, Image};

/// Tile side, pixels: each tile composites only the splats binned to it.
pub const TILE: usize = 16;

/// Renders `gaussians` as seen by `camera` over a uniform `background` colour.
///
/// Per Gaussian: EWA projection with the 0.3 px² low-pass; culled when its centre is not
/// beyond the near plane, its opacity is below 1/255 or no pixel centre lies inside the
/// ellipse where its alpha reaches 1/255. Splats are sorted by camera depth of their centres
/// (ties by index) and binned to 16 × 16 px tiles. Per pixel, front to back:
/// `alpha = min(0.99, opacity · exp(-½ dᵀ Σ⁻¹ d))`, skipped when below 1/255; compositing stops
/// before a splat that would bring the transmittance below 1e-4. Tiles run in parallel (rayon)
/// and every pixel is computed by one thread in a fixed order, so the image does not depend on
/// the thread count.
///
/// # Errors
/// An invalid camera, invalid Gaussians (non-finite values, bad opacities, zero quaternions,
/// mismatched lengths) or a non-finite background. Gaussians behind the camera, degenerate
/// (zero) scales and empty sets are fine.
///
/// ```
/// use gsplat::{Camera, Gaussians, render};
/// use glam::Vec3;
/// let cam = Camera::look_at(Vec3::new(0.0, -1.0, 0.2), Vec3::new(0.0, 0.0, 0.2), Vec3::Z,
///                           40f32.to_radians(), 64, 48)?;
/// let g = Gaussians::isotropic(vec![Vec3::new(0.0, 0.0, 0.2)], vec![[1.0, 0.0, 0.0]], 0.05, 0.9)?;
/// let img = render(&g, &cam, [1.0, 1.0, 1.0])?;
/// let centre = img.index(32, 24);
/// assert!(img.alpha[centre] > 0.85);                  // nearly opaque at the centre
/// assert!((img.depth[centre] - 1.0).abs() < 1e-4);    // 1 m from the camera
/// assert_eq!(img.alpha[img.index(0, 0)], 0.0);        // the corner sees the background
/// # Ok::<(), gsplat::Error>(())
/// ```
pub fn render(
    gaussians: &Gaussians,
    camera: &Camera,
    background: [f32; 3],
) -> Result<Image, Error> {
    camera.validate()?;
    gaussians.validate()?;
    if !background.iter().all(|c| c.is_finite()) {
        return Err(Error::Camera(format!(
            "non-finite background colour {background:?}"
        )));
    }
    let splats = sorted_splats(gaussians, camera);
    let rows = RowBins::new(&splats, camera.height);
    Ok(composite(
        &splats,
        &rows,
        camera.width,
        camera.height,
        background,
    ))
}

/// Projected, culled splats in front-to-back order (depth, then index).
fn sorted_splats(gaussians: &Gaussians, camera: &Camera) -> Vec<Splat> {
    // `collect` keeps index order.
    let projected: Vec<Splat> = (0..gaussians.len())
        .into_par_iter()
        .with_min_len(1024)
        .filter_map(|i| project(gaussians, i, camera))
        .collect();
    // Depths are positive (beyond the near plane), so their bit patterns sort like the
    // values. A stable radix sort of (depth bits, position) pairs taken in index order keeps
    // equal depths in index order.
    let keys: Vec<(u32, u32)> = projected
        .par_iter()
        .enumerate()
        .map(|(k, s)| (s.depth.to_bits(), k as u32))
        .collect();
    radix_sort(keys)
        .par_iter()
        .with_min_len(4096)
        .map(|&(_, k)| projected[k as usize])
        .collect()
}

/// Stable least-significant-digit radix sort by the first field, 8 bits per pass; passes
/// whose digit is the same for every key are skipped.
fn radix_sort(mut keys: Vec<(u32, u32)>) -> Vec<(u32, u32)> {
    let mut other = vec![(0u32, 0u32); keys.len()];
    for shift in [0u32, 8, 16, 24] {
        let mut count = [0usize; 257];
        for k in &keys {
            count[((k.0 >> shift) & 0xff) as usize + 1] += 1;
        }
        if count.contains(&keys.len()) {
            continue;
        }
        for d in 1..257 {
            count[d] += count[d - 1];
        }
        for k in &keys {
            let slot = &mut count[((k.0 >> shift) & 0xff) as usize];
            other[*slot] = *k;
            *slot += 1;
        }
        std::mem::swap(&mut keys, &mut other);
    }
    keys
}

/// Per tile row (16 px high band), the splats that touch it, in front-to-back order (CSR
/// layout). Tile rows are binned into their tiles inside the parallel compositing tasks, so
/// only this coarse pass is serial.
struct RowBins {
    /// `start[r]..start[r + 1]` indexes `items` for tile row `r`.
    start: Vec<u32>,
    items: Vec<u32>,
}

impl RowBins {
    /// Two passes over the depth-sorted splats (count, then fill), so every list comes out
    /// already sorted by depth.
    fn new(splats: &[Splat], height: usize) -> Self {
        let (start, items) = csr(
            height.div_ceil(TILE),
            splats.iter().enumerate().map(|(k, s)| {
                (
                    k as u32,
                    (s.y0 / TILE as u32) as usize..((s.y1 - 1) / TILE as u32 + 1) as usize,
                )
            }),
        );
        RowBins { start, items }
    }

    fn row(&self, r: usize) -> &[u32] {
        &self.items[self.start[r] as usize..self.start[r + 1] as usize]
    }
}

/// Compressed lists: `entries` yields (item, range of lists it belongs to); returns per-list
/// starts (`lists + 1` of them) and the items, each list in the order the items came.
fn csr(
    lists: usize,
    entries: impl Iterator<Item = (u32, std::ops::Range<usize>)> + Clone,
) -> (Vec<u32>, Vec<u32>) {
    let mut start = vec![0u32; lists + 1];
    for (_, range) in entries.clone() {
        for l in range {
            start[l + 1] += 1;
        }
    }
    for l in 1..start.len() {
        start[l] += start[l - 1];
    }
    let mut fill = start.clone();
    let mut items = vec![0u32; start[lists] as usize];
    for (item, range) in entries {
        for l in range {
            items[fill[l] as usize] = item;
            fill[l] += 1;
        }
    }
    (start, items)
}

/// Pixels per inner-loop run: a quarter of a tile row, one SSE vector, so the loop body is a
/// fixed-size array loop the compiler vectorises.
const LANES: usize = 4;
/// `LANE_MASKS[bits][l]` is 1.0 where bit `l` of `bits` is set.
const LANE_MASKS: [[f32; LANES]; 1 << LANES] = {
    let mut m = [[0.0; LANES]; 1 << LANES];
    let mut bits = 0;
    while bits < 1 << LANES {
        let mut l = 0;
        while l < LANES {
            if bits & (1 << l) != 0 {
                m[bits][l] = 1.0;
            }
            l += 1;
        }
        bits += 1;
    }
    m
};

/// Runs per tile.
const RUNS: usize = TILE * TILE / LANES;

/// Running per-pixel state of one tile, structure of arrays; each array is indexed by
/// `[4 * row + run][lane]` (pixel `x = 4 run + lane`).
struct TileState {
    /// Transmittance so far; stored negated once the pixel has stopped (it is never 0 while
    /// live, being at least 1e-4), so the vectorised loop tells live pixels apart with one
    /// comparison.
    t: [[f32; LANES]; RUNS],
    r: [[f32; LANES]; RUNS],
    g: [[f32; LANES]; RUNS],
    b: [[f32; LANES]; RUNS],
    /// Sum of weight × depth.
    d: [[f32; LANES]; RUNS],
}

impl TileState {
    fn new() -> Self {
        TileState {
            t: [[1.0; LANES]; RUNS],
            r: [[0.0; LANES]; RUNS],
            g: [[0.0; LANES]; RUNS],
            b: [[0.0; LANES]; RUNS],
            d: [[0.0; LANES]; RUNS],
        }
    }

    fn reset(&mut self) {
        *self = TileState::new();
    }
}

fn composite(
    splats: &[Splat],
    rows: &RowBins,
    width: usize,
    height: usize,
    background: [f32; 3],
) -> Image {
    let mut img = Image::blank(width, height);
    let band = TILE * width;
    let tiles_x = width.div_ceil(TILE);
    img.rgb
        .par_chunks_mut(3 * band)
        .zip(img.alpha.par_chunks_mut(band))
        .zip(img.depth.par_chunks_mut(band))
        .enumerate()
        .for_each(|(ty, ((rgb, alpha), depth))| {
            // This band's splats into its tiles, keeping depth order.
            let (start, items) = csr(
                tiles_x,
                rows.row(ty).iter().map(|&k| {
                    let s = &splats[k as usize];
                    (
                        k,
                        (s.x0 / TILE as u32) as usize..((s.x1 - 1) / TILE as u32 + 1) as usize,
                    )
                }),
            );
            let mut st = TileState::new();
            let y0 = ty * TILE;
            let th = TILE.min(height - y0);
            for tx in 0..tiles_x {
                let x0 = tx * TILE;
                let tw = TILE.min(width - x0);
                st.reset();
                let list = &items[start[tx] as usize..start[tx + 1] as usize];
                composite_tile(splats, list, x0, y0, tw, th, &mut st);
                for ly in 0..th {
                    for lx in 0..tw {
                        let (run, l) = (ly * TILE / LANES + lx / LANES, lx % LANES);
                        let q = ly * width + x0 + lx;
                        let t = st.t[run][l].abs();
                        let a = 1.0 - t;
                        rgb[3 * q] = st.r[run][l] + t * background[0];
                        rgb[3 * q + 1] = st.g[run][l] + t * background[1];
                        rgb[3 * q + 2] = st.b[run][l] + t * background[2];
                        alpha[q] = a;
                        depth[q] = if a > 0.0 { st.d[run][l] / a } else { 0.0 };
                    }
                }
            }
        });
    img
}

/// Composites one tile's splats (front to back) into `st`. Each splat touches only the rows
/// of its pixel rectangle inside the tile, and in each row only the runs of pixels that are
/// near its ellipse and still live; the loop ends once every pixel has stopped.
// Out of line so that profiles show it; called once per tile, so the call costs nothing.
#[inline(never)]
fn composite_tile(
    splats: &[Splat],
    list: &[u32],
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
    st: &mut TileState,
) {
    // Bit `x` of `live[y]`: pixel (x, y) of the tile is inside the image and still compositing.
    let row_bits = ((1u32 << w) - 1) as u16;
    let mut live = [0u16; TILE];
    live[..h].fill(row_bits);
    let mut live_rows = h;
    let (x0, y0) = (x0 as u32, y0 as u32);
    let lane: [f32; LANES] = std::array::from_fn(|l| l as f32);
    for &k in list {
        let s = &splats[k as usize];
        let lx0 = s.x0.max(x0) - x0;
        let lx1 = s.x1.min(x0 + TILE as u32) - x0;
        let ly0 = s.y0.max(y0) - y0;
        let ly1 = s.y1.min(y0 + TILE as u32) - y0;
        let bbox_bits = span_bits(lx0, lx1);
        // Per-row spans only pay off for splats wider than two runs.
        let narrow = lx1 - lx0 <= 2 * LANES as u32;
        for ly in ly0..ly1 {
            let row_live = live[ly as usize];
            if row_live & bbox_bits == 0 {
                continue;
            }
            let dy = (y0 + ly) as f32 + 0.5 - s.v;
            let todo = if narrow {
                row_live & bbox_bits
            } else {
                // The row's pixels with power >= min_power: a thin, tilted ellipse covers
                // much less of a row than its bounding box. The margin keeps every pixel the
                // exact per-pixel test below could accept.
                let disc = s.span_p - s.span_q * dy * dy;
                if disc < 0.0 || disc.is_nan() {
                    continue;
                }
                let half = disc.sqrt() * s.inv_a;
                let centre = s.u - s.b_over_a * dy - 0.5 - x0 as f32;
                let margin = 2e-3 * half + 1e-3;
                // Truncating, saturating casts (SSE2 has no floor/ceil; negatives become 0)
                // only ever widen the span by a pixel.
                let rlo = lx0.max((centre - half - margin) as u32);
                let rhi = lx1.min((centre + half + margin + 1.0) as u32);
                if rlo >= rhi {
                    continue;
                }
                row_live & span_bits(rlo, rhi)
            };
            if todo == 0 {
                continue;
            }
            // power(dx) = -½(a dx² + c dy²) - b dx dy = k0 + dx (k1 + k2 dx) along the row.
            let k0 = -0.5 * s.c * dy * dy;
            let k1 = -s.b * dy;
            let k2 = -0.5 * s.a;
            let mut row_after = row_live;
            for run in (todo.trailing_zeros() as usize / LANES)
                ..=((15 - todo.leading_zeros()) as usize / LANES)
            {
                let bits = (todo >> (run * LANES)) & ((1 << LANES) - 1);
                if bits == 0 {
                    continue;
                }
                // 1.0 for lanes that are live and in the row's span.
                let mask = &LANE_MASKS[bits as usize];
                let at = ly as usize * (TILE / LANES) + run;
                let base = (run * LANES) as f32;
                let dx0 = (x0 as f32 + base + 0.5) - s.u;
                let mut stopped = 0u32;
                let t = &mut st.t[at];
                let r = &mut st.r[at];
                let g = &mut st.g[at];
                let b = &mut st.b[at];
                let d = &mut st.d[at];
                // Branch-free (non-short-circuit `&`, selects, all-float tests) so the
                // compiler vectorises it.
                for l in 0..LANES {
                    let dx = dx0 + lane[l];
                    let power = k0 + dx * (k1 + k2 * dx);
                    let alpha = s.opacity * exp_nonpositive(power);
                    let alpha = if alpha > MAX_ALPHA { MAX_ALPHA } else { alpha };
                    let tl = t[l];
                    // 3DGS skips power > 0 (possible only through rounding) and alpha < 1/255;
                    // `power >= min_power` is that alpha test up to rounding, and keeps exp's
                    // input clamp from mattering.
                    let ok = (mask[l] > 0.0)
                        & (power <= 0.0)
                        & (power >= s.min_power)
                        & (alpha >= MIN_ALPHA);
                    let next = tl * (1.0 - alpha);
                    let stop = ok & (next < MIN_TRANSMITTANCE);
                    let draw = ok & !stop;
                    let w = if draw { alpha * tl } else { 0.0 };
                    r[l] += w * s.color[0];
                    g[l] += w * s.color[1];
                    b[l] += w * s.color[2];
                    d[l] += w * s.depth;
                    let kept = if stop { -tl } else { tl };
                    t[l] = if draw { next } else { kept };
                    stopped += u32::from(stop);
                }
                if stopped > 0 {
                    for (l, tl) in t.iter().enumerate() {
                        if *tl < 0.0 {
                            row_after &= !(1 << (run * LANES + l));
                        }
                    }
                }
            }
            if row_after != row_live {
                live[ly as usize] = row_after;
                if row_after == 0 {
                    live_rows -= 1;
                }
            }
        }
        if live_rows == 0 {
            break;
        }
    }
}

/// Bits `lo..hi` set (`hi <= 16`).
fn span_bits(lo: u32, hi: u32) -> u16 {
    (((1u32 << hi) - 1) & !((1u32 << lo) - 1)) as u16
}
