//! ERROR and WARNING answers with the codes and texts of the manual's
//! table 5.1: `ERROR:<code> <text> '<context>'` for texts ending in `:`,
//! `ERROR:<code> <text>` for texts ending in `.`. Line ends are the caller's.

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ErrorCode {
    ConnectPlc,
    MaxConnections,
    GetData,
    SendData,
    BadRequest,
    Incomplete,
    UnknownCommand,
    UnknownVariable,
    DisabledVariable,
    WrongValue,
    FileInfo,
    GetFile,
    WriteFile,
    WriteFileInfo,
    Unterminated,
    WriteTimeout,
    AbortedGet,
    SetConfUnknown,
    GetInfoUnknown,
    Shared,
    MemGet,
    MemSet,
    Unknown,
}

impl ErrorCode {
    pub const ALL: [ErrorCode; 23] = [
        ErrorCode::ConnectPlc,
        ErrorCode::MaxConnections,
        ErrorCode::GetData,
        ErrorCode::SendData,
        ErrorCode::BadRequest,
        ErrorCode::Incomplete,
        ErrorCode::UnknownCommand,
        ErrorCode::UnknownVariable,
        ErrorCode::DisabledVariable,
        ErrorCode::WrongValue,
        ErrorCode::FileInfo,
        ErrorCode::GetFile,
        ErrorCode::WriteFile,
        ErrorCode::WriteFileInfo,
        ErrorCode::Unterminated,
        ErrorCode::WriteTimeout,
        ErrorCode::AbortedGet,
        ErrorCode::SetConfUnknown,
        ErrorCode::GetInfoUnknown,
        ErrorCode::Shared,
        ErrorCode::MemGet,
        ErrorCode::MemSet,
        ErrorCode::Unknown,
    ];

    pub fn code(self) -> u16 {
        match self {
            ErrorCode::ConnectPlc => 10,
            ErrorCode::MaxConnections => 11,
            ErrorCode::GetData => 20,
            ErrorCode::SendData => 21,
            ErrorCode::BadRequest => 30,
            ErrorCode::Incomplete => 31,
            ErrorCode::UnknownCommand => 32,
            ErrorCode::UnknownVariable => 33,
            ErrorCode::DisabledVariable => 34,
            ErrorCode::WrongValue => 35,
            ErrorCode::FileInfo => 40,
            ErrorCode::GetFile => 41,
            ErrorCode::WriteFile => 42,
            ErrorCode::WriteFileInfo => 43,
            ErrorCode::Unterminated => 44,
            ErrorCode::WriteTimeout => 45,
            ErrorCode::AbortedGet => 46,
            ErrorCode::SetConfUnknown => 50,
            ErrorCode::GetInfoUnknown => 60,
            ErrorCode::Shared => 70,
            ErrorCode::MemGet => 80,
            ErrorCode::MemSet => 81,
            ErrorCode::Unknown => 1024,
        }
    }

    /// The text of table 5.1, verbatim.
    pub fn text(self) -> &'static str {
        match self {
            ErrorCode::ConnectPlc => "Unable to connect to PLC.",
            ErrorCode::MaxConnections => "Maximum connections reached.",
            ErrorCode::GetData => "Unable to get data from PLC.",
            ErrorCode::SendData => "Unable to send data to PLC.",
            ErrorCode::BadRequest => "Bad client request:",
            ErrorCode::Incomplete => "Incomplete client request.",
            ErrorCode::UnknownCommand => "Unknown command name in request:",
            ErrorCode::UnknownVariable => "Unknown variable name in request:",
            ErrorCode::DisabledVariable => "Disabled variable name:",
            ErrorCode::WrongValue => "Wrong parameter value in request:",
            ErrorCode::FileInfo => "Unable to get information about file:",
            ErrorCode::GetFile => "Unable to get file:",
            ErrorCode::WriteFile => "Unable to write file:",
            ErrorCode::WriteFileInfo => "Unable to write file information:",
            ErrorCode::Unterminated => "Unterminated write file data:",
            ErrorCode::WriteTimeout => "Timeout write file data:",
            ErrorCode::AbortedGet => "Aborted get file:",
            ErrorCode::SetConfUnknown => "Unknown name in request:",
            ErrorCode::GetInfoUnknown => "Unknown name in request:",
            ErrorCode::Shared => "Unable to connect to SHARED module.",
            ErrorCode::MemGet => "Unable to get data from address:",
            ErrorCode::MemSet => "Unable to set data in to address:",
            ErrorCode::Unknown => "Unknown error.",
        }
    }

    /// Whether the answer carries a quoted context (the text ends in `:`).
    pub fn takes_context(self) -> bool {
        self.text().ends_with(':')
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum WarningCode {
    PubfileChanged,
    PubfileSame,
    ActiveChanged,
    HiddenChanged,
}

impl WarningCode {
    pub const ALL: [WarningCode; 4] = [
        WarningCode::PubfileChanged,
        WarningCode::PubfileSame,
        WarningCode::ActiveChanged,
        WarningCode::HiddenChanged,
    ];

    pub fn code(self) -> u16 {
        match self {
            WarningCode::PubfileChanged => 250,
            WarningCode::PubfileSame => 251,
            WarningCode::ActiveChanged => 252,
            WarningCode::HiddenChanged => 253,
        }
    }

    pub fn text(self) -> &'static str {
        match self {
            WarningCode::PubfileChanged => "Changed public file:",
            WarningCode::PubfileSame => "Public file not changed:",
            WarningCode::ActiveChanged => "Changed active variables in public file:",
            WarningCode::HiddenChanged => "Changed hidden variables in public file:",
        }
    }
}

