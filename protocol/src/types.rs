//! IEC 61131-3 data types as public files name them, and PLC memory areas.

use std::fmt;

/// Capacity of a `STRING` declared without a length.
pub const DEFAULT_STRING_LEN: u16 = 80;
/// Largest `STRING[n]` accepted (Mosaic's limit).
pub const MAX_STRING_LEN: u16 = 255;

/// A variable's type. Layout in PLC memory is little-endian; REAL is binary32,
/// LREAL, DATE and DT are binary64 seconds since 1970, TIME and TOD are u32 ms.
/// A `STRING[n]` occupies `n + 1` bytes (NUL-terminated).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum IecType {
    Bool,
    Byte,
    Word,
    Dword,
    Lword,
    Sint,
    Int,
    Dint,
    Lint,
    Usint,
    Uint,
    Udint,
    Ulint,
    Real,
    Lreal,
    String(u16),
    Date,
    Time,
    Tod,
    Dt,
}

impl IecType {
    /// Every type but `STRING[n]`, in declaration order: the one list tests,
    /// property generators and fuzz checks iterate.
    pub const FIXED: [IecType; 19] = [
        IecType::Bool,
        IecType::Byte,
        IecType::Word,
        IecType::Dword,
        IecType::Lword,
        IecType::Sint,
        IecType::Int,
        IecType::Dint,
        IecType::Lint,
        IecType::Usint,
        IecType::Uint,
        IecType::Udint,
        IecType::Ulint,
        IecType::Real,
        IecType::Lreal,
        IecType::Date,
        IecType::Time,
        IecType::Tod,
        IecType::Dt,
    ];

    /// Parses a type name as it appears in a public file, case-insensitively,
    /// including the long aliases (`TIME_OF_DAY`, `DATE_AND_TIME`) and
    /// `STRING[n]`. `None` for anything else.
    pub fn parse(text: &[u8]) -> Option<IecType> {
        let mut upper = [0u8; 16];
        if text.len() > upper.len() {
            return None;
        }
        for (dst, src) in upper.iter_mut().zip(text) {
            *dst = src.to_ascii_uppercase();
        }
        let t = &upper[..text.len()];
        Some(match t {
            b"BOOL" => IecType::Bool,
            b"BYTE" => IecType::Byte,
            b"WORD" => IecType::Word,
            b"DWORD" => IecType::Dword,
            b"LWORD" => IecType::Lword,
            b"SINT" => IecType::Sint,
            b"INT" => IecType::Int,
            b"DINT" => IecType::Dint,
            b"LINT" => IecType::Lint,
            b"USINT" => IecType::Usint,
            b"UINT" => IecType::Uint,
            b"UDINT" => IecType::Udint,
            b"ULINT" => IecType::Ulint,
            b"REAL" => IecType::Real,
            b"LREAL" => IecType::Lreal,
            b"STRING" => IecType::String(DEFAULT_STRING_LEN),
            b"DATE" => IecType::Date,
            b"TIME" => IecType::Time,
            b"TOD" | b"TIME_OF_DAY" => IecType::Tod,
            b"DT" | b"DATE_AND_TIME" => IecType::Dt,
            _ => {
                let inner = t.strip_prefix(b"STRING[")?.strip_suffix(b"]")?;
                if inner.is_empty() || inner.len() > 3 || !inner.iter().all(u8::is_ascii_digit) {
                    return None;
                }
                let n = inner.iter().fold(0u16, |n, d| n * 10 + u16::from(d - b'0'));
                if n == 0 || n > MAX_STRING_LEN {
                    return None;
                }
                IecType::String(n)
            }
        })
    }

    /// Bytes the variable occupies in PLC memory. A BOOL occupies the byte
    /// that holds its bit.
    pub fn size(&self) -> usize {
        match self {
            IecType::Bool | IecType::Byte | IecType::Sint | IecType::Usint => 1,
            IecType::Word | IecType::Int | IecType::Uint => 2,
            IecType::Dword
            | IecType::Dint
            | IecType::Udint
            | IecType::Real
            | IecType::Time
            | IecType::Tod => 4,
            IecType::Lword
            | IecType::Lint
            | IecType::Ulint
            | IecType::Lreal
            | IecType::Date
            | IecType::Dt => 8,
            IecType::String(n) => usize::from(*n) + 1,
        }
    }

