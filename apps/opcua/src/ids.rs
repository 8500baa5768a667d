//! Our string NodeIds, stable across restarts and tag-file edits because
//! they are made of names only:
//!
//! | node | NodeId (`ns=<ours>;s=...`) |
//! |---|---|
//! | the `plccoms` folder | `plccoms` |
//! | a section object | `<Section>` |
//! | a section's property | `<Section>#LinkState`, `#LastPoll`, `#Backend` |
//! | a variable | `<Section>.<Variable>` |
//! | a variable's property | `<Section>.<Variable>#EURange`, `#EngineeringUnits` |
//!
//! A client may send any string: [`parse`] reads one back, never
//! panicking, and names what is wrong.

/// The root folder's id (and browse name).
pub const ROOT: &str = "plccoms";

/// What one of our string ids names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Ours<'a> {
    Root,
    Section {
        section: usize,
    },
    SectionProperty {
        section: usize,
        property: &'a str,
    },
    Variable {
        section: usize,
        variable: &'a str,
    },
    VariableProperty {
        section: usize,
        variable: &'a str,
        property: &'a str,
    },
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum IdError {
    #[error("node id is empty")]
    Empty,
    #[error("node id is {0} bytes long; at most {MAX} are ours")]
    TooLong(usize),
    #[error("no section is named at the start of node id '{0}'")]
    UnknownSection(String),
    #[error("node id '{0}': nothing after the '{1}'")]
    Truncated(String, char),
}

/// Longer ids are not ours (a section name and a variable name fit well
/// within it).
pub const MAX: usize = 1024;

pub fn variable(section: &str, variable: &str) -> String {
    // Made for every change the feed gives: one allocation, no formatter.
    let mut id = String::with_capacity(section.len() + 1 + variable.len());
    id.push_str(section);
    id.push('.');
    id.push_str(variable);
    id
}

pub fn property(owner: &str, property: &str) -> String {
    format!("{owner}#{property}")
}

/// Reads `id` against the section names `sections` (a section name may
/// itself hold `.` or `#`: the longest name that fits wins).
pub fn parse<'a, S: AsRef<str>>(id: &'a str, sections: &[S]) -> Result<Ours<'a>, IdError> {
    if id.is_empty() {
        return Err(IdError::Empty);
    }
    if id.len() > MAX {
        return Err(IdError::TooLong(id.len()));
    }
    if id == ROOT {
        return Ok(Ours::Root);
    }
    let (section, rest) = sections
        .iter()
        .enumerate()
        .filter_map(|(i, name)| {
            let name = name.as_ref();
            let rest = id.strip_prefix(name)?;
            (rest.is_empty() || rest.starts_with(['.', '#'])).then_some((i, name.len(), rest))
        })
        .max_by_key(|&(_, len, _)| len)
        .map(|(i, _, rest)| (i, rest))
        .ok_or_else(|| IdError::UnknownSection(shorten(id)))?;
    if rest.is_empty() {
        return Ok(Ours::Section { section });
    }
    let (first, after) = rest.split_at(1);
    let mark = if first == "." { '.' } else { '#' };
    if after.is_empty() {
        return Err(IdError::Truncated(shorten(id), mark));
    }
    if mark == '#' {
        return Ok(Ours::SectionProperty {
            section,
            property: after,
        });
    }
    // A variable's name holds no '#' (names are letters, digits, `_`, `.`,
    // `[`, `]`), so the last '#' starts its property.
    match after.rsplit_once('#') {
        Some((variable, property)) if !variable.is_empty() && !property.is_empty() => {
            Ok(Ours::VariableProperty {
                section,
                variable,
                property,
            })
        }
        Some(_) => Err(IdError::Truncated(shorten(id), '#')),
        None => Ok(Ours::Variable {
            section,
            variable: after,
        }),
    }
}

/// At most 64 characters of a client's id, for messages.
fn shorten(id: &str) -> String {
    id.chars().take(64).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_back_what_it_makes() {
        let sections = ["Hala", "Hala.2"];
        assert_eq!(parse("plccoms", &sections), Ok(Ours::Root));
        assert_eq!(parse("Hala", &sections), Ok(Ours::Section { section: 0 }));
        assert_eq!(
            parse(&variable("Hala", "TEMP"), &sections),
            Ok(Ours::Variable {
                section: 0,
                variable: "TEMP"
            })
        );
        // The longest section name wins.
        assert_eq!(
            parse("Hala.2.TEMP", &sections),
            Ok(Ours::Variable {
                section: 1,
                variable: "TEMP"
            })
        );
        assert_eq!(
            parse(&property(&variable("Hala", "A.B"), "EURange"), &sections),
            Ok(Ours::VariableProperty {
                section: 0,
                variable: "A.B",
                property: "EURange"
            })
        );
        assert_eq!(
            parse("Hala#LinkState", &sections),
            Ok(Ours::SectionProperty {
                section: 0,
                property: "LinkState"
            })
        );
    }

    #[test]
    fn refuses_with_a_reason() {
        let sections = ["Hala"];
        assert_eq!(parse("", &sections), Err(IdError::Empty));
        assert!(matches!(
            parse("Dvur.X", &sections),
            Err(IdError::UnknownSection(_))
        ));
        assert!(matches!(
            parse("HalaX", &sections),
            Err(IdError::UnknownSection(_))
        ));
        assert!(matches!(
            parse("Hala.", &sections),
            Err(IdError::Truncated(_, '.'))
        ));
        assert!(matches!(
            parse("Hala.A#", &sections),
            Err(IdError::Truncated(_, '#'))
        ));
        assert!(matches!(
            parse(&"x".repeat(2000), &sections),
            Err(IdError::TooLong(2000))
        ));
    }
}
