//! Motion styles: probing motions do what their documentation promises (fast moves, the object
//! on the table, stops), are reproducible, and are recorded in `truth.json`.

use glam::Vec3;
use world::{Effects, GenConfig, MotionStyle, ObjectKind, Observation, generate};

fn small(object: ObjectKind, motion: MotionStyle) -> GenConfig {
    let mut cfg = GenConfig::fixture(object);
    (
        cfg.train_episodes,
        cfg.val_episodes,
        cfg.episodes_per_recording,
        cfg.tracked,
    ) = (4, 0, 4, 60);
    cfg.observation = Observation::none();
    cfg.effects = Effects::none();
    cfg.gaussian_particles = 0;
    cfg.motion = motion;
    cfg
}

/// Per style: the fastest commanded gripper speed (m/s, between stored frames) and the lowest
/// tracked point over all frames (m).
fn speed_and_lowest(object: ObjectKind, motion: MotionStyle) -> (f32, f32) {
    let data = generate(&small(object, motion)).unwrap();
    assert_eq!(data.truth.motion, motion);
    let mut speed = 0.0f32;
    let mut lowest = f32::INFINITY;
    for (e, _) in &data.episodes {
        let g = e.gripper_positions();
        for w in g.windows(2) {
            speed = speed.max((w[1] - w[0]).length() * world::FPS);
        }
        lowest = e.positions().iter().map(|p| p.z).fold(lowest, f32::min);
    }
    (speed, lowest)
}

#[test]
fn probing_moves_faster_and_lays_hanging_objects_on_the_table() {
    let (everyday_speed, everyday_low) = speed_and_lowest(ObjectKind::Paper, MotionStyle::Everyday);
    let (probing_speed, probing_low) = speed_and_lowest(ObjectKind::Paper, MotionStyle::Probing);
    // Sweeps of 15–30 cm in 0.3–0.5 s peak at 0.6–1.9 m/s (less between 0.1 s frames);
    // everyday drifts and waving stay slower.
    assert!(
        probing_speed > 0.6 && probing_speed > 1.2 * everyday_speed,
        "probing {probing_speed} m/s vs everyday {everyday_speed} m/s"
    );
    // The hanging paper never reaches the table in everyday use; probing drapes it there.
    assert!(
        everyday_low > 0.03,
        "everyday lowest point {everyday_low} m"
    );
    assert!(probing_low < 0.01, "probing lowest point {probing_low} m");
}

#[test]
fn probing_is_reproducible_and_differs_from_everyday() {
    let a = generate(&small(ObjectKind::Sloth, MotionStyle::Probing)).unwrap();
    let b = generate(&small(ObjectKind::Sloth, MotionStyle::Probing)).unwrap();
    let c = generate(&small(ObjectKind::Sloth, MotionStyle::Everyday)).unwrap();
    let grippers = |d: &world::GeneratedDataset| -> Vec<Vec3> {
        d.episodes
            .iter()
            .flat_map(|(e, _)| e.gripper_positions().to_vec())
            .collect()
    };
    assert_eq!(grippers(&a), grippers(&b));
    assert_ne!(grippers(&a), grippers(&c));
}

/// How far a rope's tracked points lie from the line through its two (roughly) farthest-apart
/// points, m.
fn off_line(points: &[Vec3]) -> f32 {
    let a = points[0];
    let b = *points
        .iter()
        .max_by(|p, q| p.distance(a).total_cmp(&q.distance(a)))
        .unwrap();
    let c = *points
        .iter()
        .max_by(|p, q| p.distance(b).total_cmp(&q.distance(b)))
        .unwrap();
    let d = (c - b).normalize();
    points
        .iter()
        .map(|p| (*p - b).reject_from(d).length())
        .fold(0.0, f32::max)
}

