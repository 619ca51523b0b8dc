//! Bit-exact serde adapters for floating-point state.
//!
//! Checkpoints must resume to exactly the same sequence of candidates, so every `f64` in the
//! optimiser state has to survive a serialise/deserialise round trip bit for bit. Text formats
//! do not guarantee that (serde_json's default float parser may be off by one ulp, and it cannot
//! store infinities at all), so floats are written as Rust's shortest round-trip decimal string
//! (`{:?}`: `"0.1"`, `"1e-8"`, `"inf"`) and read back with `str::parse`, which rounds correctly.

use serde::de::Error as _;
use serde::{Deserialize, Deserializer, Serializer};

fn to_text(x: f64) -> String {
    format!("{x:?}")
}

fn from_text<E: serde::de::Error>(s: &str) -> Result<f64, E> {
    s.parse::<f64>()
        .map_err(|_| E::custom(format!("`{s}` is not a floating-point number")))
}

/// A single `f64`.
pub(crate) mod scalar {
    use super::*;

    pub(crate) fn serialize<S: Serializer>(x: &f64, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&to_text(*x))
    }

    pub(crate) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        let s = String::deserialize(d)?;
        from_text(&s)
    }
}

/// A `Vec<f64>`.
pub(crate) mod vec {
    use super::*;

    pub(crate) fn serialize<S: Serializer>(x: &[f64], s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(x.iter().map(|&v| to_text(v)))
    }

    pub(crate) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
        let texts = Vec::<String>::deserialize(d)?;
        texts.iter().map(|t| from_text(t)).collect()
    }
}

/// An `Option<f64>`.
pub(crate) mod opt {
    use super::*;

    pub(crate) fn serialize<S: Serializer>(x: &Option<f64>, s: S) -> Result<S::Ok, S::Error> {
        match x {
            Some(v) => s.serialize_some(&to_text(*v)),
            None => s.serialize_none(),
        }
    }

    pub(crate) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
        match Option::<String>::deserialize(d)? {
            Some(t) => from_text(&t).map(Some),
            None => Ok(None),
        }
    }
}

/// A `Vec<Vec<f64>>` (a population of points).
pub(crate) mod nested {
    use super::*;

    pub(crate) fn serialize<S: Serializer>(x: &[Vec<f64>], s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(
            x.iter()
                .map(|row| row.iter().map(|&v| to_text(v)).collect::<Vec<_>>()),
        )
    }

    pub(crate) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<Vec<f64>>, D::Error> {
        let rows = Vec::<Vec<String>>::deserialize(d)?;
        rows.iter()
            .map(|row| row.iter().map(|t| from_text(t)).collect())
            .collect()
    }
}

/// A `u128` (the RNG word position), stored as a decimal string because several serde formats
/// (and JavaScript readers of JSON) cannot represent integers above 2^53 or 2^64.
pub(crate) mod big {
    use super::*;

    pub(crate) fn serialize<S: Serializer>(x: &u128, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&x.to_string())
    }

    pub(crate) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<u128, D::Error> {
        let s = String::deserialize(d)?;
        s.parse::<u128>()
            .map_err(|_| D::Error::custom(format!("`{s}` is not an unsigned integer")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_round_trip_is_bit_exact() {
        let values = [
            0.1,
            1.0 / 3.0,
            -2.2250738585072014e-308,
            5e-324,
            1.2345678901234567e-5,
            f64::MAX,
            f64::INFINITY,
            f64::NEG_INFINITY,
            -0.0,
        ];
        for v in values {
            let back: f64 = from_text::<serde::de::value::Error>(&to_text(v)).unwrap();
            assert_eq!(back.to_bits(), v.to_bits(), "{v:?}");
        }
        let nan: f64 = from_text::<serde::de::value::Error>(&to_text(f64::NAN)).unwrap();
        assert!(nan.is_nan());
    }
}
