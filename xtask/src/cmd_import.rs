//! `cargo xtask import deform|phystwin <DIR> --out <DATASET>`, `cargo xtask dev-split` and
//! `cargo xtask merge`.

use std::path::PathBuf;

use anyhow::Context;

/// Arguments of `import`.
#[derive(clap::Args)]
pub struct ImportArgs {
    /// Source format.
    #[arg(value_enum)]
    format: SourceFormat,
    /// Source (for `deform`: a DLOk folder holding train/ and eval/; for `phystwin`: a case
    /// folder holding final_data.pkl and split.json, or the pickle itself).
    dir: PathBuf,
    /// Output dataset directory. One that already holds files is refused unless
    /// `--overwrite` is given; the dataset is written beside it and moved into place only
    /// when every source file has converted.
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing dataset at `--out` (once the new one is complete).
    #[arg(long)]
    overwrite: bool,
    /// `phystwin`: keep every N-th frame (default 3: PhysTwin's 30 fps to the paper's 10).
    #[arg(long)]
    every: Option<usize>,
    /// `phystwin`: kept frames per episode (default 40: the paper's 4 s at 10 fps).
    #[arg(long)]
    episode_frames: Option<usize>,
    /// `phystwin`: kept frames between consecutive episodes' starts (default 20: 2 s).
    #[arg(long)]
    stride_frames: Option<usize>,
    /// `phystwin`: how the controller points act on the object (default attach: joined by
    /// springs, as in PhysTwin).
    #[arg(long, value_enum)]
    manipulation: Option<ManipulationArg>,
    /// `phystwin`: radius within which a controller point holds (grasp) or pushes (push)
    /// object points, m (default 0.02; attach does not use it).
    #[arg(long)]
    gripper_radius: Option<f32>,
    /// `phystwin` with attach: how far each controller point's springs reach, m (default 0.04,
    /// PhysTwin's `controller_radius`; a case's fitted value may be given).
    #[arg(long)]
    controller_radius: Option<f32>,
    /// `phystwin` with attach: most springs per controller point (default 50, PhysTwin's
    /// `controller_max_neighbours`).
    #[arg(long)]
    controller_springs: Option<u32>,
    /// `phystwin` with attach: join the controller points by the object's fitted threshold
    /// and spring count instead of a rule of their own (pgrd before 2026-12-07).
    #[arg(long, conflicts_with_all = ["controller_radius", "controller_springs"])]
    controller_like_object: bool,
    /// `phystwin` with attach: take the controller rule PhysTwin fitted for this case from its
    /// `optimal_params.pkl` (`controller_radius`, `controller_max_neighbours`).
    #[arg(
        long,
        value_name = "PKL",
        conflicts_with_all = ["controller_radius", "controller_springs", "controller_like_object"]
    )]
    optimal_params: Option<PathBuf>,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum ManipulationArg {
    /// Each controller point is a particle joined by springs to the object points near it.
    Attach,
    /// Object points near a controller point at an episode's start follow it rigidly.
    Grasp,
    /// Controller points are spheres that push object points.
    Push,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum SourceFormat {
    /// DEFORM cable recordings (pickled [frames][3][markers] lists, 100 Hz).
    Deform,
    /// PhysTwin's processed captures (final_data.pkl: a pickled dict of numpy arrays, 30 fps).
    Phystwin,
}

/// Runs the import and prints a one-line summary per split.
pub fn run(args: &ImportArgs) -> anyhow::Result<()> {
    match args.format {
        SourceFormat::Deform => {
            let phystwin_only = args.every.is_some()
                || args.episode_frames.is_some()
                || args.stride_frames.is_some()
                || args.manipulation.is_some()
                || args.gripper_radius.is_some()
                || args.controller_radius.is_some()
                || args.controller_springs.is_some()
                || args.controller_like_object
                || args.optimal_params.is_some();
            anyhow::ensure!(
                !phystwin_only,
                "--every, --episode-frames, --stride-frames, --manipulation, --gripper-radius and \
                 the --controller-* and --optimal-params flags apply to `import phystwin` only \
             (DEFORM's files are \
                 whole episodes already)"
            );
            let t0 = std::time::Instant::now();
            let staged = crate::staged::StagedDir::new(&args.out, args.overwrite)?;
            let report = dataset::import::deform::import(&args.dir, staged.path())
                .with_context(|| format!("importing DEFORM data from {}", args.dir.display()))?;
            staged.commit()?;
            let count = |s| report.episodes.iter().filter(|e| e.1 == s).count();
            println!(
                "imported {}: {} markers, {} train + {} val episodes -> {} ({:.1} s)",
                report.object,
                report.markers,
                count(dataset::Split::Train),
                count(dataset::Split::Val),
                args.out.display(),
                t0.elapsed().as_secs_f64()
            );
        }
        SourceFormat::Phystwin => import_phystwin(args)?,
    }
    Ok(())
}

fn import_phystwin(args: &ImportArgs) -> anyhow::Result<()> {
    use dataset::import::phystwin::{self, PhysTwinOptions};
    let t0 = std::time::Instant::now();
    let d = PhysTwinOptions::default();
    let fitted = match &args.optimal_params {
        Some(path) => Some(phystwin::read_controller_rule(path).with_context(|| {
            format!("reading the fitted controller rule from {}", path.display())
        })?),
        None => None,
    };
    let opts = PhysTwinOptions {
        every: args.every.unwrap_or(d.every),
        episode_frames: args.episode_frames.unwrap_or(d.episode_frames),
        stride_frames: args.stride_frames.unwrap_or(d.stride_frames),
        manipulation: match args.manipulation {
            None => d.manipulation,
            Some(ManipulationArg::Attach) => dataset::Manipulation::Attach,
            Some(ManipulationArg::Grasp) => dataset::Manipulation::Grasp,
            Some(ManipulationArg::Push) => dataset::Manipulation::Push,
        },
        gripper_radius_m: args.gripper_radius.unwrap_or(d.gripper_radius_m),
        controller_springs: (!args.controller_like_object).then(|| {
            let start = fitted.unwrap_or(dataset::ControllerSprings::PHYSTWIN);
            dataset::ControllerSprings {
                radius_m: args.controller_radius.unwrap_or(start.radius_m),
                max_springs: args.controller_springs.unwrap_or(start.max_springs),
            }
        }),
        ..d
    };
    let controller_flags = args.controller_radius.is_some()
        || args.controller_springs.is_some()
        || args.controller_like_object
        || args.optimal_params.is_some();
    anyhow::ensure!(
        !controller_flags || opts.manipulation == dataset::Manipulation::Attach,
        "the --controller-* flags and --optimal-params apply to --manipulation attach only"
    );
    if let Some(c) = opts.controller_springs {
        anyhow::ensure!(
            c.radius_m.is_finite() && c.radius_m > 0.0,
            "--controller-radius must be a positive number of metres, got {}",
            c.radius_m
        );
    }
    anyhow::ensure!(
        opts.gripper_radius_m.is_finite() && opts.gripper_radius_m >= 0.0,
        "--gripper-radius must be a finite number of metres >= 0, got {}",
        opts.gripper_radius_m
    );
    let staged = crate::staged::StagedDir::new(&args.out, args.overwrite)?;
    let report = phystwin::import(&args.dir, staged.path(), &opts)
        .with_context(|| format!("importing PhysTwin data from {}", args.dir.display()))?;
    staged.commit()?;
    let count = |s| report.episodes.iter().filter(|e| e.split == s).count();
    println!(
        "imported {}: {} frames, {} points ({} never seen, left out), {} controller points; {}; \
         {} train + {} val episodes of {} frames at {} fps, {:.0} % of points seen -> {} ({:.1} s)",
        report.object,
        report.frames,
        report.points,
        report.never_seen,
        report.controllers,
        report.split,
        count(dataset::Split::Train),
        count(dataset::Split::Val),
        report.episode_frames,
        opts.source_fps / opts.every as f32,
        100.0 * report.seen_fraction,
        args.out.display(),
        t0.elapsed().as_secs_f64()
    );
    if opts.manipulation == dataset::Manipulation::Attach {
        match opts.controller_springs {
            Some(c) => println!(
                "controller points join the object by their own rule: up to {} springs within \
                 {} m each ({}; `fit --fit-controller` searches it)",
                c.max_springs,
                c.radius_m,
                match &args.optimal_params {
                    Some(p) => format!("fitted by PhysTwin, from {}", p.display()),
                    None => "--controller-radius, --controller-springs".to_string(),
                }
            ),
            None => println!(
                "controller points join the object by its fitted threshold and spring count"
            ),
        }
    }
    Ok(())
}

/// Arguments of `dev-split`.
#[derive(clap::Args)]
pub struct DevSplitArgs {
    /// Source dataset directory (left unchanged).
    #[arg(long)]
    data: PathBuf,
    /// New dataset directory (must not exist, or be empty).
    #[arg(long)]
    out: PathBuf,
    /// How many of the last training episodes (in file order) become `val`: the same
    /// episodes `train --holdout N` holds out of the source.
    #[arg(
        long,
        required_unless_present = "select_val",
        conflicts_with = "select_val"
    )]
    hold_out: Option<usize>,
    /// Instead of --hold-out: keep the last N `val` episodes as `val` (a selection set for
    /// `train --select-on-val`, e.g. the recordings `gen --val <more>` added) and move the
    /// other `val` episodes to `test`; every training episode stays in `train`.
    #[arg(long)]
    select_val: Option<usize>,
}

