//! Models of several members (an ensemble, each member on its own trajectory): MPPI scores a
//! candidate by its cost under every member, `mean + member_risk · sd`. A particle glued to the
//! gripper, seen by members that each add their own offset, makes the expected plans exact.

use glam::Vec3;
use plan::{
    ForwardModel, MemberPredictions, ModelState, Mppi, MppiConfig, Objective, PlanError, Workspace,
};
use springs::Actions;

/// One particle at the gripper plus `offset(gripper)`, per member.
struct Glued {
    members: Vec<fn(Vec3) -> Vec3>,
    /// Fail every candidate whose first step moves down (under the last member only).
    last_fails_downwards: bool,
}

impl Glued {
    fn new(members: Vec<fn(Vec3) -> Vec3>) -> Self {
        Glued {
            members,
            last_fails_downwards: false,
        }
    }

    fn member(&self, k: usize, a: &Actions) -> plan::Result<Vec<Vec<Vec3>>> {
        let g = |t: usize| a.frame(t).unwrap().positions[0];
        if self.last_fails_downwards && k + 1 == self.members.len() && g(1).z < g(0).z {
            return Err(PlanError::Model("diverged".into()));
        }
        Ok((1..a.num_frames())
            .map(|t| vec![g(t) + self.members[k](g(t))])
            .collect())
    }
}

impl ForwardModel for Glued {
    fn num_particles(&self) -> usize {
        1
    }
    fn name(&self) -> &str {
        "glued"
    }
    fn rollout(&self, _: &ModelState, a: &Actions) -> plan::Result<Vec<Vec<Vec3>>> {
        self.member(0, a)
    }
    fn rollout_members_batch(
        &self,
        _: &ModelState,
        actions: &[Actions],
    ) -> Vec<plan::Result<MemberPredictions>> {
        actions
            .iter()
            .map(|a| (0..self.members.len()).map(|k| self.member(k, a)).collect())
            .collect()
    }
}

/// The gripper's positions after `steps` replans towards `target`, each plan's first step
/// executed exactly.
fn plan_path(model: &dyn ForwardModel, target: Vec3, risk: f64, steps: usize) -> Vec<Vec3> {
    let ws = Workspace {
        min: Vec3::splat(-1.0),
        max: Vec3::splat(1.0),
    };
    let objective = Objective::new(&[target], ws).unwrap();
    let cfg = MppiConfig {
        member_risk: risk,
        samples: 32,
        // The members' offsets flatten the cost near its minimum (a sum of cones 10 cm
        // away): a colder weighting than the default 1 cm resolves it.
        temperature: 0.002,
        ..MppiConfig::simple()
    };
    let mut mppi = Mppi::new(cfg, 1).unwrap();
    let mut g = Vec3::ZERO;
    let mut path = Vec::new();
    for _ in 0..steps {
        let state = ModelState::at_rest(vec![g]);
        g = mppi.plan(model, &state, &[g], &objective).unwrap().next[0];
        path.push(g);
    }
    path
}

/// Where a path settled: the mean of its last 10 positions (MPPI's plan jitters by about its
/// noise around a minimum).
fn settled(path: &[Vec3]) -> Vec3 {
    let tail = &path[path.len() - 10..];
    tail.iter().copied().sum::<Vec3>() / tail.len() as f32
}

fn zero(_: Vec3) -> Vec3 {
    Vec3::ZERO
}

#[test]
fn identical_members_plan_as_one_model() {
    let target = Vec3::new(0.2, -0.1, 0.05);
    let one = Glued::new(vec![zero]);
    let two = Glued::new(vec![zero, zero]);
    for risk in [0.0, 1.0] {
        assert_eq!(
            plan_path(&one, target, risk, 12),
            plan_path(&two, target, risk, 12),
            "risk {risk}"
        );
    }
}

/// Three members that disagree by offsets at the corners of an equilateral triangle around
/// the particle: the candidate with the lowest mean cost puts the gripper on the target (the
/// triangle's Fermat point), while planning with the first member alone puts it 10 cm away.
#[test]
fn every_member_counts() {
    let target = Vec3::new(0.2, 0.0, 0.0);
    fn a(_: Vec3) -> Vec3 {
        Vec3::new(0.0, 0.1, 0.0)
    }
    fn b(_: Vec3) -> Vec3 {
        Vec3::new(0.0, -0.05, 0.0866)
    }
    fn c(_: Vec3) -> Vec3 {
        Vec3::new(0.0, -0.05, -0.0866)
    }
    let end = settled(&plan_path(&Glued::new(vec![a, b, c]), target, 0.0, 40));
    assert!(end.distance(target) < 0.015, "ended at {end}");
    let end = settled(&plan_path(&Glued::new(vec![a]), target, 0.0, 40));
    assert!(
        end.distance(target - Vec3::new(0.0, 0.1, 0.0)) < 0.015,
        "the first member alone ended at {end}"
    );
}