/// Appends `'<context>'` without CR, LF and NUL, so an answer stays one line
/// and never carries a NUL.
fn write_context(out: &mut Vec<u8>, context: &[u8]) {
    out.extend_from_slice(b" '");
    out.extend(
        context
            .iter()
            .copied()
            .filter(|&b| !matches!(b, b'\r' | b'\n' | 0)),
    );
    out.push(b'\'');
}

/// `ERROR:<code> <text> '<context>'`, or `ERROR:<code> <text>` for the
/// codes whose text ends in `.` (the context is then ignored).
pub fn write_error(out: &mut Vec<u8>, code: ErrorCode, context: &[u8]) {
    out.extend_from_slice(b"ERROR:");
    out.extend_from_slice(code.code().to_string().as_bytes());
    out.push(b' ');
    out.extend_from_slice(code.text().as_bytes());
    if code.takes_context() {
        write_context(out, context);
    }
}

/// `WARNING:<code> <text> '<context>'`.
pub fn write_warning(out: &mut Vec<u8>, code: WarningCode, context: &[u8]) {
    out.extend_from_slice(b"WARNING:");
    out.extend_from_slice(code.code().to_string().as_bytes());
    out.push(b' ');
    out.extend_from_slice(code.text().as_bytes());
    write_context(out, context);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn error(code: ErrorCode, context: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        write_error(&mut out, code, context);
        out
    }

    fn warning(code: WarningCode, context: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        write_warning(&mut out, code, context);
        out
    }

    #[test]
    fn manual_examples() {
        assert_eq!(
            error(ErrorCode::UnknownVariable, b"GET:test"),
            b"ERROR:33 Unknown variable name in request: 'GET:test'"
        );
        assert_eq!(
            error(ErrorCode::MemGet, b"%R70000"),
            b"ERROR:80 Unable to get data from address: '%R70000'"
        );
        assert_eq!(
            error(ErrorCode::WrongValue, b"EN:test_1 a"),
            b"ERROR:35 Wrong parameter value in request: 'EN:test_1 a'"
        );
        assert_eq!(
            warning(WarningCode::PubfileChanged, b"Test.pub"),
            b"WARNING:250 Changed public file: 'Test.pub'"
        );
        assert_eq!(
            warning(WarningCode::PubfileSame, b"Test.pub"),
            b"WARNING:251 Public file not changed: 'Test.pub'"
        );
        assert_eq!(
            warning(WarningCode::ActiveChanged, b"[10/1648]"),
            b"WARNING:252 Changed active variables in public file: '[10/1648]'"
        );
        assert_eq!(
            warning(WarningCode::HiddenChanged, b"[6]"),
            b"WARNING:253 Changed hidden variables in public file: '[6]'"
        );
    }

    #[test]
    fn period_texts_take_no_context() {
        assert_eq!(
            error(ErrorCode::MaxConnections, b"ignored"),
            b"ERROR:11 Maximum connections reached."
        );
        assert_eq!(
            error(ErrorCode::Incomplete, b"SET:x"),
            b"ERROR:31 Incomplete client request."
        );
        assert_eq!(error(ErrorCode::Unknown, b""), b"ERROR:1024 Unknown error.");
        assert_eq!(
            error(ErrorCode::ConnectPlc, b""),
            b"ERROR:10 Unable to connect to PLC."
        );
    }

    #[test]
    fn context_never_breaks_the_line() {
        assert_eq!(
            error(ErrorCode::UnknownCommand, b"FOO:\r\nx\0y"),
            b"ERROR:32 Unknown command name in request: 'FOO:xy'"
        );
        assert_eq!(
            warning(WarningCode::PubfileChanged, b"a\rb"),
            b"WARNING:250 Changed public file: 'ab'"
        );
    }

    #[test]
    fn codes_are_distinct_and_texts_end_in_colon_or_period() {
        let mut codes: Vec<u16> = ErrorCode::ALL.iter().map(|c| c.code()).collect();
        codes.extend(WarningCode::ALL.iter().map(|c| c.code()));
        let n = codes.len();
        codes.sort_unstable();
        codes.dedup();
        assert_eq!(codes.len(), n);
        for c in ErrorCode::ALL {
            assert!(c.text().ends_with(':') || c.text().ends_with('.'), "{c:?}");
        }
        for c in WarningCode::ALL {
            assert!(c.text().ends_with(':'));
        }
    }
}
