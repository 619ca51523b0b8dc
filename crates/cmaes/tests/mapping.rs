//! Property tests of the normalisation mapping and of the box reflection.

use cmaes::{Bounds, Parameter, Parameters, Scale};
use proptest::prelude::*;

fn parameter() -> impl Strategy<Value = Parameter> {
    (
        prop_oneof![Just(Scale::Linear), Just(Scale::Log)],
        -3.0f64..3.0,
        0.01f64..6.0,
    )
        .prop_map(|(scale, a, span)| match scale {
            // Log ranges: lower in [1e-3, 1e3], upper up to 6 decades above.
            Scale::Log => Parameter::log("p", 10f64.powf(a), 10f64.powf(a + span)),
            Scale::Linear => Parameter::linear("p", a * 100.0, a * 100.0 + span * 50.0),
        })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn normalised_to_real_and_back(p in parameter(), u in 0.0f64..=1.0) {
        let params = Parameters::new(vec![p]).unwrap();
        let real = params.to_real(&[u]).unwrap();
        let back = params.to_normalised(&real).unwrap();
        prop_assert!((back[0] - u).abs() < 1e-12, "{u} -> {real:?} -> {back:?}");
    }

    #[test]
    fn real_to_normalised_and_back(p in parameter(), t in 0.0f64..=1.0) {
        let value = p.lower + t * (p.upper - p.lower);
        let params = Parameters::new(vec![p]).unwrap();
        let u = params.to_normalised(&[value]).unwrap();
        prop_assert!((0.0..=1.0).contains(&u[0]));
        let back = params.to_real(&u).unwrap();
        prop_assert!((back[0] - value).abs() <= 1e-12 * value.abs().max(1.0),
            "{value} -> {u:?} -> {back:?}");
    }

    #[test]
    fn integers_survive_the_round_trip(p in parameter(), t in 0.0f64..=1.0, u in 0.0f64..=1.0) {
        let p = p.integer();
        prop_assume!(p.lower.ceil() <= p.upper.floor());
        let k = (p.lower + t * (p.upper - p.lower)).round().clamp(p.lower.ceil(), p.upper.floor());
        let params = Parameters::new(vec![p]).unwrap();
        let back = params.to_real(&params.to_normalised(&[k]).unwrap()).unwrap();
        prop_assert_eq!(back[0], k);
        let any = params.to_real(&[u]).unwrap()[0];
        prop_assert_eq!(any, any.round());
    }

    #[test]
    fn reflection_lands_in_the_box_and_fixes_its_interior(
        lo in -5.0f64..5.0, width in 0.01f64..10.0, x in -100.0f64..100.0,
    ) {
        let b = Bounds { lower: vec![lo], upper: vec![lo + width] };
        let y = b.reflect(&[x])[0];
        prop_assert!(y >= lo && y <= lo + width, "{x} -> {y}");
        if x >= lo && x <= lo + width {
            prop_assert!((y - x).abs() <= 1e-12 * x.abs().max(1.0));
        }
        // Mirror symmetry about the lower face.
        let mirrored = b.reflect(&[2.0 * lo - x])[0];
        prop_assert!((mirrored - y).abs() < 1e-9 * (1.0 + x.abs()), "{y} vs {mirrored}");
    }
}