/// Three members, two glued to the gripper and one that lifts the particle by half the
/// gripper's x: their mean cost is lowest with the gripper on the target (two members against
/// one), but there they disagree by 10 cm; with a risk weight of 2 the plan goes about 5 cm
/// down, where the members' costs are equal.
#[test]
fn a_risk_weight_goes_where_the_members_agree() {
    let target = Vec3::new(0.2, 0.0, 0.0);
    fn lifts(g: Vec3) -> Vec3 {
        Vec3::new(0.0, 0.0, 0.5 * g.x)
    }
    let model = Glued::new(vec![zero, zero, lifts]);
    let neutral = settled(&plan_path(&model, target, 0.0, 40));
    assert!(neutral.distance(target) < 0.015, "ended at {neutral}");
    let cautious = settled(&plan_path(&model, target, 2.0, 40));
    // Where the costs agree, z = −x/4, the mean cost 2·|(x − 0.2, 0, x/4)| is lowest at
    // x = 0.2 / 1.0625: 4.7 cm from the target.
    let x = 0.2 / 1.0625;
    let agreed = Vec3::new(x, 0.0, -0.25 * x);
    assert!(cautious.distance(agreed) < 0.02, "ended at {cautious}");
}

#[test]
fn a_member_failing_drops_the_candidate_alone() {
    let target = Vec3::new(0.2, 0.0, 0.1);
    let mut model = Glued::new(vec![zero, zero]);
    model.last_fails_downwards = true;
    let ws = Workspace {
        min: Vec3::splat(-1.0),
        max: Vec3::splat(1.0),
    };
    let objective = Objective::new(&[target], ws).unwrap();
    let mut mppi = Mppi::new(MppiConfig::simple(), 1).unwrap();
    let step = mppi
        .plan(
            &model,
            &ModelState::at_rest(vec![Vec3::ZERO]),
            &[Vec3::ZERO],
            &objective,
        )
        .unwrap();
    assert!(step.failed > 0 && step.failed < step.rollouts, "{step:?}");
}

#[test]
fn a_negative_or_non_finite_risk_is_refused() {
    for risk in [-0.1, f64::NAN, f64::INFINITY] {
        let cfg = MppiConfig {
            member_risk: risk,
            ..MppiConfig::simple()
        };
        assert!(Mppi::new(cfg, 1).is_err(), "risk {risk}");
    }
}

/// Each plan reports how much the members disagree about its best candidate: not at all for
/// identical members, by half their cost difference for two that differ everywhere.
#[test]
fn the_plan_reports_the_members_spread_about_its_best_candidate() {
    let ws = Workspace {
        min: Vec3::splat(-1.0),
        max: Vec3::splat(1.0),
    };
    let objective = Objective::new(&[Vec3::new(0.2, 0.0, 0.0)], ws).unwrap();
    let state = ModelState::at_rest(vec![Vec3::ZERO]);
    let plan = |model: &Glued| {
        let mut mppi = Mppi::new(MppiConfig::simple(), 1).unwrap();
        mppi.plan(model, &state, &[Vec3::ZERO], &objective).unwrap()
    };
    let same = plan(&Glued::new(vec![zero, zero]));
    assert_eq!(same.best_member_sd, vec![0.0; 3]);
    // Member 1 sees the particle 10 cm higher wherever the gripper goes; at a target on the
    // table the costs (two-sided Chamfer of one point, twice the distance) then differ by
    // between 0 and 0.2, so the spread lies in (0, 0.1].
    fn up(_: Vec3) -> Vec3 {
        Vec3::new(0.0, 0.0, 0.1)
    }
    let apart = plan(&Glued::new(vec![zero, up]));
    assert_eq!(apart.best_member_sd.len(), 3);
    assert!(
        apart
            .best_member_sd
            .iter()
            .all(|&s| s > 0.0 && s <= 0.1 + 1e-9),
        "{:?}",
        apart.best_member_sd
    );
}
