//! Successive halving of refits ([`DiagnoseConfig::race`]): run each for half the
//! generations, look at every one on the same [`RACE_SCENES`] training scenes, and finish only
//! the best. A finished refit is bit for bit the uninterrupted one ([`fit::PausedFit`]), so a
//! race changes a diagnosis only where the halfway order differs from the final one.

use std::time::Instant;

use fit::FitConfig;
use scene::Scene;

use crate::GapError;
use crate::candidates::{Candidate, CandidateFamily};
use crate::diagnose::{DiagnoseConfig, Model, RACE_SCENES};

/// A raced refit's first half: started, advanced half of `config.generations`, and its look
/// (the optimiser's mean, the best generation's best and, with
/// [`DiagnoseConfig::keep_start`], the refit's start, on [`RACE_SCENES`] training scenes).
fn first_half(
    train: &[Scene],
    family: &CandidateFamily,
    config: &DiagnoseConfig,
    fit_cfg: &FitConfig,
) -> Result<(fit::PausedFit, fit::FitOutcome), GapError> {
    let mut run = fit::PausedFit::start(train, family, fit_cfg)?;
    run.advance(train, family, config.generations.div_ceil(2))?;
    let look = run.clone().finish(train, family, 1, RACE_SCENES)?;
    Ok((run, look))
}

/// A kept refit's second half (up to `generations` in all) and final rescoring: bit for bit
/// the unraced refit of that many generations.
fn second_half(
    train: &[Scene],
    family: &CandidateFamily,
    mut run: fit::PausedFit,
    config: &DiagnoseConfig,
    generations: usize,
) -> Result<fit::FitOutcome, GapError> {
    run.advance(train, family, generations)?;
    Ok(run.finish(train, family, config.rescore, config.rescore_scenes)?)
}

/// The race of [`DiagnoseConfig::race`]: the refits of the library candidates among `all`
/// (the probe's two starts race in [`race_probe_starts`]), index-aligned with `all`; `None`
/// where the candidate is not raced (the probe, or every candidate when there is no race or
/// nothing to cut).
pub(crate) fn race(
    train: &[Scene],
    all: &[Candidate],
    config: &DiagnoseConfig,
    fit_cfg: &FitConfig,
    family_of: &dyn Fn(Option<Candidate>) -> Result<CandidateFamily, GapError>,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<Option<Model>>, GapError> {
    let racers: Vec<usize> = (0..all.len())
        .filter(|&k| all[k] != Candidate::ExternalField)
        .collect();
    let mut out: Vec<Option<Model>> = all.iter().map(|_| None).collect();
    if config.race == 0 || config.race >= racers.len() {
        return Ok(out);
    }
    let half = config.generations.div_ceil(2);
    let mut runs = Vec::new();
    for &k in &racers {
        let t = Instant::now();
        let family = family_of(Some(all[k]))?;
        let (run, look) = first_half(train, &family, config, fit_cfg)?;
        runs.push((k, family, run, look, t.elapsed().as_secs_f64()));
    }
    let mut order: Vec<usize> = (0..runs.len()).collect();
    order.sort_by(|&a, &b| {
        runs[a]
            .3
            .best_loss
            .total_cmp(&runs[b].3.best_loss)
            .then(a.cmp(&b))
    });
    let kept = &order[..config.race];
    progress(&format!(
        "race: {} candidates after {half} of {} generations, by training loss on {} scenes: {}; kept {}",
        runs.len(),
        config.generations,
        RACE_SCENES.min(train.len()),
        order
            .iter()
            .map(|&i| format!("{} {:.3e}", all[runs[i].0].name(), runs[i].3.best_loss))
            .collect::<Vec<_>>()
            .join(", "),
        config.race
    ));
    for (i, (k, family, run, look, wall)) in runs.into_iter().enumerate() {
        let model = if kept.contains(&i) {
            let t = Instant::now();
            let done = second_half(train, &family, run, config, config.generations)?;
            Model {
                family,
                real: done.best,
                train_loss: done.best_loss,
                wall_s: wall + t.elapsed().as_secs_f64(),
                raced_out: false,
            }
        } else {
            Model {
                family,
                real: look.best,
                train_loss: look.best_loss,
                wall_s: wall,
                raced_out: true,
            }
        };
        out[k] = Some(model);
    }
    Ok(out)
}

/// The probe's two starts raced ([`DiagnoseConfig::race`] > 0): both refits (`families`, the
/// one started at the residuals' focus first, then the broad one) run half the generations,
/// and only the one with the lower training loss on [`RACE_SCENES`] scenes then is finished
/// (to [`DiagnoseConfig::probe_generations`] in all).
/// Returns the finished refit, both halfway losses (focus, broad; m²) and whether the focus
/// start won (ties go to the broad start, as between finished refits).
pub(crate) fn race_probe_starts(
    train: &[Scene],
    families: [CandidateFamily; 2],
    config: &DiagnoseConfig,
    fit_cfg: &FitConfig,
) -> Result<(Model, [f64; 2], bool), GapError> {
    let t = Instant::now();
    let mut runs = Vec::with_capacity(2);
    let mut looks = [0.0; 2];
    for (family, look) in families.iter().zip(&mut looks) {
        let (run, halfway) = first_half(train, family, config, fit_cfg)?;
        *look = halfway.best_loss;
        runs.push(run);
    }
    let from_focus = looks[0] < looks[1];
    let [focus_family, broad_family] = families;
    let (family, run) = if from_focus {
        (focus_family, runs.swap_remove(0))
    } else {
        (broad_family, runs.swap_remove(1))
    };
    let done = second_half(train, &family, run, config, config.probe_generations())?;
    let model = Model {
        family,
        real: done.best,
        train_loss: done.best_loss,
        wall_s: t.elapsed().as_secs_f64(),
        raced_out: false,
    };
    Ok((model, looks, from_focus))
}
