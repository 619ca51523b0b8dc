//! How far the backbone's adjoint grows over a window, and how far nearby rollouts separate.
//!
//! Training through the backbone (`--sim-gradient adjoint`) multiplies one step adjoint per
//! step: over a long window the product can grow without bound and the training gradient
//! becomes `inf` or NaN (`docs/residual.md`, Training, "Where it breaks down"). For a few training
//! segments of `steps` steps this prints
//! - `fd`: the largest particle distance between two backbone rollouts whose starts differ by
//!   up to 1e-4 m along x, divided by that offset, after k steps (finite, so it saturates);
//! - `adj`: the norm of the position adjoint propagated back over the last k steps from the
//!   same direction, over the direction's norm (position part / velocity part);
//! - `check`: the largest mismatch, over the segment's steps, between one step's adjoint and
//!   central differences of the step (`⟨g, J p⟩` for fixed directions, offsets 1e-5 m), as a
//!   fraction of the steps' mean `|⟨g, J p⟩|`: whether the growth is the backbone's own or
//!   the adjoint's.
//!
//! ```sh
//! cargo run --release -p pgrd-residual --example adjoint_growth -- <data-dir> <run-dir> [paper|deform] [steps] [segments]
//! # steps: default 100; segments: default 3 (recorded starts, seed 1)
//! ```
//!
//! Only backbones without library effects (`backbone.json` without `effects`).

mod common;

use glam::Vec3;
use rand::SeedableRng;

/// A fixed direction per particle along x, entries in [−1, 1].
fn direction(i: usize) -> f32 {
    ((i * 7919) % 13) as f32 / 6.0 - 1.0
}

fn norm(v: &[Vec3]) -> f32 {
    v.iter().map(|g| g.length_squared()).sum::<f32>().sqrt()
}

fn main() -> Result<(), common::Error> {
    let inputs = common::inputs(
        "usage: adjoint_growth <data-dir> <run-dir> [paper|deform] [steps] [segments]",
    )?;
    let rest = &inputs.rest;
    let steps: usize = rest.first().map_or(Ok(100), |s| s.parse())?;
    let segments: usize = rest.get(1).map_or(Ok(3), |s| s.parse())?;
    let set = inputs.training_set()?;
    let marks: Vec<usize> = [1, 5, 10, 25, 50, 100, 200, 300, 400]
        .into_iter()
        .filter(|&k| k <= steps)
        .collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    for _ in 0..segments {
        let s = set.sample(&mut rng, steps, false)?;
        let bb = set.backbone(&s);
        let actions = &s.scene.actions;
        let eps = 1e-4f32;
        let mut moved = s.scene.init.clone();
        for (i, x) in moved.x.iter_mut().enumerate() {
            x.x += eps * direction(i);
        }
        let a = bb.rollout(&s.scene.init, actions)?;
        let b = bb.rollout(&moved, actions)?;
        let apart = |k: usize| {
            a.positions[k]
                .iter()
                .zip(&b.positions[k])
                .map(|(p, q)| (*p - *q).length())
                .fold(0.0, f32::max)
                / eps
        };
        let fd: Vec<String> = marks
            .iter()
            .filter(|&&k| k < a.positions.len())
            .map(|&k| format!("{k}:{:.1e}", apart(k)))
            .collect();
        println!("fd  {}", fd.join(" "));

        let n = bb.num_particles();
        let mut state = s.scene.init.clone();
        let mut scratch = bb.scratch();
        // Each step's tape and the state it started from.
        let (mut tapes, mut starts) = (Vec::with_capacity(steps), Vec::with_capacity(steps));
        for k in 0..steps {
            let (Some(from), Some(to)) = (actions.frame(k), actions.frame(k + 1)) else {
                break;
            };
            starts.push(state.clone());
            let mut tape = springs::StepTape::new();
            bb.step_taped(&mut state, from, to, &mut scratch, &mut tape)?;
            tapes.push(tape);
        }
        let adjoint = bb.step_adjoint();
        let start: Vec<Vec3> = (0..n).map(|i| Vec3::new(direction(i), 0.0, 0.0)).collect();
        let n0 = norm(&start);
        let mut adj = Vec::new();
        for &k in marks.iter().filter(|&&k| k <= tapes.len()) {
            let (mut gx, mut gv) = (start.clone(), vec![Vec3::ZERO; n]);
            for tape in tapes[tapes.len() - k..].iter().rev() {
                adjoint.vjp(tape, &mut gx, &mut gv)?;
            }
            adj.push(format!("{k}:{:.1e}/{:.1e}", norm(&gx) / n0, norm(&gv) / n0));
        }
        println!("adj {}", adj.join(" "));

        let g: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(direction(i), direction(i + 3), direction(i + 5)))
            .collect();
        let p: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(direction(i + 1), direction(i + 7), direction(i + 2)))
            .collect();
        let dot = |a: &[Vec3], b: &[Vec3]| -> f64 {
            a.iter().zip(b).map(|(u, w)| f64::from(u.dot(*w))).sum()
        };
        let (mut worst, mut at, mut scale) = (0.0f64, 0, 0.0f64);
        let eps = 1e-5f32;
        for (k, (tape, before)) in tapes.iter().zip(&starts).enumerate() {
            let (Some(from), Some(to)) = (actions.frame(k), actions.frame(k + 1)) else {
                break;
            };
            let (mut gx, mut gv) = (g.clone(), vec![Vec3::ZERO; n]);
            adjoint.vjp(tape, &mut gx, &mut gv)?;
            let mut ends = [before.clone(), before.clone()];
            for (end, sign) in ends.iter_mut().zip([1.0f32, -1.0]) {
                for (x, d) in end.x.iter_mut().zip(&p) {
                    *x += sign * eps * *d;
                }
                bb.step(end, from, to, &mut scratch)?;
            }
            let [plus, minus] = ends;
            let diff: Vec<Vec3> = plus.x.iter().zip(&minus.x).map(|(a, b)| *a - *b).collect();
            let fd = dot(&g, &diff) / (2.0 * f64::from(eps));
            scale += fd.abs() / tapes.len() as f64;
            let miss = (dot(&gx, &p) - fd).abs();
            if miss > worst {
                (worst, at) = (miss, k);
            }
        }
        println!(
            "check: largest mismatch {:.1e} of the steps' mean |<g, J p>| (step {at})",
            worst / scale
        );
    }
    Ok(())
}