#[test]
fn planning_style_drags_the_rope_from_straight_starts() {
    let mut cfg = small(ObjectKind::Rope, MotionStyle::Planning);
    (cfg.train_episodes, cfg.episodes_per_recording) = (8, 1);
    let data = generate(&cfg).unwrap();
    assert_eq!(data.truth.motion, MotionStyle::Planning);
    let mut straight = 0;
    let (mut low_steps, mut high, mut all_steps, mut fastest) = (0, 0.0f32, 0, 0.0f32);
    for (e, _) in &data.episodes {
        // A straight rope's surface points lie within its 1.6 cm diameter of the line.
        if off_line(e.frame(0)) < 0.025 {
            straight += 1;
        }
        let g = e.gripper_positions();
        high = g.iter().map(|p| p.z).fold(high, f32::max);
        for w in g.windows(2) {
            all_steps += 1;
            // Dragging: the gripper near the table moving at least 5 mm per 0.1 s.
            let step = (w[1] - w[0]).length();
            if w[0].z < 0.03 && step > 0.005 {
                low_steps += 1;
            }
            fastest = fastest.max(step * world::FPS);
        }
    }
    // Each recording starts straight with probability 1/2 (4 of them for this seed; the curved
    // ones lie 6–18 cm off a line): both kinds of start must occur among the 8.
    assert!(
        (1..=7).contains(&straight),
        "{straight} of 8 starts straight"
    );
    // About half the steps drag (52 % for this seed): most moves start and end on the table.
    assert!(
        low_steps * 5 > all_steps * 2,
        "{low_steps} of {all_steps} steps drag over the table"
    );
    assert!(high > 0.15, "the gripper never lifted: highest {high} m");
    assert!(fastest < 1.0, "fastest gripper speed {fastest} m/s");
}

#[test]
fn styles_parse_by_name_and_unknown_names_are_errors() {
    for m in MotionStyle::ALL {
        assert_eq!(m.name().parse::<MotionStyle>().unwrap(), m);
    }
    let e = "wiggle".parse::<MotionStyle>().unwrap_err().to_string();
    assert!(e.contains("wiggle") && e.contains("probing"), "{e}");
}

#[test]
fn truth_files_without_a_motion_field_read_as_everyday() {
    let data = generate(&small(ObjectKind::Rope, MotionStyle::Everyday)).unwrap();
    let json = serde_json::to_value(&data.truth).unwrap();
    // Everyday is the default and is not written (older truth files look the same).
    assert!(json.get("motion").is_none());
    let probing = generate(&small(ObjectKind::Rope, MotionStyle::Probing)).unwrap();
    assert_eq!(
        serde_json::to_value(&probing.truth).unwrap()["motion"],
        "probing"
    );
    let truth: world::Truth = serde_json::from_value(json).unwrap();
    assert_eq!(truth.motion, MotionStyle::Everyday);
}

#[test]
fn branches_share_the_start_and_part_after_the_branch_frame() {
    let mut cfg = small(ObjectKind::Rope, MotionStyle::Planning);
    // Two recordings of three branches each, one episode per branch; default tracker noise,
    // so "identical before the branch" covers the observations too.
    (cfg.train_episodes, cfg.episodes_per_recording, cfg.branches) = (6, 1, 3);
    cfg.observation = Observation::default();
    let data = generate(&cfg).unwrap();
    assert_eq!(data.episodes.len(), 6);
    assert_eq!(data.truth.recordings.len(), 2);
    for rec in &data.truth.recordings {
        assert_eq!(rec.branches.len(), 2);
        let trunk = &data.episodes[rec.episodes[0]].0;
        let n = trunk.particles();
        for branch in &rec.branches {
            let f = branch.from_frame;
            assert!((8..40).contains(&f), "branch frame {f}");
            let other = &data.episodes[branch.episodes[0]].0;
            // Everything up to and including the branch frame is shared.
            assert_eq!(
                trunk.positions()[..(f + 1) * n],
                other.positions()[..(f + 1) * n]
            );
            assert_eq!(
                trunk.gripper_positions()[..=f],
                other.gripper_positions()[..=f]
            );
            // The gripper paths part afterwards, and so do the objects.
            let apart = |a: &[Vec3], b: &[Vec3]| {
                a.iter()
                    .zip(b)
                    .map(|(p, q)| p.distance(*q))
                    .fold(0.0, f32::max)
            };
            let grip = apart(trunk.gripper_positions(), other.gripper_positions());
            let rope = apart(&trunk.positions()[39 * n..], &other.positions()[39 * n..]);
            assert!(
                grip > 0.01 && rope > 0.005,
                "gripper {grip} m, rope {rope} m apart"
            );
        }
    }
    // One branch is the plain recording: the same dataset as without branching.
    (cfg.train_episodes, cfg.branches) = (2, 1);
    let plain = generate(&cfg).unwrap();
    assert!(plain.truth.recordings.iter().all(|r| r.branches.is_empty()));
    assert_eq!(
        plain.episodes[1].0.positions(),
        data.episodes[data.truth.recordings[1].episodes[0]]
            .0
            .positions()
    );
}

#[test]
fn branching_everyday_motions_is_a_configuration_error() {
    let mut cfg = small(ObjectKind::Rope, MotionStyle::Everyday);
    cfg.branches = 2;
    let err = generate(&cfg).unwrap_err().to_string();
    assert!(err.contains("planning"), "{err}");
    cfg.branches = 0;
    assert!(generate(&cfg).is_err());
}
