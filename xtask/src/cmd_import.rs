//! `cargo xtask import deform <DIR> --out <DATASET>` and `cargo xtask dev-split`.

use std::path::PathBuf;

use anyhow::Context;

/// Arguments of `import`.
#[derive(clap::Args)]
pub struct ImportArgs {
    /// Source format.
    #[arg(value_enum)]
    format: SourceFormat,
    /// Source directory (for `deform`: a DLOk folder holding train/ and eval/).
    dir: PathBuf,
    /// Output dataset directory.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum SourceFormat {
    /// DEFORM cable recordings (pickled [frames][3][markers] lists, 100 Hz).
    Deform,
}

/// Runs the import and prints a one-line summary per split.
pub fn run(args: &ImportArgs) -> anyhow::Result<()> {
    match args.format {
        SourceFormat::Deform => {
            let t0 = std::time::Instant::now();
            let report = dataset::import::deform::import(&args.dir, &args.out)
                .with_context(|| format!("importing DEFORM data from {}", args.dir.display()))?;
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
