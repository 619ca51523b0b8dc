//! The `cargo xtask gen` command as an example binary of this crate (same source file), so the
//! generator can be run before or without xtask:
//! `cargo run --release -p pgrd-world --example gen -- --object rope --out /tmp/rope`.

#[path = "../../../xtask/src/cmd_gen.rs"]
mod cmd_gen;
#[path = "../../../xtask/src/staged.rs"]
mod staged;

use clap::Parser;

/// Generate a reference-world dataset.
#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    args: cmd_gen::GenArgs,
}

fn main() -> anyhow::Result<()> {
    cmd_gen::run(&Cli::parse().args)
}
