//! "Where": the error of one model's held-out predictions localised in space, time and state.

use glam::Vec3;
use scene::Scene;
use serde::{Deserialize, Serialize};

/// Height above the ground below which a particle counts as in ground contact, m.
pub const CONTACT_HEIGHT_M: f32 = 0.01;

/// Mean error of a group of samples.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Bin {
    /// What the group is.
    pub label: String,
    /// Range of the binned quantity `[lo, hi]` (its unit is in the quantity's name).
    #[serde(deserialize_with = "crate::nan::pair")]
    pub range: [f64; 2],
    /// Share of all samples in the group.
    #[serde(deserialize_with = "crate::nan::f64")]
    pub share: f64,
    /// Mean position error, cm.
    #[serde(deserialize_with = "crate::nan::f64")]
    pub mean_error_cm: f64,
}

/// Error against one state quantity: quantile bins and the rank correlation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Trend {
    /// The quantity and its unit.
    pub quantity: String,
    /// Five equal-count bins.
    pub bins: Vec<Bin>,
    /// Spearman rank correlation between the quantity and the error.
    #[serde(deserialize_with = "crate::nan::f64")]
    pub spearman: f64,
}

/// Where the error lies.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Where {
    /// Reference shape (tracked particles of the first held-out episode's start frame), m.
    pub reference_shape: Vec<[f32; 3]>,
    /// Mean error per tracked particle over all held-out steps and episodes, cm.
    #[serde(deserialize_with = "crate::nan::vec")]
    pub per_particle_cm: Vec<f64>,
    /// Mean error per region of the rest shape: five bins along the principal axis.
    pub regions: Vec<Bin>,
    /// Mean error per predicted step over episodes, cm.
    #[serde(deserialize_with = "crate::nan::vec")]
    pub per_step_cm: Vec<f64>,
    /// Ground contact / fast motion / free motion.
    pub phases: Vec<Bin>,
    /// Error against speed, height, strain and distance from the gripper.
    pub state: Vec<Trend>,
    /// Held-out episodes left out because their tracked count differs from the first
    /// episode's (the data format forbids such datasets, so 0 for valid data; reports written
    /// before session 87 lack it and read as 0).
    #[serde(default)]
    pub skipped_episodes: usize,
}

struct Sample {
    error: f32,
    speed: f32,
    height: f32,
    strain: f32,
    gripper: Option<f32>,
}

fn neighbours(x: &[Vec3], k: usize) -> Vec<Vec<(usize, f32)>> {
    x.iter()
        .enumerate()
        .map(|(i, p)| {
            let mut d: Vec<(f32, usize)> = x
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(j, q)| (p.distance(*q), j))
                .collect();
            d.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            d.into_iter().take(k).map(|(r, j)| (j, r)).collect()
        })
        .collect()
}

fn samples(
    scene: &Scene,
    pred: &[Vec<Vec3>],
    ground_z: f32,
    dt: f32,
    out: &mut Vec<Sample>,
    per_particle: &mut [(f64, usize)],
    per_step: &mut [(f64, usize)],
) {
    let n = scene.tracked;
    let rest = &scene.init.x[..n];
    let nb = neighbours(rest, 4);
    for (s, (p, g)) in pred.iter().zip(&scene.truth).enumerate() {
        let vis = &scene.visible[s];
        let prev: &[Vec3] = if s == 0 { rest } else { &scene.truth[s - 1] };
        let grippers = scene
            .actions
            .frame(s + 1)
            .map(|f| f.positions.to_vec())
            .unwrap_or_default();
        for i in 0..n.min(p.len()) {
            if !vis[i] {
                continue;
            }
            let e = p[i].distance(g[i]);
            let strain = nb[i]
                .iter()
                .filter(|(_, r0)| *r0 > 0.0)
                .map(|(j, r0)| (g[i].distance(g[*j]) / r0 - 1.0).abs())
                .sum::<f32>()
                / nb[i].len().max(1) as f32;
            out.push(Sample {
                error: e,
                speed: g[i].distance(prev[i]) / dt,
                height: g[i].z - ground_z,
                strain,
                gripper: grippers
                    .iter()
                    .map(|q| q.distance(g[i]))
                    .min_by(f32::total_cmp),
            });
            per_particle[i].0 += f64::from(e);
            per_particle[i].1 += 1;
            per_step[s].0 += f64::from(e);
            per_step[s].1 += 1;
        }
    }
}

