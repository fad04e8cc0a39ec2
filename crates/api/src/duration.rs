//! The one duration syntax of every command line and environment variable (`crossview serve`,
//! `crossview-loadtest`): a number with a unit, `250ms`, `1.5s`, `2m`, `1h`. A bare `0` is
//! zero; any other bare number is refused, so `200` never means milliseconds to one command
//! and seconds to another.
use std::time::Duration;

/// Longest duration accepted (a year): beyond it a value is a typo, and the bound keeps the
/// conversion from overflowing.
const MAX_SECONDS: f64 = 365.0 * 86_400.0;

/// Parses `250ms`, `1.5s`, `2m` (or `2min`), `1h`, or `0`.
pub fn parse_duration(s: &str) -> Result<Duration, String> {
    let s = s.trim();
    let split = s.find(|c: char| c.is_ascii_alphabetic()).unwrap_or(s.len());
    let (num, unit) = (s[..split].trim(), s[split..].trim());
    let v: f64 = num
        .parse()
        .map_err(|_| format!("'{s}' is not a duration (e.g. 250ms, 1.5s, 2m, 1h)"))?;
    let scale = match unit {
        "ms" => 1e-3,
        "s" => 1.0,
        "m" | "min" => 60.0,
        "h" => 3600.0,
        "" if v == 0.0 => 0.0,
        "" => return Err(format!("'{s}' needs a unit: {s}ms, {s}s, {s}m or {s}h")),
        _ => return Err(format!("'{s}': unknown unit '{unit}' (ms, s, m, h)")),
    };
    let secs = v * scale;
    if !(0.0..=MAX_SECONDS).contains(&secs) {
        return Err(format!("'{s}' is out of range (0 to 365 days)"));
    }
    Ok(Duration::from_secs_f64(secs))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_syntax() {
        assert_eq!(parse_duration("200ms"), Ok(Duration::from_millis(200)));
        assert_eq!(parse_duration("1.5s"), Ok(Duration::from_millis(1500)));
        assert_eq!(parse_duration(" 2m "), Ok(Duration::from_secs(120)));
        assert_eq!(parse_duration("2min"), Ok(Duration::from_secs(120)));
        assert_eq!(parse_duration("1h"), Ok(Duration::from_secs(3600)));
        assert_eq!(parse_duration("0"), Ok(Duration::ZERO));
        for bad in [
            "50",
            "1.5",
            "-1s",
            "soon",
            "3 parsecs",
            "NaNs",
            "1e30s",
            "inf",
            "",
        ] {
            assert!(parse_duration(bad).is_err(), "{bad}");
        }
        assert!(parse_duration("50").unwrap_err().contains("needs a unit"));
    }
}
