//! The historian's keys: `HISTORY*` of a PLC section (what is recorded) and
//! of `[*]` (where, how long, how often it is made durable), and the forms
//! of their values that the other kinds of key do not cover: mask lists,
//! deadbands, stamp pairs and retention limits.

use std::collections::HashMap;
use std::time::Duration;

use plccoms_protocol::value::Delta;

use super::diag::Diags;
use super::ini::Entry;
use super::Severity;

/// What the historian records of a section (`HISTORY*` keys).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct History {
    /// `HISTORY`: variable masks (`*` wildcards); empty: nothing recorded.
    pub masks: Vec<String>,
    /// `HISTORY_DELTA`: a change smaller than or equal to this is not
    /// recorded (0: every change), as the delta of `EN:`.
    pub delta: Deadband,
    /// `HISTORY_HEARTBEAT`: an unchanged value is recorded again this often
    /// (zero: never).
    pub heartbeat: Duration,
    /// `HISTORY_TRIGGER`: a BOOL variable whose rising edge captures every
    /// recorded variable at each cycle from `pre` cycles before to `post`
    /// cycles after.
    pub trigger: Option<String>,
    pub pre: u32,
    pub post: u32,
    /// `HISTORY_STAMP`: variables whose samples carry the time the PLC
    /// stamped in another variable.
    pub stamps: Vec<StampPair>,
}

impl History {
    /// Whether the section records anything.
    pub fn enabled(&self) -> bool {
        !self.masks.is_empty()
    }
}

/// A deadband, parsed as `EN:`'s delta (finite and non-negative, so equality
/// is an equivalence).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Deadband(pub Delta);

impl Eq for Deadband {}

/// `VALUE_VAR:STAMP_VAR` of `HISTORY_STAMP`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StampPair {
    pub value: String,
    pub stamp: String,
}

/// `HISTORY_RETENTION`: day files older than `days`, and the oldest ones
/// while all of them take more than `bytes`, are deleted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Retention {
    pub days: Option<u32>,
    pub bytes: Option<u64>,
}

/// The historian's forms of value (a [`super::Kind::Form`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Form {
    /// Comma-separated variable masks.
    Masks,
    /// A non-negative decimal number.
    Deadband,
    /// Comma-separated `VALUE_VAR:STAMP_VAR` pairs.
    Stamps,
    /// `<n>d` and/or a size (`500MB`, `10GiB`), comma-separated.
    Retention,
}

impl Form {
    /// What the form allows, for messages.
    pub fn allowed(self) -> &'static str {
        match self {
            Form::Masks => "variable names or masks with *, comma-separated",
            Form::Deadband => "a non-negative number",
            Form::Stamps => "VALUE_VAR:STAMP_VAR pairs, comma-separated",
            Form::Retention => "days (30d) and/or a size (500MB, 10GiB), comma-separated",
        }
    }

    /// A good value other than the default, for tests.
    pub fn example(self) -> &'static str {
        match self {
            Form::Masks => "TEMP*, PRESSURE",
            Form::Deadband => "0.5",
            Form::Stamps => "ALARM:ALARM_TIME",
            Form::Retention => "30d, 10GB",
        }
    }

    /// `Err` is the problem with `text`.
    pub fn check(self, text: &str) -> Result<(), String> {
        match self {
            Form::Masks => parse_masks(text).map(drop),
            Form::Deadband => parse_deadband(text).map(drop),
            Form::Stamps => parse_stamps(text).map(drop),
            Form::Retention => parse_retention(text).map(drop),
        }
    }
}

/// The comma-separated parts of a list, each trimmed; an empty part is an
/// error naming its position.
fn parts(text: &str) -> Result<Vec<&str>, String> {
    text.split(',')
        .map(str::trim)
        .enumerate()
        .map(|(i, part)| {
            if part.is_empty() {
                Err(format!("has an empty entry (number {})", i + 1))
            } else {
                Ok(part)
            }
        })
        .collect()
}

/// A variable name or mask: no spaces, control characters, quotes, `,` or
/// `:`.
fn check_name(part: &str, what: &str) -> Result<(), String> {
    match part
        .chars()
        .find(|c| c.is_whitespace() || c.is_control() || matches!(c, '"' | '\'' | ',' | ':'))
    {
        Some(c) => Err(format!("has {what} '{part}' with the character {c:?}")),
        None => Ok(()),
    }
}

pub fn parse_masks(text: &str) -> Result<Vec<String>, String> {
    parts(text)?
        .into_iter()
        .map(|part| check_name(part, "the mask").map(|()| part.to_string()))
        .collect()
}

pub fn parse_deadband(text: &str) -> Result<Deadband, String> {
    Delta::parse(text.as_bytes())
        .map(Deadband)
        .map_err(|_| "is not a non-negative number".to_string())
}