/// Writes the development split and prints what went where.
pub fn dev_split(args: &DevSplitArgs) -> anyhow::Result<()> {
    let src = dataset::Dataset::open(&args.data)
        .with_context(|| format!("opening {}", args.data.display()))?;
    let (report, what) = match (args.hold_out, args.select_val) {
        (Some(n), _) => (
            dataset::dev_split(&src, &args.out, n),
            format!("the last {n} training episodes of {}", args.data.display()),
        ),
        (None, Some(n)) => (
            dataset::select_split(&src, &args.out, n),
            format!("the last {n} val episodes of {}", args.data.display()),
        ),
        (None, None) => anyhow::bail!("give --hold-out N or --select-val N"),
    };
    let report = report
        .with_context(|| format!("writing the development split to {}", args.out.display()))?;
    let (first, last) = (report.val_indices.first(), report.val_indices.last());
    println!(
        "{}: {} train, {} val ({what}, dataset indices {}..={}), {} test (the rest of its val, and its test) -> {}",
        src.meta.object,
        report.train,
        report.val,
        first.copied().unwrap_or_default(),
        last.copied().unwrap_or_default(),
        report.test,
        args.out.display()
    );
    Ok(())
}

/// Arguments of `merge`.
#[derive(clap::Args)]
pub struct MergeArgs {
    /// New dataset directory (must not exist, or be empty).
    #[arg(long)]
    out: PathBuf,
    /// `DIR:SPLIT` or `DIR:SPLIT=AS`: the `SPLIT` episodes of the dataset in `DIR`, listed as
    /// `AS` (default `SPLIT`). Repeat it; the merged dataset lists the parts in the order
    /// given, so the part to hold out with `train --holdout` goes last among the training
    /// ones. Every part must be the same object recorded the same way.
    #[arg(long = "part", required = true, value_parser = parse_part)]
    parts: Vec<PartArg>,
}

