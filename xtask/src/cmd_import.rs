//! `cargo xtask import deform <DIR> --out <DATASET>`.

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
