//! `cargo xtask diagnose` (where / which / how far for one dataset and fitted run) and
//! `cargo xtask diagnose-bench` (the diagnosis scored on reference-world data whose effect was
//! withheld from the model; `cmd_diagnose_bench.rs`). Method: `docs/gap.md`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use dataset::{Dataset, Split};
use gap::{BaseEffect, Candidate, DiagnoseConfig, Diagnosis};
use scene::{Protocol, Scene};

use crate::common::{
    BackboneFile, ProtocolArg, SubstepArg, backbone_path, load_scenes, predict_tracked,
    read_backbone, read_residual, scenes,
};
use crate::report::write_json;

#[path = "cmd_diagnose_bench.rs"]
mod bench;
pub use bench::{DiagnoseBenchArgs, run_bench};

/// Arguments of `diagnose`.
#[derive(clap::Args)]
pub struct DiagnoseArgs {
    /// Dataset directory (train split for refits, val split held out).
    #[arg(long)]
    pub data: PathBuf,
    /// Run directory holding backbone.json (from `cargo xtask fit`).
    #[arg(long)]
    pub run: PathBuf,
    /// Report directory (created): report.json and report.html.
    #[arg(long)]
    pub out: PathBuf,
    /// CMA-ES candidates per generation of each refit.
    #[arg(long, default_value_t = 8)]
    pub population: usize,
    /// Generations of each refit.
    #[arg(long, default_value_t = 10)]
    pub generations: usize,
    /// Training episodes sampled per generation.
    #[arg(long, default_value_t = 8)]
    pub samples: usize,
    /// Seed of the refits and the bootstrap.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Bootstrap resamples over held-out episodes.
    #[arg(long, default_value_t = 2000)]
    pub resamples: usize,
    /// Final selection of every refit: the optimiser's mean and the best candidates
    /// of this many of the best generations are scored on all training episodes and the best
    /// is kept (0: the best candidate by its own generation's sampled episodes).
    #[arg(long, default_value_t = 3)]
    pub rescore: usize,
    /// Most training episodes the rescoring scores: a subset of this many, drawn with the
    /// seed, when there are more (0: all; with 100 training episodes the default 64 saves
    /// about 13 % of each refit's rollouts, `docs/gap.md`).
    #[arg(long, default_value_t = 64)]
    pub rescore_scenes: usize,
    /// Race the library candidates' refits (0: off): every candidate gets half the
    /// generations, and only the best N by training loss get the rest and the rescoring; the
    /// control and the probe always get the whole budget. Faster, at some risk to the verdict
    /// (`docs/gap.md`, "Racing the refits").
    #[arg(long, default_value_t = 0)]
    pub race: usize,
    /// Window of each episode.
    #[arg(long, value_enum, default_value_t = ProtocolArg::Paper)]
    pub protocol: ProtocolArg,
    /// Comma-separated candidate effects (default: the nine library effects). Names starting
    /// with `+` are added to the nine instead, e.g. `+gravity-scale` (an extra candidate,
    /// offered on request only; `docs/gap.md`).
    #[arg(long)]
    pub candidates: Option<String>,
    /// Effects already in the model, refitted with the backbone in the control and in every
    /// candidate refit, and not candidates themselves: comma-separated `name` (starts at the
    /// effect's usual strength) or `name=v1[:v2]` (e.g. `bending=0.12`, as printed after a
    /// diagnosis). Default: the effects in the run's backbone.json, if any.
    #[arg(long = "with")]
    pub with: Option<String>,
    /// Skip the generic external-field probe (the verdict can then not be `unknown`).
    #[arg(long)]
    pub no_probe: bool,
    /// Name the significant candidate with the largest shrinkage even when others are tied
    /// with it on held-out error (by default the signature breaks such ties).
    #[arg(long)]
    pub no_tie_break: bool,
    /// Least held-out shrinkage (fraction) a candidate, and the effect inside it, must reach
    /// besides an interval above 0 to count as significant (`gap::VerdictRule`).
    #[arg(long, default_value_t = gap::VerdictRule::default().min_shrinkage)]
    pub min_shrinkage: f64,
    /// Ignore `<run>/residual.safetensors` (by default a trained network there is scored on
    /// the held-out episodes: how much of the gap is learnable, and `unknown` when it beats
    /// every library model).
    #[arg(long)]
    pub no_network: bool,
    /// Also write this run directory with the model the diagnosis refitted: when the verdict
    /// is an effect, the model that has it, i.e. `backbone.json` with the refitted backbone
    /// parameters and the base effects plus the verdict's, at their refitted values (for
    /// `eval`, `train`, `render` and another `diagnose`, which then starts from those effects
    /// as its base). With the verdict `none`
    /// or `unknown` it holds the control refit instead (the run's own effects refitted, none
    /// added; the command prints its held-out MDE beside the model as given). A refined
    /// stiffness field of the run (`refine`) is kept as it is: the diagnosis holds it fixed.
    #[arg(long)]
    pub write_run: Option<PathBuf>,
    /// How the simulator chooses its substep in every rollout of the diagnosis (the backbone
    /// as given included): every contender is refitted and compared under it. Default: the
    /// run's own. `--write-run` records it in the model it writes.
    #[arg(long, value_enum)]
    pub substep: Option<SubstepArg>,
    /// Print only the verdict line.
    #[arg(long)]
    pub quiet: bool,
}

