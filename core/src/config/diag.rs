//! Problems found in the ini file, each at a line of it.

use std::fmt;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Severity {
    Warning,
    Error,
}

/// A problem at one line of the ini file. Displays as `PLCComS.ini:12: message`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Diagnostic {
    pub severity: Severity,
    pub file: PathBuf,
    /// 1-based.
    pub line: usize,
    pub message: String,
}

impl fmt::Display for Diagnostic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}: {}", self.file.display(), self.line, self.message)
    }
}

/// The diagnostics of one file, as they are found.
pub(super) struct Diags<'a> {
    pub file: &'a Path,
    pub list: Vec<Diagnostic>,
}

impl<'a> Diags<'a> {
    pub fn new(file: &'a Path) -> Diags<'a> {
        Diags {
            file,
            list: Vec::new(),
        }
    }

    pub fn make(&self, severity: Severity, line: usize, message: String) -> Diagnostic {
        Diagnostic {
            severity,
            file: self.file.to_path_buf(),
            line,
            message,
        }
    }

    pub fn push(&mut self, severity: Severity, line: usize, message: String) {
        let d = self.make(severity, line, message);
        self.list.push(d);
    }
}
