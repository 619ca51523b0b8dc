//! Interior fill of the reference world's solid objects from a tracked-size sample of their
//! surface: the fill must lie inside the true body and reach most of it.

use glam::Vec3;
use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use world::{Effects, Lab, ObjectKind, Resolution};

fn tree(points: &[Vec3]) -> ImmutableKdTree<f32, u32, 3, 32> {
    let pts: Vec<[f32; 3]> = points.iter().map(|p| p.to_array()).collect();
    ImmutableKdTree::new_from_slice(&pts)
}

fn dist(t: &ImmutableKdTree<f32, u32, 3, 32>, p: Vec3) -> f32 {
    t.nearest_one::<SquaredEuclidean>(&p.to_array())
        .distance
        .sqrt()
}

/// The body's lattice, its surface (particles with fewer than 6 lattice neighbours), a
/// tracked-size sample of that surface (every k-th in the lattice's order) and the lattice
/// spacing.
fn body(object: ObjectKind, tracked: usize) -> (Vec<Vec3>, Vec<Vec3>, Vec<Vec3>, f32) {
    let lab = Lab::new(object, &Effects::none(), Resolution::Full, 0).unwrap();
    let fine = lab.positions().to_vec();
    let t = tree(&fine);
    let spacing = fine
        .iter()
        .map(|p| {
            t.nearest_n::<SquaredEuclidean>(&p.to_array(), std::num::NonZero::new(2).unwrap())[1]
                .distance
                .sqrt()
        })
        .fold(f32::INFINITY, f32::min);
    let surface: Vec<Vec3> = fine
        .iter()
        .copied()
        .filter(|p| {
            t.within_unsorted::<SquaredEuclidean>(&p.to_array(), (1.01 * spacing).powi(2))
                .len()
                < 7
        })
        .collect();
    let step = surface.len().div_ceil(tracked).max(1);
    let sample = surface.iter().copied().step_by(step).collect();
    (fine, surface, sample, spacing)
}

fn check(object: ObjectKind, tracked: usize) {
    let (fine, surface, sample, spacing) = body(object, tracked);
    let fill_spacing = {
        let t = tree(&sample);
        let mut d: Vec<f32> = sample
            .iter()
            .map(|p| {
                t.nearest_n::<SquaredEuclidean>(&p.to_array(), std::num::NonZero::new(2).unwrap())
                    [1]
                .distance
                .sqrt()
            })
            .collect();
        d.sort_by(f32::total_cmp);
        d[d.len() / 2]
    };
    let inside = springs::fill_interior(&sample, fill_spacing).unwrap();
    let body = tree(&fine);
    // Precision: every fill point lies in the body (within one lattice spacing of a particle).
    let stray = inside
        .iter()
        .filter(|p| dist(&body, **p) > 1.5 * spacing)
        .count();
    assert!(
        stray * 20 <= inside.len(),
        "{object:?}: {stray} of {} fill points outside the body",
        inside.len()
    );
    // Recall: most of the body deeper than one fill spacing has a fill or sample point within
    // one fill spacing.
    let skin = tree(&surface);
    let filled = tree(&[inside.clone(), sample.clone()].concat());
    let deep: Vec<Vec3> = fine
        .iter()
        .copied()
        .filter(|p| dist(&skin, *p) > fill_spacing)
        .collect();
    let reached = deep
        .iter()
        .filter(|p| dist(&filled, **p) <= fill_spacing)
        .count();
    assert!(deep.len() > 30, "{object:?}: {} deep particles", deep.len());
    assert!(
        reached * 10 >= deep.len() * 9,
        "{object:?}: fill reaches {reached} of {} deep body particles ({} fill points, {} sampled of {} surface)",
        deep.len(),
        inside.len(),
        sample.len(),
        surface.len()
    );
}

#[test]
fn teddy_body_is_filled_from_its_tracked_surface() {
    check(ObjectKind::Teddy, 150);
}

#[test]
fn sloth_body_is_filled_from_its_tracked_surface() {
    check(ObjectKind::Sloth, 150);
}
