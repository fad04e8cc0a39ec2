//! Whole numbers as JSON writers send them. JSON Schema counts `2191.0` as an integer, and
//! numpy, JavaScript and every writer that holds numbers as `f64` send it so; serde's `u64`
//! refuses it. These accept an integral number in range, written either way, and refuse
//! fractions, negatives, NaN-like values and numbers beyond `u64::MAX` with a clear message.
use serde::de::{self, Deserializer, Visitor};

/// `2^64` as an `f64`: every integral `f64` below it fits a `u64`.
const TWO_POW_64: f64 = 18_446_744_073_709_551_616.0;

struct WholeU64;

impl<'de> Visitor<'de> for WholeU64 {
    type Value = u64;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("a whole number within 0..=18446744073709551615")
    }

    fn visit_u64<E: de::Error>(self, v: u64) -> Result<u64, E> {
        Ok(v)
    }

    fn visit_i64<E: de::Error>(self, v: i64) -> Result<u64, E> {
        u64::try_from(v).map_err(|_| E::invalid_value(de::Unexpected::Signed(v), &self))
    }

    fn visit_f64<E: de::Error>(self, v: f64) -> Result<u64, E> {
        if v.is_finite() && v.fract() == 0.0 && (0.0..TWO_POW_64).contains(&v) {
            // Exact: integral and below 2^64.
            Ok(v as u64)
        } else {
            Err(E::invalid_value(de::Unexpected::Float(v), &self))
        }
    }
}

/// A `u64` field written `7` or `7.0` (`#[serde(deserialize_with = "integral::u64")]`).
pub fn u64<'de, D: Deserializer<'de>>(d: D) -> Result<u64, D::Error> {
    d.deserialize_any(WholeU64)
}

/// An optional `u64` field written `7`, `7.0` or `null`.
pub fn option_u64<'de, D: Deserializer<'de>>(d: D) -> Result<Option<u64>, D::Error> {
    struct Optional;
    impl<'de> Visitor<'de> for Optional {
        type Value = Option<u64>;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("null or a whole number within 0..=18446744073709551615")
        }
        fn visit_none<E: de::Error>(self) -> Result<Self::Value, E> {
            Ok(None)
        }
        fn visit_unit<E: de::Error>(self) -> Result<Self::Value, E> {
            Ok(None)
        }
        fn visit_some<D: Deserializer<'de>>(self, d: D) -> Result<Self::Value, D::Error> {
            u64(d).map(Some)
        }
    }
    d.deserialize_option(Optional)
}

#[cfg(test)]
mod tests {
    use serde::Deserialize;

    #[derive(Debug, Deserialize, PartialEq)]
    struct T {
        #[serde(deserialize_with = "super::u64")]
        n: u64,
        #[serde(default, deserialize_with = "super::option_u64")]
        o: Option<u64>,
    }

    fn parse(s: &str) -> Result<T, String> {
        serde_json::from_str(s).map_err(|e| e.to_string())
    }

    #[test]
    fn integral_numbers_are_taken_either_way_and_the_rest_refused() {
        assert_eq!(parse(r#"{"n": 2191}"#).unwrap(), T { n: 2191, o: None });
        assert_eq!(
            parse(r#"{"n": 2191.0, "o": 3.0}"#).unwrap(),
            T {
                n: 2191,
                o: Some(3)
            }
        );
        assert_eq!(
            parse(r#"{"n": 1e3, "o": null}"#).unwrap(),
            T { n: 1000, o: None }
        );
        let max = parse(r#"{"n": 18446744073709551615}"#).unwrap();
        assert_eq!(max.n, u64::MAX);
        for bad in [
            r#"{"n": 1.5}"#,
            r#"{"n": -1}"#,
            r#"{"n": -1.0}"#,
            r#"{"n": 1.9e29}"#,
            r#"{"n": 18446744073709551616}"#,
            r#"{"n": "7"}"#,
            r#"{"n": 1, "o": 0.5}"#,
        ] {
            let e = parse(bad).unwrap_err();
            assert!(
                e.contains("whole number") || e.contains("invalid"),
                "{bad}: {e}"
            );
        }
    }
}
