//! JSON has no NaN: `serde_json` writes an f64 NaN (an empty bin's range, an EMD not computed)
//! as `null`. These read `null` back as NaN, so a report survives the round trip.

use serde::{Deserialize, Deserializer};

fn or_nan(v: Option<f64>) -> f64 {
    v.unwrap_or(f64::NAN)
}

pub(crate) fn f64<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Option::<f64>::deserialize(d).map(or_nan)
}

pub(crate) fn pair<'de, D: Deserializer<'de>>(d: D) -> Result<[f64; 2], D::Error> {
    <[Option<f64>; 2]>::deserialize(d).map(|[a, b]| [or_nan(a), or_nan(b)])
}

pub(crate) fn vec<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
    Vec::<Option<f64>>::deserialize(d).map(|v| v.into_iter().map(or_nan).collect())
}
