//! `cargo xtask ensemble`: combine trained residual networks into one model whose residual is
//! their mean (`residual::ResidualNet::ensemble`), written as a run that `eval`, `render`,
//! `plan` and `train --init-from`'s refusal all see as one network.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use serde::Serialize;

use crate::common;

/// Arguments of `ensemble`.
#[derive(clap::Args)]
pub struct EnsembleArgs {
    /// Members: run directories of `cargo xtask train` (their residual.safetensors, or with
    /// `--member-step best-trained` a snapshot) or network files (`*.safetensors` with the
    /// `.json` beside). All must share one configuration and be trained on one backbone.
    #[arg(required = true, num_args = 1..)]
    members: Vec<PathBuf>,
    /// Output run directory: gets the backbone's backbone.json, the ensemble as
    /// residual.safetensors / residual.json, and ensemble.json (what was combined).
    #[arg(long)]
    run: PathBuf,
    /// Run whose backbone.json the networks were trained on (default: the first member that is
    /// a run directory). Member run directories with another backbone.json are refused.
    #[arg(long)]
    backbone_run: Option<PathBuf>,
    /// Which network of a member run directory: `selected` (its residual.safetensors, the
    /// held-out choice, which may be the backbone itself) or `best-trained` (the snapshot,
    /// `train --snapshot-every`, with the lowest held-out MDE among trained steps, step 0
    /// excluded; needs `train --holdout`).
    #[arg(long, value_enum, default_value = "selected")]
    member_step: MemberStep,
    /// How the members' residuals combine: `mean`, or `agreement` (the mean shrunk per
    /// particle by |m|² / (|m|² + s²) where the members disagree; `residual::EnsembleRule`).
    #[arg(long, value_enum, default_value = "mean")]
    rule: Rule,
    /// Average the members' parameters into one network instead of combining their residuals
    /// (stochastic weight averaging; one network's cost per step). Meaningful only for
    /// snapshots of one training run (e.g. its `snapshots/step_*/residual.safetensors`), not
    /// for networks of different seeds. Only with `--rule mean`.
    #[arg(long)]
    average_weights: bool,
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
enum Rule {
    Mean,
    Agreement,
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
enum MemberStep {
    Selected,
    BestTrained,
}

/// File name of the record an ensemble's run holds (what was combined); `train` refuses runs
/// that have one.
pub const RECORD: &str = "ensemble.json";

/// One member as recorded in ensemble.json.
#[derive(Debug, Serialize)]
struct Member {
    /// The network file read.
    file: PathBuf,
    /// Optimiser step of that network, when the member's train.json says.
    step: Option<usize>,
    /// Its held-out MDE in the member's own selection, cm, when recorded.
    heldout_mde_cm: Option<f64>,
}

/// Held-out selection record of a training run (the fields read here).
#[derive(serde::Deserialize)]
struct Selection {
    steps: Vec<usize>,
    mde_cm: Vec<Option<f64>>,
    best_step: usize,
}

fn read_selection(run: &Path) -> anyhow::Result<Option<Selection>> {
    let path = run.join("train.json");
    if !path.exists() {
        return Ok(None);
    }
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let value: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    match value.get("selection") {
        None | Some(serde_json::Value::Null) => Ok(None),
        Some(s) => serde_json::from_value(s.clone())
            .map(Some)
            .with_context(|| format!("reading the selection of {}", path.display())),
    }
}

/// The network file of member `path` and what its run says about it.
fn resolve(path: &Path, pick: MemberStep) -> anyhow::Result<Member> {
    if path.is_file() {
        return Ok(Member {
            file: path.to_path_buf(),
            step: None,
            heldout_mde_cm: None,
        });
    }
    if !path.is_dir() {
        bail!(
            "member {} is neither a run directory nor a file",
            path.display()
        );
    }
    let sel = read_selection(path)?;
    let mde_at = |step: usize| {
        sel.as_ref().and_then(|s| {
            s.steps
                .iter()
                .zip(&s.mde_cm)
                .rev()
                .find(|(t, _)| **t == step)
                .and_then(|(_, m)| *m)
        })
    };
    match pick {
        MemberStep::Selected => {
            let file = path.join("residual.safetensors");
            if !file.exists() {
                bail!(
                    "{} has no residual.safetensors (run `cargo xtask train`)",
                    path.display()
                );
            }
            let step = sel.as_ref().map(|s| s.best_step);
            Ok(Member {
                file,
                step,
                heldout_mde_cm: step.and_then(mde_at),
            })
        }
        MemberStep::BestTrained => {
            let Some(s) = &sel else {
                bail!(
                    "{}: `--member-step best-trained` needs a run trained with --holdout",
                    path.display()
                );
            };
            let file_at = |step: usize| {
                let snap = path
                    .join("snapshots")
                    .join(format!("step_{step:05}"))
                    .join("residual.safetensors");
                if snap.exists() {
                    Some(snap)
                } else if step == s.best_step {
                    Some(path.join("residual.safetensors"))
                } else {
                    None
                }
            };
            let best = s
                .steps
                .iter()
                .zip(&s.mde_cm)
                .filter(|(t, m)| **t > 0 && m.is_some_and(f64::is_finite))
                .filter_map(|(t, m)| Some((*t, (*m)?, file_at(*t)?)))
                .min_by(|a, b| a.1.total_cmp(&b.1));
            let Some((step, mde, file)) = best else {
                bail!(
                    "{}: no trained step with a held-out MDE has a network on disk \
                     (train with --snapshot-every at the --select-every steps)",
                    path.display()
                );
            };
            Ok(Member {
                file,
                step: Some(step),
                heldout_mde_cm: Some(mde),
            })
        }
    }
}

/// Writes the ensemble run and prints one line per member.
pub fn run(args: &EnsembleArgs) -> anyhow::Result<()> {
    if args.average_weights && args.rule != Rule::Mean {
        bail!("--average-weights makes one network; it takes no --rule");
    }
    // A member named twice would silently count double in the mean.
    for (i, m) in args.members.iter().enumerate() {
        let same = |o: &PathBuf| match (m.canonicalize(), o.canonicalize()) {
            (Ok(a), Ok(b)) => a == b,
            _ => m == o,
        };
        if args.members[..i].iter().any(same) {
            bail!(
                "member {} is named twice; every member counts once",
                m.display()
            );
        }
    }
    let backbone_run = match &args.backbone_run {
        Some(r) => r.clone(),
        None => args
            .members
            .iter()
            .find(|m| m.is_dir())
            .cloned()
            .context("no member is a run directory: name the backbone with --backbone-run")?,
    };
    let backbone_file = common::backbone_path(&backbone_run);
    let backbone = std::fs::read(&backbone_file)
        .with_context(|| format!("reading {}", backbone_file.display()))?;
    for m in args.members.iter().filter(|m| m.is_dir()) {
        let theirs = common::backbone_path(m);
        if theirs.exists() && std::fs::read(&theirs)? != backbone {
            bail!(
                "{} was trained on another backbone than {}",
                m.display(),
                backbone_file.display()
            );
        }
    }
    let out_net = args.run.join("residual.safetensors");
    if out_net.exists() && !args.run.join(RECORD).exists() {
        bail!(
            "{} already holds a trained network; write the ensemble to a new run directory",
            args.run.display()
        );
    }
    let members = args
        .members
        .iter()
        .map(|m| resolve(m, args.member_step))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let nets = members
        .iter()
        .map(|m| {
            residual::ResidualNet::load(&m.file)
                .with_context(|| format!("loading {}", m.file.display()))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let ensemble = if args.average_weights {
        residual::ResidualNet::average_weights(&nets)?
    } else {
        residual::ResidualNet::ensemble(nets)?.with_ensemble_rule(match args.rule {
            Rule::Mean => residual::EnsembleRule::Mean,
            Rule::Agreement => residual::EnsembleRule::Agreement,
        })
    };
    std::fs::create_dir_all(&args.run)
        .with_context(|| format!("creating {}", args.run.display()))?;
    dataset::write_atomic(&common::backbone_path(&args.run), &backbone)?;
    ensemble
        .save(&out_net)
        .with_context(|| format!("writing {}", out_net.display()))?;
    let record = serde_json::json!({
        "backbone_run": backbone_run,
        "member_step": args.member_step,
        "rule": args.rule,
        "average_weights": args.average_weights,
        "members": members,
    });
    dataset::write_atomic(
        &args.run.join(RECORD),
        serde_json::to_string_pretty(&record)?.as_bytes(),
    )?;
    for (k, m) in members.iter().enumerate() {
        let step = m.step.map_or("-".into(), |s| s.to_string());
        let mde = m
            .heldout_mde_cm
            .map_or("-".into(), |v| format!("{v:.3} cm held out"));
        println!("member {k}: {} (step {step}, {mde})", m.file.display());
    }
    let what = if args.average_weights {
        format!("weight average of {} networks", members.len())
    } else {
        format!("ensemble of {} networks", ensemble.ensemble_size())
    };
    println!(
        "{what} ({} parameters) -> {}",
        ensemble.parameter_count(),
        out_net.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run directory with a selection record over steps 0, 250, 500, 750 and snapshot files
    /// (empty: `resolve` only looks for them) at the steps given.
    fn fake_run(dir: &Path, mde: [f64; 4], snapshots: &[usize]) {
        std::fs::create_dir_all(dir).unwrap();
        let train = serde_json::json!({
            "selection": { "steps": [0, 250, 500, 750], "mde_cm": mde, "best_step": 0 }
        });
        std::fs::write(dir.join("train.json"), train.to_string()).unwrap();
        for s in snapshots {
            let snap = dir.join("snapshots").join(format!("step_{s:05}"));
            std::fs::create_dir_all(&snap).unwrap();
            std::fs::write(snap.join("residual.safetensors"), b"").unwrap();
        }
    }

    #[test]
    fn best_trained_skips_step_zero_and_missing_snapshots() {
        let dir = std::env::temp_dir().join(format!("pgrd-ens-pick-{}", std::process::id()));
        // Step 0 (the backbone) is lowest and step 500 second, but 500 has no file on disk.
        fake_run(&dir, [1.0, 2.5, 1.5, 2.0], &[250, 750]);
        let m = resolve(&dir, MemberStep::BestTrained).unwrap();
        assert_eq!(m.step, Some(750));
        assert_eq!(m.heldout_mde_cm, Some(2.0));
        assert!(
            m.file
                .ends_with("snapshots/step_00750/residual.safetensors")
        );
        // `selected` wants the run's own network, which this run lacks.
        let err = resolve(&dir, MemberStep::Selected).unwrap_err().to_string();
        assert!(err.contains("no residual.safetensors"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn members_without_a_selection_or_a_path_are_refused() {
        let dir = std::env::temp_dir().join(format!("pgrd-ens-nosel-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let err = resolve(&dir, MemberStep::BestTrained)
            .unwrap_err()
            .to_string();
        assert!(err.contains("--holdout"), "{err}");
        let err = resolve(&dir.join("absent"), MemberStep::Selected)
            .unwrap_err()
            .to_string();
        assert!(err.contains("neither a run directory nor a file"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn members_on_another_backbone_and_trained_outputs_are_refused() {
        let dir = std::env::temp_dir().join(format!("pgrd-ens-bb-{}", std::process::id()));
        let (a, b, out) = (dir.join("a"), dir.join("b"), dir.join("out"));
        for (run, text) in [(&a, "{\"k\": 1}"), (&b, "{\"k\": 2}")] {
            std::fs::create_dir_all(run).unwrap();
            std::fs::write(common::backbone_path(run), text).unwrap();
        }
        let args = |members: Vec<PathBuf>| EnsembleArgs {
            members,
            run: out.clone(),
            backbone_run: None,
            member_step: MemberStep::Selected,
            rule: Rule::Mean,
            average_weights: false,
        };
        let err = run(&args(vec![a.clone(), b.clone()]))
            .unwrap_err()
            .to_string();
        assert!(err.contains("another backbone"), "{err}");
        let err = run(&args(vec![a.clone(), dir.join("a/../a")]))
            .unwrap_err()
            .to_string();
        assert!(err.contains("named twice"), "{err}");
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(out.join("residual.safetensors"), b"").unwrap();
        let err = run(&args(vec![a.clone()])).unwrap_err().to_string();
        assert!(err.contains("already holds a trained network"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn averaged_weights_make_one_network() {
        let dir = std::env::temp_dir().join(format!("pgrd-ens-avg-{}", std::process::id()));
        let (bb, out) = (dir.join("bb"), dir.join("out"));
        std::fs::create_dir_all(&bb).unwrap();
        std::fs::write(common::backbone_path(&bb), "{}").unwrap();
        let cfg = residual::ModelConfig::tiny();
        let files: Vec<PathBuf> = (1..=2)
            .map(|seed| {
                let f = dir.join(format!("n{seed}.safetensors"));
                residual::ResidualNet::new(&cfg, seed)
                    .unwrap()
                    .save(&f)
                    .unwrap();
                f
            })
            .collect();
        let mut args = EnsembleArgs {
            members: files.clone(),
            run: out.clone(),
            backbone_run: Some(bb.clone()),
            member_step: MemberStep::Selected,
            rule: Rule::Agreement,
            average_weights: true,
        };
        let err = run(&args).unwrap_err().to_string();
        assert!(err.contains("no --rule"), "{err}");
        args.rule = Rule::Mean;
        run(&args).unwrap();
        let got = residual::ResidualNet::load(&out.join("residual.safetensors")).unwrap();
        assert_eq!(got.ensemble_size(), 1);
        let nets: Vec<_> = files
            .iter()
            .map(|f| residual::ResidualNet::load(f).unwrap())
            .collect();
        let want = residual::ResidualNet::average_weights(&nets).unwrap();
        for ((_, g), (_, w)) in got.named_vars().iter().zip(want.named_vars().iter()) {
            let d = (g.as_tensor() - w.as_tensor())
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap();
            assert_eq!(d, 0.0);
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