pub fn parse_stamps(text: &str) -> Result<Vec<StampPair>, String> {
    parts(text)?
        .into_iter()
        .map(|part| {
            let Some((value, stamp)) = part.split_once(':') else {
                return Err(format!("has '{part}', which is not VALUE_VAR:STAMP_VAR"));
            };
            let (value, stamp) = (value.trim(), stamp.trim());
            for name in [value, stamp] {
                if name.is_empty() || name.contains('*') {
                    return Err(format!(
                        "has '{part}': both sides must be variable names, without *"
                    ));
                }
                check_name(name, "the name")?;
            }
            Ok(StampPair {
                value: value.to_string(),
                stamp: stamp.to_string(),
            })
        })
        .collect()
}

pub fn parse_retention(text: &str) -> Result<Retention, String> {
    let mut retention = Retention::default();
    for part in parts(text)? {
        let digits = part.bytes().take_while(u8::is_ascii_digit).count();
        let (number, unit) = part.split_at(digits);
        let bad = || format!("has '{part}', which is not <n>d or a size such as 500MB or 10GiB");
        let n: u64 = number.parse().map_err(|_| bad())?;
        let multiplier: u64 = match unit.trim().to_ascii_lowercase().as_str() {
            "d" => {
                if retention.days.is_some() {
                    return Err(format!("gives days twice ('{part}')"));
                }
                let days = u32::try_from(n)
                    .ok()
                    .filter(|&d| d >= 1)
                    .ok_or_else(|| format!("has '{part}': days must be 1 or more"))?;
                retention.days = Some(days);
                continue;
            }
            "b" => 1,
            "kb" => 1_000,
            "mb" => 1_000_000,
            "gb" => 1_000_000_000,
            "tb" => 1_000_000_000_000,
            "kib" => 1 << 10,
            "mib" => 1 << 20,
            "gib" => 1 << 30,
            "tib" => 1 << 40,
            _ => return Err(bad()),
        };
        if retention.bytes.is_some() {
            return Err(format!("gives a size twice ('{part}')"));
        }
        let bytes = n
            .checked_mul(multiplier)
            .filter(|&b| b > 0)
            .ok_or_else(|| format!("has '{part}': a size must be above 0 and below 2^64 bytes"))?;
        retention.bytes = Some(bytes);
    }
    Ok(retention)
}

/// Warns of `HISTORY_*` keys of a section that records nothing.
pub(super) fn warn_unused(history: &History, map: &HashMap<&str, &Entry>, diags: &mut Diags<'_>) {
    if history.enabled() {
        return;
    }
    let mut unused: Vec<&Entry> = map
        .iter()
        .filter(|(key, _)| key.starts_with("HISTORY_"))
        .map(|(_, entry)| *entry)
        .collect();
    unused.sort_by_key(|e| e.line);
    for entry in unused {
        diags.push(
            Severity::Warning,
            entry.line,
            format!("{} has no effect without HISTORY", entry.key),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn masks() {
        assert_eq!(parse_masks("A, b*,C").unwrap(), ["A", "b*", "C"]);
        assert_eq!(
            parse_masks("A,,B").unwrap_err(),
            "has an empty entry (number 2)"
        );
        assert_eq!(
            parse_masks("A B").unwrap_err(),
            "has the mask 'A B' with the character ' '"
        );
    }

    #[test]
    fn deadband() {
        assert_eq!(parse_deadband("0.5").unwrap().0.as_f64(), 0.5);
        assert!(parse_deadband("-1").is_err());
        assert!(parse_deadband("x").is_err());
    }

    #[test]
    fn stamps() {
        assert_eq!(
            parse_stamps("A:T, B : U").unwrap(),
            [
                StampPair {
                    value: "A".into(),
                    stamp: "T".into()
                },
                StampPair {
                    value: "B".into(),
                    stamp: "U".into()
                }
            ]
        );
        assert_eq!(
            parse_stamps("A").unwrap_err(),
            "has 'A', which is not VALUE_VAR:STAMP_VAR"
        );
        assert!(parse_stamps("A*:T").is_err());
        assert!(parse_stamps("A:").is_err());
    }

    #[test]
    fn retention() {
        assert_eq!(
            parse_retention("30d, 10GB").unwrap(),
            Retention {
                days: Some(30),
                bytes: Some(10_000_000_000)
            }
        );
        assert_eq!(
            parse_retention("1MiB").unwrap(),
            Retention {
                days: None,
                bytes: Some(1 << 20)
            }
        );
        for bad in [
            "",
            "0d",
            "5x",
            "d",
            "1d,2d",
            "1MB,1GB",
            "99999999999999999999TB",
        ] {
            assert!(parse_retention(bad).is_err(), "{bad}");
        }
    }
}