/// `a,b` names the candidates; `+a,+b` adds them to the nine library effects.
fn parse_candidates(list: &str) -> anyhow::Result<Vec<Candidate>> {
    let names: Vec<&str> = list.split(',').map(str::trim).collect();
    let adding = names.iter().filter(|n| n.starts_with('+')).count();
    if adding != 0 && adding != names.len() {
        anyhow::bail!("--candidates: either name every candidate or add with '+' to all, not both");
    }
    let mut out = if adding > 0 {
        Candidate::LIBRARY.to_vec()
    } else {
        Vec::new()
    };
    for name in names {
        let c = Candidate::parse(name.trim_start_matches('+'))?;
        if !out.contains(&c) {
            out.push(c);
        }
    }
    Ok(out)
}

fn config_from(args: &DiagnoseArgs, run_effects: &[BaseEffect]) -> anyhow::Result<DiagnoseConfig> {
    let candidates = match &args.candidates {
        Some(list) => parse_candidates(list)?,
        None => Candidate::LIBRARY.to_vec(),
    };
    Ok(DiagnoseConfig {
        population: args.population,
        generations: args.generations,
        samples: args.samples,
        seed: args.seed,
        resamples: args.resamples,
        rescore: args.rescore,
        rescore_scenes: args.rescore_scenes,
        race: args.race,
        candidates,
        base: match &args.with {
            Some(list) => BaseEffect::parse_list(list)?,
            None => run_effects.to_vec(),
        },
        probe: !args.no_probe,
        rule: gap::VerdictRule {
            signature_tie_break: !args.no_tie_break,
            min_shrinkage: args.min_shrinkage,
            ..gap::VerdictRule::default()
        },
        ..DiagnoseConfig::default()
    })
}

/// Writes `<out>/report.json` and `<out>/report.html`.
pub fn write_report(out: &Path, diagnosis: &Diagnosis, title: &str) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    write_json(&out.join("report.json"), diagnosis)?;
    let html = gap::render_html(diagnosis, title);
    dataset::write_atomic(&out.join("report.html"), html.as_bytes())
        .with_context(|| format!("writing {}", out.join("report.html").display()))
}

/// One line on a diagnosis's network comparison ([`gap::Learnable`]).
pub(crate) fn learnable_line(l: &gap::Learnable) -> String {
    format!(
        "residual network: held-out MDE {:.3} cm (its backbone {:.3} cm); against {}: {:+.1}% [{:+.1}, {:+.1}]{}",
        l.network_mde_cm,
        l.backbone_mde_cm,
        l.model,
        100.0 * l.vs_model.shrinkage,
        100.0 * l.vs_model.ci95[0],
        100.0 * l.vs_model.ci95[1],
        if l.changed_verdict {
            " -> verdict unknown"
        } else {
            ""
        }
    )
}

/// Per held-out episode, the MDE (cm, mean over steps) of the backbone with the network and of
/// the backbone alone. An episode whose hybrid rollout fails gets the backbone's error (with a
/// warning), so a failure cannot make the network look better.
pub(crate) fn network_errors(
    data: &Dataset,
    protocol: Protocol,
    backbone: &BackboneFile,
    options: &residual::BackboneOptionsFn,
    net: &residual::ResidualNet,
) -> anyhow::Result<(Vec<f64>, Vec<f64>)> {
    use rayon::prelude::*;
    // The network was trained on the run's backbone, under the run's integrator.
    let params = &backbone.params;
    let val = load_scenes(data, Split::Val, protocol, &backbone.substep.scene_config())?;
    let mde = |scene: &Scene, pred: &[Vec<glam::Vec3>]| -> anyhow::Result<f64> {
        let e = scene::score_steps(scene, pred, false)?;
        Ok(100.0 * e.iter().map(|x| x.mde).sum::<f64>() / e.len().max(1) as f64)
    };
    let rows: Vec<anyhow::Result<(f64, f64)>> = val
        .par_iter()
        .map(|(i, scene)| {
            let alone = mde(scene, &predict_tracked(scene, params, options, None, None)?)?;
            let history = residual::History::from_episode(scene, &data.load_episode(*i)?, data.meta.fps)?;
            let with = match predict_tracked(scene, params, options, Some(net), Some(&history)) {
                Ok(p) => mde(scene, &p)?,
                Err(e) => {
                    eprintln!("warning: episode {i}: the hybrid rollout failed ({e:#}); scored as its backbone");
                    alone
                }
            };
            Ok((with, alone))
        })
        .collect();
    let rows = rows.into_iter().collect::<anyhow::Result<Vec<_>>>()?;
    Ok(rows.into_iter().unzip())
}

