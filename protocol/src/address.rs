//! Direct addressing of PLC memory in GET, SET and GETMEM:
//! `%<area>[<width>]<offset>[.<bit>]`, e.g. `%R100`, `%S6`, `%RW10`, `%SL48`,
//! `%R5.3`.
//!
//! Area letters are X, Y, S, R. The width letter is this project's reading of
//! the vendor's examples: none or `B` is a BYTE, `W` a WORD, `L` a DWORD (the
//! manual shows only these forms); `F` (REAL) and `D` (LREAL) are our own
//! additions. `.bit` (0-7) addresses one BOOL and is allowed only without a
//! width or with `B`. Letters are case-insensitive.

use crate::types::{Area, IecType};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DirectAddress {
    pub area: Area,
    /// Byte offset in the area.
    pub offset: u32,
    /// Bit in the byte, for a BOOL.
    pub bit: Option<u8>,
    pub ty: IecType,
}

/// Parses a direct address; `None` for anything malformed, a bit above 7, or
/// an offset whose last byte does not fit in 32 bits.
pub fn parse_direct(text: &[u8]) -> Option<DirectAddress> {
    let rest = text.strip_prefix(b"%")?;
    let (&area, mut rest) = rest.split_first()?;
    let area = Area::from_letter(area)?;
    let mut width = None;
    if let Some((&letter, after)) = rest.split_first() {
        if letter.is_ascii_alphabetic() {
            width = Some(letter.to_ascii_uppercase());
            rest = after;
        }
    }
    let (digits, bit) = match rest.iter().position(|&b| b == b'.') {
        Some(dot) => (&rest[..dot], Some(&rest[dot + 1..])),
        None => (rest, None),
    };
    let offset = parse_u32(digits)?;
    let ty = match (width, bit) {
        (None | Some(b'B'), Some(bit)) => {
            let bit = parse_u32(bit)?;
            if bit > 7 {
                return None;
            }
            return Some(DirectAddress {
                area,
                offset,
                bit: Some(bit as u8),
                ty: IecType::Bool,
            });
        }
        (_, Some(_)) => return None,
        (None | Some(b'B'), None) => IecType::Byte,
        (Some(b'W'), None) => IecType::Word,
        (Some(b'L'), None) => IecType::Dword,
        (Some(b'F'), None) => IecType::Real,
        (Some(b'D'), None) => IecType::Lreal,
        _ => return None,
    };
    offset.checked_add(ty.size() as u32 - 1)?;
    Some(DirectAddress {
        area,
        offset,
        bit: None,
        ty,
    })
}

/// Decimal digits only (no sign), at most `u32::MAX`.
fn parse_u32(digits: &[u8]) -> Option<u32> {
    if digits.is_empty() || !digits.iter().all(u8::is_ascii_digit) {
        return None;
    }
    digits.iter().try_fold(0u32, |n, d| {
        n.checked_mul(10)?.checked_add(u32::from(d - b'0'))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn addr(area: Area, offset: u32, bit: Option<u8>, ty: IecType) -> Option<DirectAddress> {
        Some(DirectAddress {
            area,
            offset,
            bit,
            ty,
        })
    }

    #[test]
    fn vendor_examples() {
        assert_eq!(
            parse_direct(b"%R100"),
            addr(Area::R, 100, None, IecType::Byte)
        );
        assert_eq!(parse_direct(b"%S6"), addr(Area::S, 6, None, IecType::Byte));
        assert_eq!(
            parse_direct(b"%RW10"),
            addr(Area::R, 10, None, IecType::Word)
        );
        assert_eq!(
            parse_direct(b"%SL48"),
            addr(Area::S, 48, None, IecType::Dword)
        );
        assert_eq!(
            parse_direct(b"%R5.3"),
            addr(Area::R, 5, Some(3), IecType::Bool)
        );
    }

    #[test]
    fn other_forms() {
        assert_eq!(parse_direct(b"%rb7"), addr(Area::R, 7, None, IecType::Byte));
        assert_eq!(
            parse_direct(b"%xb2.7"),
            addr(Area::X, 2, Some(7), IecType::Bool)
        );
        assert_eq!(parse_direct(b"%YF0"), addr(Area::Y, 0, None, IecType::Real));
        assert_eq!(
            parse_direct(b"%Rd8"),
            addr(Area::R, 8, None, IecType::Lreal)
        );
        assert_eq!(
            parse_direct(b"%R4294967295"),
            addr(Area::R, u32::MAX, None, IecType::Byte)
        );
        assert_eq!(
            parse_direct(b"%R70000"),
            addr(Area::R, 70000, None, IecType::Byte)
        );
    }

    #[test]
    fn malformed() {
        for text in [
            "",
            "%",
            "%R",
            "R100",
            "%Q1",
            "%RX1",
            "%RW",
            "%R-1",
            "%R+1",
            "%R1.",
            "%R1.8",
            "%R1.10",
            "%RW1.2",
            "%RL1.0",
            "%R1.2.3",
            "%R 1",
            "%R1 ",
            "%R4294967296",
            "%RW4294967295",
            "%RL4294967293",
            "%R1a",
            "%R.1",
            "%%R1",
        ] {
            assert_eq!(parse_direct(text.as_bytes()), None, "{text}");
        }
        assert!(parse_direct(b"%RL4294967292").is_some());
    }
}
