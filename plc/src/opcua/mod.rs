//! OPC UA without I/O: node ids ([`nodeid`]), the tag file and the layout
//! of a section's variables ([`tags`]), StatusCode names ([`status`]), and
//! the rule that names a browsed variable after its browse path
//! ([`path_name`], [`unique_names`]).
//!
//! An OPC UA section's variables live in R, one after another (see
//! [`tags::vars`]); S holds `__PLC_RUN` and `__PF_CRC` as the standard fixed
//! file places them, answered by the backend. `__PF_CRC` is the CRC of the
//! variable list the backend built ([`VARS_FILE`]): when the server's nodes
//! change, it changes, and the section reloads its table as for a new
//! public file.

pub mod nodeid;
pub mod status;
pub mod structure;
pub mod tags;

use std::collections::HashSet;

use plccoms_protocol::cp1250;

use crate::memory::MemoryMap;

/// The areas of an OPC UA section: S for the system variables, R for the
/// nodes' values (room for 100,000 variables of 255-character strings).
pub const MAP: MemoryMap = MemoryMap {
    sizes: [0, 0, 4 * 1024, 32 * 1024 * 1024],
};

/// The name under which the backend serves the variable list it built (a
/// tag file, [`tags::write`]) through the file services, and which GETINFO
/// and the log show.
pub const VARS_FILE: &str = "OPCUA_VARS.csv";

/// Joins browse names into a variable name: `.` between them; in each,
/// the characters a name cannot hold on the line protocol (space and
/// control characters, `, : * " ;`, `.` itself, and characters cp1250 lacks)
/// become `_`, as does a leading `%` or `#`. Cut to [`crate::pubfile::MAX_NAME`]
/// bytes.
pub fn path_name<S: AsRef<str>>(path: &[S]) -> String {
    let mut name = String::new();
    for (i, part) in path.iter().enumerate() {
        if i > 0 {
            name.push('.');
        }
        let part = part.as_ref();
        if part.is_empty() {
            name.push('_');
        }
        for c in part.chars() {
            let bad = c <= ' '
                || c == '\u{7f}'
                || matches!(c, ',' | ':' | '*' | '"' | ';' | '.')
                || cp1250::try_encode(c.encode_utf8(&mut [0; 4])).is_none();
            name.push(if bad { '_' } else { c });
        }
    }
    // `%` marks direct addresses; `#` starts a comment line in a tag file.
    if name.starts_with(['%', '#']) {
        name.replace_range(..1, "_");
    }
    let mut end = name.len();
    // Each character is one cp1250 byte: cut at a character boundary.
    while name[..end].chars().count() > crate::pubfile::MAX_NAME {
        end = name[..end].char_indices().last().map_or(0, |(i, _)| i);
    }
    name.truncate(end);
    name
}

/// Makes `names` unique, ignoring case as the variable table does: a name
/// seen before gets `_2`, `_3`, ... (the first free one). Returns the
/// renamings (old, new) for the log.
pub fn unique_names(names: &mut [String]) -> Vec<(String, String)> {
    let mut seen: HashSet<String> = HashSet::with_capacity(names.len());
    let mut renamed = Vec::new();
    for name in names.iter_mut() {
        if seen.insert(name.to_uppercase()) {
            continue;
        }
        let mut n = 2;
        let new = loop {
            let candidate = format!("{name}_{n}");
            if seen.insert(candidate.to_uppercase()) {
                break candidate;
            }
            n += 1;
        };
        renamed.push((std::mem::replace(name, new.clone()), new));
    }
    renamed
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn browse_paths_become_names_the_protocol_carries() {
        assert_eq!(
            path_name(&["DB_LINE1", "MOTOR", "SPEED"]),
            "DB_LINE1.MOTOR.SPEED"
        );
        assert_eq!(
            path_name(&["\"DB 1\"", "a.b", "x:y,z*;", "€"]),
            "_DB_1_.a_b.x_y_z__.€"
        );
        assert_eq!(path_name(&["%I0", ""]), "_I0._");
        assert_eq!(path_name(&["#x"]), "_x");
        assert_eq!(path_name(&["日本"]), "__");
        assert_eq!(path_name(&["x".repeat(300)]).len(), 255);
    }

    #[test]
    fn collisions_get_the_first_free_suffix() {
        let mut names: Vec<String> = ["A.B", "a.b", "A.B_2", "A.B"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        let renamed = unique_names(&mut names);
        assert_eq!(names, ["A.B", "a.b_2", "A.B_2_2", "A.B_3"]);
        assert_eq!(renamed.len(), 3);
    }
}
