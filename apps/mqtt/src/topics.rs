//! Topic names. A section's topics are
//!
//! ```text
//! <prefix>/<section>/<VAR>          the value (retained by default)
//! <prefix>/<section>/<VAR>/set      a write, from MQTT clients
//! <prefix>/<section>/<VAR>/error    why a write was refused
//! <prefix>/<section>/status         online / offline (the last will)
//! <prefix>/<section>/plc            online / offline: the link to the PLC
//! ```
//!
//! Variable names are upper case (as the line protocol prints them), so
//! they never meet the lower-case `status` and `plc`. Names and section
//! names are cp1250 in the PLC and UTF-8 on MQTT; the characters MQTT gives a
//! meaning in a topic level are escaped as `%` and two upper-case hex digits
//! of their byte: `/` is `%2F`, `+` is `%2B`, `#` is `%23`, and `%` itself is
//! `%25` (NUL, impossible in a name, would be `%00`). Nothing else is
//! escaped, so a name reads as it is written in the PLC program.

use plccoms_protocol::cp1250;

/// One topic level for `name` (cp1250 bytes): UTF-8, escaped.
pub fn level(name: &[u8]) -> String {
    escape(&cp1250::decode(name))
}

/// `text` with `% / + #` and NUL escaped.
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '%' | '/' | '+' | '#' | '\0' => out.push_str(&format!("%{:02X}", c as u32)),
            c => out.push(c),
        }
    }
    out
}

/// Why a topic level does not name a variable.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LevelError {
    #[error("'%' at byte {0} is not followed by two hex digits")]
    BadEscape(usize),
    #[error("holds '{0}', which has no cp1250 form")]
    NotCp1250(char),
}

/// The cp1250 name a topic level stands for: the inverse of [`level`] (any
/// `%XX` is taken, upper or lower case hex, so `%41` is `A`).
pub fn unlevel(level: &str) -> Result<Vec<u8>, LevelError> {
    let bytes = level.as_bytes();
    let mut text = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' {
            let hex = bytes
                .get(i + 1..i + 3)
                .and_then(|h| std::str::from_utf8(h).ok())
                .and_then(|h| u8::from_str_radix(h, 16).ok())
                .ok_or(LevelError::BadEscape(i))?;
            text.push(hex);
            i += 3;
        } else {
            text.push(bytes[i]);
            i += 1;
        }
    }
    // An escape may produce bytes that are not UTF-8 on their own; they are
    // taken as Latin-1, which every escape this server writes is (ASCII).
    let text = match String::from_utf8(text) {
        Ok(text) => text,
        Err(e) => e.into_bytes().iter().map(|&b| char::from(b)).collect(),
    };
    match cp1250::try_encode(&text) {
        Some(name) => Ok(name),
        None => Err(LevelError::NotCp1250(
            text.chars()
                .find(|c| cp1250::try_encode(&c.to_string()).is_none())
                .unwrap_or('?'),
        )),
    }
}

/// The topics of one section.
#[derive(Debug, Clone)]
pub struct Topics {
    /// `<prefix>/<section>`.
    base: String,
}

impl Topics {
    pub fn new(prefix: &str, section: &str) -> Topics {
        Topics {
            base: format!("{prefix}/{}", escape(section)),
        }
    }

    pub fn base(&self) -> &str {
        &self.base
    }

    /// The value topic of `name` (cp1250).
    pub fn value(&self, name: &[u8]) -> String {
        format!("{}/{}", self.base, level(name))
    }

    /// The value topic of a variable, from its name's topic level.
    pub fn value_of_level(&self, level: &str) -> String {
        format!("{}/{level}", self.base)
    }

    pub fn status(&self) -> String {
        format!("{}/status", self.base)
    }

    pub fn plc(&self) -> String {
        format!("{}/plc", self.base)
    }

    /// The subscription that catches every write.
    pub fn set_filter(&self) -> String {
        format!("{}/+/set", self.base)
    }

    /// The name level of a `<base>/<level>/set` topic.
    pub fn set_level<'t>(&self, topic: &'t str) -> Option<&'t str> {
        let level = topic
            .strip_prefix(self.base.as_str())?
            .strip_prefix('/')?
            .strip_suffix("/set")?;
        (!level.is_empty() && !level.contains('/')).then_some(level)
    }

    pub fn error_of_level(&self, level: &str) -> String {
        format!("{}/{level}/error", self.base)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_become_levels_and_back() {
        assert_eq!(level(b"COUNTER"), "COUNTER");
        assert_eq!(level(b"A/B+C#D%E"), "A%2FB%2BC%23D%25E");
        // cp1250 0x8A is Š, 0x9A is š.
        assert_eq!(level(b"TEPLOTA_\x8AKOLA"), "TEPLOTA_ŠKOLA");
        for name in [&b"A/B+C#D%E"[..], b"TEPLOTA_\x8AKOLA", b"X.Y[2]", b"%25"] {
            assert_eq!(unlevel(&level(name)).unwrap(), name);
        }
        assert_eq!(unlevel("%41%2f").unwrap(), b"A/");
        assert_eq!(unlevel("A%4"), Err(LevelError::BadEscape(1)));
        assert_eq!(unlevel("A%zz"), Err(LevelError::BadEscape(1)));
        assert_eq!(unlevel("日本"), Err(LevelError::NotCp1250('日')));
    }

    #[test]
    fn section_topics() {
        let t = Topics::new("site/plccoms", "Hala 1/A");
        assert_eq!(t.value(b"X"), "site/plccoms/Hala 1%2FA/X");
        assert_eq!(t.status(), "site/plccoms/Hala 1%2FA/status");
        assert_eq!(t.set_filter(), "site/plccoms/Hala 1%2FA/+/set");
        assert_eq!(
            t.set_level("site/plccoms/Hala 1%2FA/X%2FY/set"),
            Some("X%2FY")
        );
        assert_eq!(t.set_level("site/plccoms/Hala 1%2FA//set"), None);
        assert_eq!(t.set_level("site/plccoms/Other/X/set"), None);
        assert_eq!(t.error_of_level("X"), "site/plccoms/Hala 1%2FA/X/error");
    }
}
