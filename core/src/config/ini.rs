//! The line scan: what rust-ini cannot do. It strips trailing `#`/`;`
//! comments outside quotes (a comment starts at the value's start, after
//! whitespace or right after a closing quote), reports lines that are neither
//! `[SECTION]` nor `KEY = VALUE`, and remembers the line of every key so that
//! every message names file and line. rust-ini then handles quotes; escapes
//! stay off so Windows paths keep their backslashes.

use ini::{Ini, ParseOption};

use super::diag::{Diagnostic, Diags, Severity};

/// One `KEY = VALUE` line: the key upper-case, the value unquoted.
pub(super) struct Entry {
    pub key: String,
    pub value: String,
    pub line: usize,
}

/// A section as written, before its values are read.
pub(super) struct RawSection {
    pub name: String,
    pub line: usize,
    pub entries: Vec<Entry>,
    /// Malformed lines found by the scan, the header included.
    pub errors: Vec<Diagnostic>,
}

/// A file as written.
pub(super) struct RawFile {
    /// Malformed lines before the first section header.
    pub errors: Vec<Diagnostic>,
    pub sections: Vec<RawSection>,
}

/// Scans `text` and reads it with rust-ini. Keys outside any section are
/// warnings in `diags`; an `Err` is text that rust-ini refuses.
pub(super) fn read(text: &str, diags: &mut Diags<'_>) -> Result<RawFile, Diagnostic> {
    let scanned = scan(text, diags);
    let ini = Ini::load_from_str_opt(
        &scanned.normalized,
        ParseOption {
            enabled_quote: true,
            enabled_escape: false,
            enabled_indented_mutiline_value: false,
            enabled_preserve_key_leading_whitespace: false,
        },
    )
    .map_err(|e| diags.make(Severity::Error, e.line, e.msg.into_owned()))?;

    // rust-ini keeps sections and keys in file order, as the scan saw them:
    // pair them up to know each key's line.
    let mut scanned_sections = scanned.sections.into_iter();
    let mut sections = Vec::new();
    for (name, props) in ini.iter() {
        let scanned_section = name.and_then(|_| scanned_sections.next());
        let (header_line, lines) = match &scanned_section {
            Some(s) => (s.line, &s.key_lines),
            None => (0, &scanned.general),
        };
        let entries: Vec<Entry> = props
            .iter()
            .enumerate()
            .map(|(i, (key, value))| Entry {
                key: key.to_ascii_uppercase(),
                value: value.to_string(),
                line: lines.get(i).copied().unwrap_or(header_line.max(1)),
            })
            .collect();
        match scanned_section {
            None => {
                for entry in entries {
                    diags.push(
                        Severity::Warning,
                        entry.line,
                        format!("{} is outside any section; ignored", entry.key),
                    );
                }
            }
            Some(s) => sections.push(RawSection {
                name: s.name,
                line: s.line,
                entries,
                errors: s.errors,
            }),
        }
    }
    Ok(RawFile {
        errors: scanned.general_errors,
        sections,
    })
}

struct Scanned {
    /// The text rust-ini reads: one line per input line, comments and bad
    /// lines blanked, keys as `KEY=value`.
    normalized: String,
    /// Lines of keys before the first section header.
    general: Vec<usize>,
    /// Malformed lines before the first section header.
    general_errors: Vec<Diagnostic>,
    sections: Vec<ScannedSection>,
}

struct ScannedSection {
    name: String,
    line: usize,
    key_lines: Vec<usize>,
    /// Malformed lines in the section, its header included.
    errors: Vec<Diagnostic>,
}

