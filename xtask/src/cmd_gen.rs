//! `cargo xtask gen`: write a reference-world dataset (see `docs/world.md`).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use world::{Effects, GenConfig, MotionStyle, ObjectKind, Observation};

/// Size preset of a generated dataset.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Preset {
    /// 100 train + 20 val episodes, full-resolution fine model, default tracked counts.
    Full,
    /// The `fixtures/` size: 3 train + 2 val episodes, coarse fine model, 150 tracked.
    Fixture,
}

/// Arguments of `cargo xtask gen`.
#[derive(clap::Args, Clone, Debug)]
pub struct GenArgs {
    /// Object: rope, paper, flag, sloth, duster, teddy, or `all` (each into <out>/<object>).
    #[arg(long)]
    pub object: String,
    /// Output directory. One that already holds files is refused unless `--overwrite` is
    /// given; the dataset is written beside it and moved into place only when complete.
    #[arg(long)]
    pub out: PathBuf,
    /// Replace an existing dataset at `--out` (once the new one is complete).
    #[arg(long)]
    pub overwrite: bool,
    /// Effects: `default`, `none`, or a comma-separated list of effect names.
    #[arg(long, default_value = "default")]
    pub effects: String,
    /// Observation model: `default` (noise, drift, occlusion) or `none`.
    #[arg(long, default_value = "default")]
    pub observation: String,
    /// Training episodes [default: 100, or 3 with --preset fixture].
    #[arg(long)]
    pub episodes: Option<usize>,
    /// Validation episodes [default: 20, or 2 with --preset fixture].
    #[arg(long)]
    pub val: Option<usize>,
    /// Seed of every random choice.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Episodes cut from one continuous recording [default: 10]; fewer means more recordings,
    /// each starting from a freshly placed object.
    #[arg(long)]
    pub episodes_per_recording: Option<usize>,
    /// Tracked particles [default: per object, or 150 with --preset fixture].
    #[arg(long)]
    pub tracked: Option<usize>,
    /// Gripper motions: `everyday` (each object's usual manipulation), `probing` (fast
    /// sweeps, holds, slides over the table, jerks: motions that excite the diagnosis's
    /// effects) or `planning` (MPPI-like moves from the rest pose: drags, lifts, lowers); the
    /// pushed teddy is poked in every style.
    #[arg(long, default_value_t = MotionStyle::Everyday)]
    pub motion: MotionStyle,
    /// Gripper continuations per recording (`--motion planning` only): each recording is
    /// replayed this many times from the same start, the gripper paths parting after about
    /// 40 % of it, so the data show the same state under different actions.
    #[arg(long, default_value_t = 1)]
    pub branches: usize,
    /// Gauss–Seidel sweeps over the links per XPBD substep (1: the world every dataset so far
    /// was made with). More bring the solve closer to the nominal material where one sweep
    /// does not converge, e.g. a sheet with a large mass contrast (docs/world.md, "Solver").
    #[arg(long, default_value_t = 1)]
    pub link_sweeps: usize,
    /// Dataset size preset.
    #[arg(long, value_enum, default_value = "full")]
    pub preset: Preset,
    /// Also render frames 0, 13, 26 and 39 of the episode whose gripper travels farthest to this
    /// PNG (`{object}` in the path is replaced by the object's name).
    #[arg(long)]
    pub preview: Option<PathBuf>,
    /// Render this episode (dataset index) instead of the busiest one.
    #[arg(long, requires = "preview")]
    pub preview_episode: Option<usize>,
}

/// Runs `gen`.
pub fn run(args: &GenArgs) -> anyhow::Result<()> {
    let objects: Vec<ObjectKind> = if args.object == "all" {
        ObjectKind::ALL.to_vec()
    } else {
        vec![args.object.parse()?]
    };
    for object in objects {
        let mut cfg = match args.preset {
            Preset::Full => GenConfig::new(object),
            Preset::Fixture => GenConfig::fixture(object),
        };
        cfg.effects = Effects::parse(&args.effects, object)?;
        cfg.observation = Observation::parse(&args.observation)?;
        cfg.seed = args.seed;
        cfg.motion = args.motion;
        cfg.branches = args.branches;
        cfg.link_sweeps = args.link_sweeps;
        if let Some(e) = args.episodes {
            cfg.train_episodes = e;
        }
        if let Some(e) = args.episodes_per_recording {
            cfg.episodes_per_recording = e;
        }
        if let Some(v) = args.val {
            cfg.val_episodes = v;
        }
        if let Some(t) = args.tracked {
            cfg.tracked = t;
        }
        let dir = if args.object == "all" {
            args.out.join(object.name())
        } else {
            args.out.clone()
        };
        // Checked before the minutes of simulation, not after.
        let staged = crate::staged::StagedDir::new(&dir, args.overwrite)?;

        let bar = ProgressBar::new(0);
        bar.set_style(
            ProgressStyle::with_template("{msg:>8} [{bar:30}] {pos}/{len} recordings {elapsed}")
                .context("progress style")?
                .progress_chars("=> "),
        );
        bar.set_message(object.name());
        let start = Instant::now();
        let data = world::generate_with_progress(&cfg, &|done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        })?;
        let simulated = start.elapsed().as_secs_f64();
        data.write(staged.path())
            .with_context(|| format!("writing {}", dir.display()))?;
        staged.commit()?;
        bar.finish_and_clear();
        println!(
            "{}: {} episodes ({} train, {} val), {} tracked of {} fine particles, effects [{}] -> {} ({:.1} s)",
            object,
            data.episodes.len(),
            cfg.train_episodes,
            cfg.val_episodes,
            cfg.tracked,
            data.truth.fine_particles,
            data.truth
                .effects_enabled
                .iter()
                .map(|e| e.name())
                .collect::<Vec<_>>()
                .join(","),
            dir.display(),
            simulated,
        );
        if let Some(p) = &args.preview {
            let path = PathBuf::from(p.to_string_lossy().replace("{object}", object.name()));
            let travel = |e: &dataset::Episode| -> f32 {
                (1..e.frames())
                    .map(|t| e.gripper_frame(t)[0].distance(e.gripper_frame(t - 1)[0]))
                    .sum()
            };
            let chosen = match args.preview_episode {
                Some(k) => data.episodes.get(k).with_context(|| {
                    format!(
                        "--preview-episode {k}: only {} episodes",
                        data.episodes.len()
                    )
                })?,
                None => data
                    .episodes
                    .iter()
                    .max_by(|a, b| travel(&a.0).total_cmp(&travel(&b.0)))
                    .context("no episode to render")?,
            };
            world::render_strip(&chosen.0, &[0, 13, 26, 39], data.meta.gripper_radius, &path)?;
            println!("{object}: preview -> {}", path.display());
        }
    }
    Ok(())
}