#[derive(Clone, Debug)]
struct PartArg {
    dir: PathBuf,
    split: dataset::Split,
    as_split: dataset::Split,
}

fn parse_part(s: &str) -> Result<PartArg, String> {
    let (dir, splits) = s
        .rsplit_once(':')
        .ok_or_else(|| format!("`{s}`: expected DIR:SPLIT or DIR:SPLIT=AS"))?;
    let (split, as_split) = splits.split_once('=').unwrap_or((splits, splits));
    if dir.is_empty() {
        return Err(format!("`{s}`: the dataset directory is missing"));
    }
    Ok(PartArg {
        dir: dir.into(),
        split: split.parse()?,
        as_split: as_split.parse()?,
    })
}

/// Writes the merged dataset and prints what came from where.
pub fn merge(args: &MergeArgs) -> anyhow::Result<()> {
    let mut opened: Vec<(PathBuf, dataset::Dataset)> = Vec::new();
    for p in &args.parts {
        if !opened.iter().any(|(d, _)| *d == p.dir) {
            let data = dataset::Dataset::open(&p.dir)
                .with_context(|| format!("opening {}", p.dir.display()))?;
            opened.push((p.dir.clone(), data));
        }
    }
    let find = |dir: &PathBuf| {
        &opened
            .iter()
            .find(|(d, _)| d == dir)
            .expect("opened above")
            .1
    };
    let parts: Vec<dataset::MergePart<'_>> = (args.parts.iter())
        .map(|p| dataset::MergePart {
            data: find(&p.dir),
            split: p.split,
            as_split: p.as_split,
        })
        .collect();
    let report = dataset::merge(&parts, &args.out)
        .with_context(|| format!("merging into {}", args.out.display()))?;
    for (p, n) in args.parts.iter().zip(&report.per_part) {
        println!(
            "{n:4} {} episodes of {} as {}",
            p.split,
            p.dir.display(),
            p.as_split
        );
    }
    let [train, val, test] = report.counts;
    println!(
        "-> {}: {train} train, {val} val, {test} test",
        args.out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::{ImportArgs, ManipulationArg, SourceFormat, parse_part, run};
    use dataset::Split;

    fn phystwin_args(out: std::path::PathBuf) -> ImportArgs {
        ImportArgs {
            format: SourceFormat::Phystwin,
            dir: std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../fixtures/phystwin/rope_lift"),
            out,
            overwrite: false,
            every: None,
            episode_frames: Some(10),
            stride_frames: Some(5),
            manipulation: Some(ManipulationArg::Push),
            gripper_radius: Some(0.03),
            controller_radius: None,
            controller_springs: None,
            controller_like_object: false,
            optimal_params: None,
        }
    }

    #[test]
    fn import_phystwin_takes_its_options_and_deform_refuses_them() {
        let dir = std::env::temp_dir().join(format!("pgrd-import-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        run(&phystwin_args(dir.join("pt"))).unwrap();
        let data = dataset::Dataset::open(dir.join("pt")).unwrap();
        assert_eq!(data.meta.manipulation, dataset::Manipulation::Push);
        assert_eq!((data.meta.gripper_radius, data.meta.fps), (0.03, 10.0));
        assert_eq!(data.split_indices(Split::Train).len(), 4);
        let args = ImportArgs {
            format: SourceFormat::Deform,
            ..phystwin_args(dir.join("dlo"))
        };
        let err = format!("{:#}", run(&args).unwrap_err());
        assert!(err.contains("apply to `import phystwin` only"), "{err}");
        let args = ImportArgs {
            gripper_radius: Some(f32::NAN),
            ..phystwin_args(dir.join("nan"))
        };
        let err = format!("{:#}", run(&args).unwrap_err());
        assert!(err.contains("--gripper-radius"), "{err}");
        // The controllers' own rule: for attach only, written as given.
        let attach = |out: &str, radius| ImportArgs {
            manipulation: Some(ManipulationArg::Attach),
            controller_radius: radius,
            controller_springs: Some(7),
            ..phystwin_args(dir.join(out))
        };
        run(&attach("own", Some(0.025))).unwrap();
        let data = dataset::Dataset::open(dir.join("own")).unwrap();
        let rule = data.meta.controller_springs.unwrap();
        assert_eq!((rule.radius_m, rule.max_springs), (0.025, 7));
        let err = format!("{:#}", run(&attach("bad", Some(0.0))).unwrap_err());
        assert!(err.contains("--controller-radius"), "{err}");
        // A case's fitted rule, from PhysTwin's optimal_params.pkl.
        let fitted = |out: &str, manipulation| ImportArgs {
            manipulation,
            optimal_params: Some(
                std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                    .join("../fixtures/phystwin/rope_lift/optimal_params.pkl"),
            ),
            ..phystwin_args(dir.join(out))
        };
        run(&fitted("fitted", Some(ManipulationArg::Attach))).unwrap();
        let data = dataset::Dataset::open(dir.join("fitted")).unwrap();
        let rule = data.meta.controller_springs.unwrap();
        assert_eq!((rule.radius_m, rule.max_springs), (0.035, 24));
        let push = fitted("fitted-push", Some(ManipulationArg::Push));
        let err = format!("{:#}", run(&push).unwrap_err());
        assert!(err.contains("attach only"), "{err}");
        let err = format!(
            "{:#}",
            run(&ImportArgs {
                optimal_params: Some(dir.join("missing.pkl")),
                ..fitted("missing", Some(ManipulationArg::Attach))
            })
            .unwrap_err()
        );
        assert!(err.contains("missing.pkl"), "{err}");
        let args = ImportArgs {
            controller_radius: Some(0.03),
            ..phystwin_args(dir.join("push"))
        };
        let err = format!("{:#}", run(&args).unwrap_err());
        assert!(err.contains("attach only"), "{err}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn parts_name_a_directory_a_split_and_optionally_a_new_split() {
        let p = parse_part("data/rope:train").unwrap();
        assert_eq!(
            (p.dir.to_str(), p.split, p.as_split),
            (Some("data/rope"), Split::Train, Split::Train)
        );
        let p = parse_part("a:b/rope:test=val").unwrap();
        assert_eq!(
            (p.dir.to_str(), p.split, p.as_split),
            (Some("a:b/rope"), Split::Test, Split::Val)
        );
        for bad in [
            "data/rope",
            "data/rope:training",
            ":train",
            "data/rope:train=dev",
        ] {
            assert!(parse_part(bad).is_err(), "{bad}");
        }
    }
}