/// Every line that is not blank, a comment, `[SECTION]` or `KEY = VALUE` is an
/// error of the section it is in (a bad header is an error of its own
/// section); such lines are blanked for rust-ini.
fn scan(text: &str, diags: &Diags<'_>) -> Scanned {
    let mut out = Scanned {
        normalized: String::with_capacity(text.len()),
        general: Vec::new(),
        general_errors: Vec::new(),
        sections: Vec::new(),
    };
    for (index, raw) in text.split('\n').enumerate() {
        let line_no = index + 1;
        let line = raw.strip_suffix('\r').unwrap_or(raw).trim();
        let mut error = None;
        if line.is_empty() || line.starts_with('#') || line.starts_with(';') {
            // blank or comment
        } else if let Some(rest) = line.strip_prefix('[') {
            let (name, problem) = scan_section(rest);
            // rust-ini only sees a placeholder name: the real one is ours.
            out.normalized
                .push_str(&format!("[s{}]", out.sections.len()));
            out.sections.push(ScannedSection {
                name,
                line: line_no,
                key_lines: Vec::new(),
                errors: Vec::new(),
            });
            error = problem;
        } else {
            match scan_key(line) {
                Ok((key, value)) => {
                    out.normalized.push_str(key);
                    out.normalized.push('=');
                    out.normalized.push_str(&value);
                    match out.sections.last_mut() {
                        Some(s) => s.key_lines.push(line_no),
                        None => out.general.push(line_no),
                    }
                }
                Err(problem) => error = Some(problem),
            }
        }
        if let Some(message) = error {
            let d = diags.make(Severity::Error, line_no, message);
            match out.sections.last_mut() {
                Some(s) => s.errors.push(d),
                None => out.general_errors.push(d),
            }
        }
        out.normalized.push('\n');
    }
    out
}

/// The section name after `[`, and what is wrong with the header, if anything.
fn scan_section(rest: &str) -> (String, Option<String>) {
    let Some(close) = rest.find(']') else {
        return (
            rest.trim().to_string(),
            Some(format!("section header [{rest} has no closing ']'")),
        );
    };
    let name = rest[..close].trim().to_string();
    let after = rest[close + 1..].trim_start();
    let problem = if !(after.is_empty() || after.starts_with('#') || after.starts_with(';')) {
        Some(format!(
            "unexpected '{after}' after section header [{name}]"
        ))
    } else if name.is_empty() {
        Some("empty section name []".to_string())
    } else if name.contains('[') {
        Some(format!("invalid character '[' in section name [{name}]"))
    } else {
        None
    };
    (name, problem)
}

/// `(key, value)` with the value's comment removed but its quotes kept for
/// rust-ini.
fn scan_key(line: &str) -> Result<(&str, String), String> {
    let Some(eq) = line.find('=') else {
        return Err(format!(
            "'{line}' is neither a [SECTION] header nor KEY = VALUE"
        ));
    };
    let key = line[..eq].trim();
    if key.is_empty() {
        return Err(format!("'{line}' has no key before '='"));
    }
    if let Some(bad) = key.chars().find(|&c| matches!(c, ':' | '\\' | '"' | '\'')) {
        return Err(format!("invalid character '{bad}' in key '{key}'"));
    }
    let value = strip_value_comment(line[eq + 1..].trim_start())
        .map_err(|quote| format!("{key}: unterminated {quote} quote in value"))?;
    Ok((key, value))
}

/// Cuts a trailing comment the way rust-ini would read quotes: a quote opens
/// only at the start of the value or right after a closing quote, and a
/// backslash inside quotes takes the next character with it. A `#` or `;`
/// starts a comment at those same places or after whitespace.
fn strip_value_comment(value: &str) -> Result<String, char> {
    let bytes = value.as_bytes();
    let mut i = 0;
    let mut end = bytes.len();
    let mut part_start = true;
    while i < bytes.len() {
        let b = bytes[i];
        if part_start && (b == b'"' || b == b'\'') {
            let mut j = i + 1;
            loop {
                match bytes.get(j) {
                    None => return Err(b as char),
                    Some(b'\\') => j += 2,
                    Some(&c) if c == b => break,
                    Some(_) => j += 1,
                }
            }
            i = j + 1;
            continue;
        }
        if (b == b'#' || b == b';')
            && (part_start || i == 0 || matches!(bytes[i - 1], b' ' | b'\t'))
        {
            end = i;
            break;
        }
        part_start = false;
        i += 1;
    }
    let mut kept = value[..end].trim_end().to_string();
    // A trailing backslash would make rust-ini join the next line; a space
    // after it stops that and is trimmed away again.
    if kept.ends_with('\\') {
        kept.push(' ');
    }
    Ok(kept)
}