/// `--write-run` must not replace the diagnosed run's own backbone, nor put a backbone under a
/// network trained on another one; checked before the diagnosis runs.
fn check_write_run(dir: &Path, run: &Path) -> anyhow::Result<()> {
    let same = match (std::fs::canonicalize(dir), std::fs::canonicalize(run)) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    anyhow::ensure!(
        !same,
        "--write-run {} is the diagnosed run itself; name a new directory",
        dir.display()
    );
    let net = dir.join("residual.safetensors");
    anyhow::ensure!(
        !net.exists(),
        "--write-run {}: it holds a residual network trained on another backbone ({}); name a new directory",
        dir.display(),
        net.display()
    );
    Ok(())
}

/// Runs `diagnose`.
pub fn run(args: &DiagnoseArgs) -> anyhow::Result<Diagnosis> {
    let t0 = Instant::now();
    let data = Dataset::open(&args.data)?;
    let backbone = read_backbone(&args.run)?;
    let protocol: Protocol = args.protocol.into();
    let substep = args.substep.unwrap_or(backbone.substep);
    let train = scenes(&data, Split::Train, protocol, substep)?;
    let val = scenes(&data, Split::Val, protocol, substep)?;
    if let Some(dir) = &args.write_run {
        check_write_run(dir, &args.run)?;
    }
    let mut config = config_from(args, &backbone.effects)?;
    // A refined stiffness field stays at its values in every model; the refits move the
    // global stiffness it multiplies.
    config.field = backbone.refined.as_ref().map(|r| r.log_factor.clone());
    let quiet = args.quiet;
    if !quiet {
        println!("  substep rule: {}", substep.name());
    }
    let d = gap::diagnose(&train, &val, &backbone.params, &config, &mut |line| {
        if !quiet {
            println!("  {line}");
        }
    })?;
    let mut d = d;
    if !args.no_network
        && let Some(net) = read_residual(&args.run)?
    {
        let options = backbone.options_for(&data, protocol)?;
        let (network, backbone_alone) = network_errors(&data, protocol, &backbone, &options, &net)?;
        gap::add_learnable(&mut d, &network, &backbone_alone)?;
        if let Some(l) = &d.learnable {
            println!("  {}", learnable_line(l));
        }
    }
    let title = format!("{} ({})", data.meta.object, args.data.display());
    write_report(&args.out, &d, &title)?;
    let how = d.how_far.as_ref().map_or(String::new(), |h| {
        format!(
            "; adding {}: held-out MDE {:.3} -> {:.3} cm ({:.1}% shrinkage)",
            h.effect,
            h.before.mde_cm,
            h.after.mde_cm,
            100.0 * h.shrinkage_mde
        )
    });
    println!(
        "diagnosis of {}: verdict {}{} ({:.1} s) -> {}",
        data.meta.object,
        d.verdict,
        how,
        t0.elapsed().as_secs_f64(),
        args.out.join("report.html").display()
    );
    // The user's next step: diagnose again with the verdict's effect in the model. With the
    // verdict `none` / `unknown` there is no effect to add, but the control refit (the same
    // model refitted on the train split) may still differ from the model as given, for better
    // or worse: `--write-run` writes it, with both scores.
    let added = Candidate::parse(&d.verdict).ok();
    if added.is_some() || args.write_run.is_some() {
        let (params, effects) = d.refitted_model(&backbone.params, added)?;
        if added.is_some() {
            let list: Vec<String> = effects.iter().map(BaseEffect::label).collect();
            println!(
                "to diagnose the model with it: --with {} (values refitted here)",
                list.join(",")
            );
        }
        if let Some(dir) = &args.write_run {
            let mut file = backbone.clone();
            file.params = params;
            file.effects = effects;
            file.protocol = protocol.name().to_string();
            file.substep = substep;
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            write_json(&backbone_path(dir), &file)?;
            if added.is_some() {
                println!(
                    "wrote {} ({}, refitted here)",
                    backbone_path(dir).display(),
                    file.label()
                );
            } else {
                println!(
                    "verdict {}: no effect to add; wrote the control refit to {} ({}; held-out MDE {:.3} cm, as given {:.3} cm)",
                    d.verdict,
                    backbone_path(dir).display(),
                    file.label(),
                    d.control.heldout_mde_cm,
                    d.backbone_as_given.mde_cm
                );
            }
        }
    }
    Ok(d)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn candidates_are_named_or_added_to_the_library() {
        let named = parse_candidates("drag, bending").unwrap();
        assert_eq!(named, vec![Candidate::Drag, Candidate::Bending]);
        let added = parse_candidates("+gravity-scale").unwrap();
        assert_eq!(added.len(), Candidate::LIBRARY.len() + 1);
        assert_eq!(added.last(), Some(&Candidate::GravityScale));
        // Adding one already there changes nothing.
        assert_eq!(
            parse_candidates("+drag").unwrap(),
            Candidate::LIBRARY.to_vec()
        );
        assert!(parse_candidates("drag,+bending").is_err());
        assert!(parse_candidates("+gravity").is_err());
    }
}