    pub fn is_string(&self) -> bool {
        matches!(self, IecType::String(_))
    }
}

impl fmt::Display for IecType {
    /// The name LIST prints: the canonical short name, `STRING[n]` with its
    /// capacity.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let name = match self {
            IecType::Bool => "BOOL",
            IecType::Byte => "BYTE",
            IecType::Word => "WORD",
            IecType::Dword => "DWORD",
            IecType::Lword => "LWORD",
            IecType::Sint => "SINT",
            IecType::Int => "INT",
            IecType::Dint => "DINT",
            IecType::Lint => "LINT",
            IecType::Usint => "USINT",
            IecType::Uint => "UINT",
            IecType::Udint => "UDINT",
            IecType::Ulint => "ULINT",
            IecType::Real => "REAL",
            IecType::Lreal => "LREAL",
            IecType::String(n) => return write!(f, "STRING[{n}]"),
            IecType::Date => "DATE",
            IecType::Time => "TIME",
            IecType::Tod => "TOD",
            IecType::Dt => "DT",
        };
        f.write_str(name)
    }
}

/// A PLC memory area, by the letter public files and direct addresses use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Area {
    /// Inputs.
    X,
    /// Outputs.
    Y,
    /// System registers (`__PLC_RUN`, `__PF_CRC`).
    S,
    /// User registers.
    R,
}

impl Area {
    pub const ALL: [Area; 4] = [Area::X, Area::Y, Area::S, Area::R];

    pub fn from_letter(letter: u8) -> Option<Area> {
        match letter.to_ascii_uppercase() {
            b'X' => Some(Area::X),
            b'Y' => Some(Area::Y),
            b'S' => Some(Area::S),
            b'R' => Some(Area::R),
            _ => None,
        }
    }

    pub fn letter(self) -> char {
        match self {
            Area::X => 'X',
            Area::Y => 'Y',
            Area::S => 'S',
            Area::R => 'R',
        }
    }

    /// Index for per-area tables.
    pub fn index(self) -> usize {
        self as usize
    }
}

impl fmt::Display for Area {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.letter())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fixed_lists_each_type_once_by_its_name() {
        for (i, ty) in IecType::FIXED.iter().enumerate() {
            assert_eq!(IecType::parse(ty.to_string().as_bytes()), Some(*ty));
            assert!(!IecType::FIXED[..i].contains(ty), "{ty} twice");
        }
    }

    #[test]
    fn parses_every_type_and_alias() {
        assert_eq!(IecType::parse(b"bool"), Some(IecType::Bool));
        assert_eq!(IecType::parse(b"Time_Of_Day"), Some(IecType::Tod));
        assert_eq!(IecType::parse(b"DATE_AND_TIME"), Some(IecType::Dt));
        assert_eq!(IecType::parse(b"STRING"), Some(IecType::String(80)));
        assert_eq!(IecType::parse(b"string[40]"), Some(IecType::String(40)));
        assert_eq!(IecType::parse(b"STRING[0]"), None);
        assert_eq!(IecType::parse(b"STRING[256]"), None);
        assert_eq!(IecType::parse(b"STRING[]"), None);
        assert_eq!(IecType::parse(b"FLOAT"), None);
        assert_eq!(IecType::parse(b"A_VERY_LONG_TYPE_NAME_INDEED"), None);
    }

    #[test]
    fn list_names_round_trip() {
        for name in [
            "BOOL",
            "BYTE",
            "WORD",
            "DWORD",
            "LWORD",
            "SINT",
            "INT",
            "DINT",
            "LINT",
            "USINT",
            "UINT",
            "UDINT",
            "ULINT",
            "REAL",
            "LREAL",
            "STRING[12]",
            "DATE",
            "TIME",
            "TOD",
            "DT",
        ] {
            let ty = IecType::parse(name.as_bytes()).unwrap();
            assert_eq!(ty.to_string(), name);
        }
    }
}