fn ranks(v: &[f32]) -> Vec<f64> {
    let mut idx: Vec<usize> = (0..v.len()).collect();
    idx.sort_by(|a, b| v[*a].total_cmp(&v[*b]).then(a.cmp(b)));
    let mut r = vec![0.0; v.len()];
    let mut i = 0;
    while i < idx.len() {
        let mut j = i;
        while j + 1 < idx.len() && v[idx[j + 1]] == v[idx[i]] {
            j += 1;
        }
        let avg = (i + j) as f64 / 2.0;
        for k in &idx[i..=j] {
            r[*k] = avg;
        }
        i = j + 1;
    }
    r
}

/// Spearman rank correlation (0 when either side is constant or too short).
pub fn spearman(a: &[f32], b: &[f32]) -> f64 {
    if a.len() != b.len() || a.len() < 3 {
        return 0.0;
    }
    let (ra, rb) = (ranks(a), ranks(b));
    let m = (a.len() - 1) as f64 / 2.0;
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in ra.iter().zip(&rb) {
        sab += (x - m) * (y - m);
        saa += (x - m) * (x - m);
        sbb += (y - m) * (y - m);
    }
    if saa > 0.0 && sbb > 0.0 {
        sab / (saa * sbb).sqrt()
    } else {
        0.0
    }
}

/// Equal-count bins of `values` with the mean of `errors` (m) in each, in cm.
fn quantile_bins(values: &[f32], errors: &[f32], bins: usize, total: usize) -> Vec<Bin> {
    let mut idx: Vec<usize> = (0..values.len()).collect();
    idx.sort_by(|a, b| values[*a].total_cmp(&values[*b]).then(a.cmp(b)));
    (0..bins)
        .filter_map(|b| {
            let lo = b * idx.len() / bins;
            let hi = (b + 1) * idx.len() / bins;
            let part = &idx[lo..hi];
            let first = *part.first()?;
            let last = *part.last()?;
            let mean = part.iter().map(|i| f64::from(errors[*i])).sum::<f64>() / part.len() as f64;
            Some(Bin {
                label: format!("q{}", b + 1),
                range: [f64::from(values[first]), f64::from(values[last])],
                share: part.len() as f64 / total.max(1) as f64,
                mean_error_cm: 100.0 * mean,
            })
        })
        .collect()
}

