//! What the per-spring candidate effects add to a model step: a 1000-particle lattice
//! (10,476 springs) jostled out of rest so that strains take both signs, one 0.1 s step with
//! the plain backbone's automatic substep held fixed for every variant (so the rows compare the
//! cost of a substep, not the effects' stability limits). Then every candidate at its starting
//! strength (`candidate/<name>`): what a base effect adds to every rollout of a diagnosis, the
//! source of `gap::effort`'s per-effect factors (no grippers here: the gripper effects cost
//! nothing per particle).
//! Run: `cargo bench -p pgrd-gap` (one thread: a step is sequential).
#![allow(missing_docs)] // criterion_group! generates an undocumented pub fn

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use gap::forces::{PlasticCreep, StrainStiffening};
use glam::Vec3;
use springs::{
    ActionFrame, Backbone, BackboneOptions, Effect, SimConfig, SpringParams, State, Substep,
};

/// 10 x 10 x 10 lattice, 1 cm spacing, 1 cm above the ground (threshold 1.75 cm: face, edge
/// and body diagonals).
fn lattice() -> Vec<Vec3> {
    let mut x = Vec::with_capacity(1000);
    for i in 0..10 {
        for j in 0..10 {
            for k in 0..10 {
                x.push(Vec3::new(i as f32, j as f32, k as f32 + 1.0) * 0.01);
            }
        }
    }
    x
}

/// Every lattice particle once, each 1 cm from the one before (rows and layers walked back and
/// forth).
fn serpentine() -> std::sync::Arc<[u32]> {
    let mut order = Vec::with_capacity(1000);
    for i in 0..10u32 {
        for jj in 0..10u32 {
            let j = if i % 2 == 0 { jj } else { 9 - jj };
            for kk in 0..10u32 {
                let k = if (i * 10 + jj) % 2 == 0 { kk } else { 9 - kk };
                order.push(i * 100 + j * 10 + k);
            }
        }
    }
    order.into()
}

fn params() -> SpringParams {
    SpringParams {
        threshold: 0.0175,
        ..SpringParams::reference_rope()
    }
}

/// The lattice with every particle moved up to ±1.5 mm per axis (fixed sequence).
fn jostled(x: &[Vec3]) -> State {
    let mut s = 0x9e37_79b9_7f4a_7c15_u64;
    let mut unit = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32 - 0.5
    };
    State::at_rest(
        x.iter()
            .map(|p| *p + Vec3::new(unit(), unit(), unit()) * 0.003)
            .collect(),
    )
}

fn bench(c: &mut Criterion) {
    let x = lattice();
    let plain = Backbone::new(&x, &[], params(), SimConfig::default()).expect("lattice");
    let config = SimConfig {
        substep: Substep::Fixed {
            dt: plain.substep_dt(),
        },
        ..SimConfig::default()
    };
    eprintln!(
        "lattice: {} springs, {} substeps of {:.3e} s per 0.1 s step",
        plain.springs().len(),
        plain.substeps(),
        plain.substep_dt()
    );
    let mut variants: Vec<(String, Option<Box<dyn Effect>>)> = vec![
        ("plain".into(), None),
        (
            "nonlinear-elasticity".into(),
            Some(Box::new(StrainStiffening {
                beta: 400.0,
                gamma: 0.3,
            })),
        ),
        (
            "plasticity".into(),
            Some(Box::new(PlasticCreep {
                yield_strain: 0.02,
                rate: 5.0,
            })),
        ),
    ];
    let centre = x.iter().copied().sum::<Vec3>() / x.len() as f32;
    let frame = gap::MaterialFrame::new(&x, centre).expect("frame");
    for cand in gap::Candidate::LIBRARY
        .into_iter()
        .chain(gap::Candidate::EXTRA)
        .chain([gap::Candidate::ExternalField])
    {
        variants.push((
            format!("candidate/{}", cand.name()),
            Some(cand.effect(&cand.start(), &frame)),
        ));
    }
    let none = ActionFrame {
        positions: &[],
        closed: &[],
    };
    let start = jostled(&x);
    for (name, effect) in variants {
        // `bending-damping` and `twist` need a chain: a serpentine through the lattice, 1 cm
        // per link (the damping's cost is one banded solve over all 1000 particles per
        // substep; the twist's ends are not held here, so it carries its frames along the
        // chain each substep and adds no force: its gradient, another pass, is not timed).
        let chain = matches!(
            name.as_str(),
            "candidate/bending-damping" | "candidate/twist"
        )
        .then(serpentine);
        let options = BackboneOptions {
            masses: None,
            effects: effect.into_iter().collect(),
            chain,
            ..Default::default()
        };
        let bb = Backbone::with_options(&x, &[], params(), config, options)
            .expect("lattice with effect");
        let mut sc = bb.scratch();
        c.bench_function(&format!("lattice_1000p/step_0.1s/{name}"), |b| {
            b.iter_batched_ref(
                || start.clone(),
                |st| bb.step(st, none, none, &mut sc).expect("step"),
                BatchSize::SmallInput,
            )
        });
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