/// Localises the error of `predictions` (one per scene: steps × tracked positions, m).
/// `material` is the tracked particles' principal-axis coordinate in [−1, 1].
pub fn locate(scenes: &[Scene], predictions: &[Vec<Vec<Vec3>>], material: &[f32]) -> Where {
    let n = scenes.first().map_or(0, |s| s.tracked);
    let steps = scenes.iter().map(|s| s.truth.len()).max().unwrap_or(0);
    let mut per_particle = vec![(0.0, 0usize); n];
    let mut per_step = vec![(0.0, 0usize); steps];
    let mut all = Vec::new();
    let mut skipped_episodes = 0;
    for (scene, pred) in scenes.iter().zip(predictions) {
        if scene.tracked != n {
            // Per-particle means need one particle numbering across episodes.
            skipped_episodes += 1;
            continue;
        }
        let cfg = scene.sim_config();
        samples(
            scene,
            pred,
            cfg.ground_z.unwrap_or(0.0),
            cfg.step_dt,
            &mut all,
            &mut per_particle,
            &mut per_step,
        );
    }
    let mean_cm = |(s, c): &(f64, usize)| {
        if *c > 0 {
            100.0 * s / *c as f64
        } else {
            f64::NAN
        }
    };
    let per_particle_cm: Vec<f64> = per_particle.iter().map(mean_cm).collect();
    let total = all.len();
    let errors: Vec<f32> = all.iter().map(|s| s.error).collect();
    let group = |label: &str, pick: &dyn Fn(&Sample) -> bool| {
        let (sum, count) = all
            .iter()
            .filter(|s| pick(s))
            .fold((0.0, 0usize), |(s, c), x| (s + f64::from(x.error), c + 1));
        Bin {
            label: label.to_string(),
            range: [f64::NAN, f64::NAN],
            share: count as f64 / total.max(1) as f64,
            mean_error_cm: if count > 0 {
                100.0 * sum / count as f64
            } else {
                f64::NAN
            },
        }
    };
    let mut speeds: Vec<f32> = all.iter().map(|s| s.speed).collect();
    speeds.sort_by(f32::total_cmp);
    let fast = speeds
        .get(speeds.len() * 3 / 4)
        .copied()
        .unwrap_or(f32::INFINITY);
    let contact = |s: &Sample| s.height < CONTACT_HEIGHT_M;
    let phases = vec![
        group("ground contact", &|s| contact(s)),
        group("fast motion (top speed quartile, off the ground)", &|s| {
            !contact(s) && s.speed > fast
        }),
        group("free motion", &|s| !contact(s) && s.speed <= fast),
    ];
    let mut state = Vec::new();
    let mut trend = |quantity: &str, values: Vec<f32>, errs: Vec<f32>| {
        if values.len() >= 5 {
            state.push(Trend {
                quantity: quantity.to_string(),
                bins: quantile_bins(&values, &errs, 5, values.len()),
                spearman: spearman(&values, &errs),
            });
        }
    };
    trend(
        "speed_m_per_s",
        all.iter().map(|s| s.speed).collect(),
        errors.clone(),
    );
    trend(
        "height_m",
        all.iter().map(|s| s.height).collect(),
        errors.clone(),
    );
    trend(
        "strain",
        all.iter().map(|s| s.strain).collect(),
        errors.clone(),
    );
    let (gd, ge): (Vec<f32>, Vec<f32>) = all
        .iter()
        .filter_map(|s| s.gripper.map(|d| (d, s.error)))
        .unzip();
    trend("gripper_distance_m", gd, ge);
    // Regions: five bins of the material coordinate, weighting each particle equally.
    let valid: Vec<usize> = (0..n.min(material.len()))
        .filter(|i| per_particle[*i].1 > 0)
        .collect();
    let mat: Vec<f32> = valid.iter().map(|i| material[*i]).collect();
    let perr: Vec<f32> = valid
        .iter()
        .map(|i| (per_particle_cm[*i] / 100.0) as f32)
        .collect();
    let mut regions = quantile_bins(&mat, &perr, 5, mat.len());
    for (k, r) in regions.iter_mut().enumerate() {
        r.label = format!("axis segment {} of 5", k + 1);
    }
    Where {
        reference_shape: scenes
            .first()
            .map(|s| s.init.x[..s.tracked].iter().map(|p| p.to_array()).collect())
            .unwrap_or_default(),
        per_particle_cm,
        regions,
        per_step_cm: per_step.iter().map(mean_cm).collect(),
        phases,
        state,
        skipped_episodes,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spearman_of_monotone_and_reversed() {
        let a = [1.0, 2.0, 3.0, 4.0, 5.0];
        assert!((spearman(&a, &[2.0, 4.0, 8.0, 16.0, 32.0]) - 1.0).abs() < 1e-12);
        assert!((spearman(&a, &[5.0, 4.0, 3.0, 2.0, 1.0]) + 1.0).abs() < 1e-12);
        assert_eq!(spearman(&a, &[1.0; 5]), 0.0);
    }

    #[test]
    fn quantile_bins_split_evenly() {
        let v: Vec<f32> = (0..10).map(|i| i as f32).collect();
        let e: Vec<f32> = (0..10).map(|i| 0.01 * i as f32).collect();
        let b = quantile_bins(&v, &e, 5, 10);
        assert_eq!(b.len(), 5);
        assert_eq!(b[0].range, [0.0, 1.0]);
        assert!((b[0].mean_error_cm - 0.5).abs() < 1e-5);
        assert!((b[4].mean_error_cm - 8.5).abs() < 1e-5);
        assert!((b.iter().map(|x| x.share).sum::<f64>() - 1.0).abs() < 1e-12);
    }
}
