//! How a variable's bytes, as read from the PLC, become the value a client
//! sees, and how a client's value becomes the bytes written: the one place
//! for both (the server's `Var::decode`/`Var::encode` and the simulated PLC's
//! program use it).
//!
//! - [`Codec::Native`]: Tecomat memory, the type's own little-endian layout
//!   (public files and `%` addresses).
//! - [`Codec::Registers`]: Modbus registers. The raw value's bytes travel
//!   high byte first, in 16-bit words whose order [`WordOrder`] gives;
//!   8-bit types use one register (their value in its low byte); `STRING[n]`
//!   two characters a register, high byte first; [`Raw::Ts48`] a 48-bit count
//!   of milliseconds since 1970-01-01 UTC in three registers (shown as DT
//!   with milliseconds). With a [`Scale`] the client sees `raw x factor +
//!   offset`, computed in double precision, as LREAL, and a value written is
//!   converted back, refused when the raw value does not fit its type.
//!
//! Printing ([`Codec::format`]): the vendor's forms, except where a tag file
//! says more. Its `decimals` give a REAL's or LREAL's decimals (a REAL at
//! most 6); a scaled value without them prints in its shortest form within
//! NUM_OF_DECIMALS (at most 15): the shortest decimal that reads back as
//! the same double when it has no more decimals than that, else rounded to
//! that many with trailing zeros dropped. So 223 x 0.1 is `22.3`, not
//! `22.3000000000`, and 4294967295 x 0.001 is `4294967.295`, not
//! `4294967.2949999999`; with SCIENT_NOTATION the mantissa is shortened
//! alike (`2.5e+01`). The text reads back as the value printed
//! (`core::present` reads it).

use std::fmt;

use plccoms_protocol::value::{FormatOptions, Value};
use plccoms_protocol::IecType;

/// The order of a multi-register value's bytes on the wire, named by where
/// the bytes of the big-endian value ABCD (A most significant) go.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum WordOrder {
    /// High word first, high byte first (the Modbus convention; S7).
    #[default]
    Abcd,
    /// Low word first, high byte first (B&R, many energy meters).
    Cdab,
    /// High word first, bytes swapped within each word.
    Badc,
    /// Low word first, bytes swapped: plain little-endian.
    Dcba,
}

impl WordOrder {
    pub fn parse(text: &str) -> Option<WordOrder> {
        Some(match text.to_ascii_uppercase().as_str() {
            "ABCD" => WordOrder::Abcd,
            "CDAB" => WordOrder::Cdab,
            "BADC" => WordOrder::Badc,
            "DCBA" => WordOrder::Dcba,
            _ => return None,
        })
    }

    /// Rearranges big-endian `bytes` (an even count) into this order, or
    /// back: every order is its own inverse.
    pub fn apply(self, bytes: &mut [u8]) {
        match self {
            WordOrder::Abcd => {}
            WordOrder::Cdab => {
                let words = bytes.len() / 2;
                for i in 0..words / 2 {
                    let j = words - 1 - i;
                    bytes.swap(2 * i, 2 * j);
                    bytes.swap(2 * i + 1, 2 * j + 1);
                }
            }
            WordOrder::Badc => bytes.chunks_exact_mut(2).for_each(|w| w.swap(0, 1)),
            WordOrder::Dcba => bytes.reverse(),
        }
    }
}

impl fmt::Display for WordOrder {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            WordOrder::Abcd => "ABCD",
            WordOrder::Cdab => "CDAB",
            WordOrder::Badc => "BADC",
            WordOrder::Dcba => "DCBA",
        })
    }
}

/// What the registers hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Raw {
    Iec(IecType),
    /// Milliseconds since 1970-01-01 UTC, 48 bits in three registers.
    Ts48,
}

/// Client value = raw x `factor` + `offset`, shown as LREAL.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scale {
    pub factor: f64,
    pub offset: f64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Registers {
    pub raw: Raw,
    pub order: WordOrder,
    pub scale: Option<Scale>,
}

#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Codec {
    #[default]
    Native,
    Registers(Registers),
    /// An S7 type in a non-optimised block, big-endian (see
    /// [`crate::s7::value`]).
    S7(crate::s7::value::Layout),
}

/// Why a value cannot be written (answered as ERROR:35).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct EncodeError(pub String);

/// Largest TS48 value: 2^48 - 1 ms.
const TS48_MAX: u64 = (1 << 48) - 1;

impl Raw {
    /// Bytes (two per register) the raw value occupies.
    pub fn len(self) -> u32 {
        match self {
            Raw::Ts48 => 6,
            Raw::Iec(IecType::String(n)) => 2 * u32::from(n).div_ceil(2),
            Raw::Iec(ty) => (ty.size() as u32).max(2),
        }
    }

    pub fn is_empty(self) -> bool {
        false
    }
}

impl fmt::Display for Raw {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Raw::Iec(ty) => write!(f, "{ty}"),
            Raw::Ts48 => f.write_str("TS48"),
        }
    }
}

impl Codec {
    /// Bytes read from the PLC for a variable of client type `ty`.
    pub fn byte_len(&self, ty: IecType) -> u32 {
        match self {
            Codec::Native => ty.size() as u32,
            Codec::Registers(r) => r.raw.len(),
            Codec::S7(layout) => layout.len(),
        }
    }

    /// The client's value of the bytes read (`byte_len` of them; missing
    /// ones count as 0). A BOOL's bit is the caller's to pick.
    pub fn decode(&self, ty: IecType, bytes: &[u8]) -> Value {
        let r = match self {
            Codec::Native => return Value::decode(ty, bytes),
            Codec::S7(layout) => return layout.decode(bytes),
            Codec::Registers(r) => r,
        };
        let mut wire = [0u8; 8];
        let raw = match r.raw {
            Raw::Iec(IecType::String(n)) => {
                let mut text = bytes.to_vec();
                text.resize(r.raw.len() as usize, 0);
                r.order.apply(&mut text);
                return Value::decode(IecType::String(n), &text);
            }
            Raw::Ts48 => {
                let n = bytes.len().min(6);
                wire[..n].copy_from_slice(&bytes[..n]);
                r.order.apply(&mut wire[..6]);
                let ms = wire[..6]
                    .iter()
                    .fold(0u64, |acc, &b| acc << 8 | u64::from(b));
                Value::Date(ms as f64 / 1000.0)
            }
            Raw::Iec(raw_ty) => {
                let len = r.raw.len() as usize;
                let n = bytes.len().min(len);
                wire[..n].copy_from_slice(&bytes[..n]);
                let wire = &mut wire[..len];
                r.order.apply(wire);
                wire.reverse();
                Value::decode(raw_ty, wire)
            }
        };
        match r.scale {
            Some(scale) => Value::LReal(raw.as_f64() * scale.factor + scale.offset),
            None => raw,
        }
    }

    /// Appends the text GET and DIFF print for `value` of client type `ty`,
    /// `decimals` being what a tag file states (see the module's doc).
    pub fn format(
        &self,
        ty: IecType,
        decimals: Option<u8>,
        value: &Value,
        opts: &FormatOptions,
        out: &mut Vec<u8>,
    ) {
        let real = matches!(ty, IecType::Real | IecType::Lreal);
        let scaled = matches!(self, Codec::Registers(Registers { scale: Some(_), .. }));
        match decimals {
            Some(n) if real => {
                let opts = FormatOptions {
                    num_of_decimals: n,
                    ..*opts
                };
                value.format(ty, &opts, out);
            }
            None if real && scaled => shortest(value.as_f64(), opts, out),
            _ => value.format(ty, opts, out),
        }
    }

    /// The bytes that make a variable of client type `ty` hold `value`
    /// (`byte_len` of them), or why it cannot hold it.
    pub fn encode(&self, ty: IecType, value: &Value) -> Result<Vec<u8>, EncodeError> {
        let mut out = Vec::with_capacity(self.byte_len(ty) as usize);
        let r = match self {
            Codec::Native => {
                value.encode(ty, &mut out);
                return Ok(out);
            }
            Codec::S7(layout) => return layout.encode(value),
            Codec::Registers(r) => r,
        };
        let raw = match r.scale {
            Some(scale) => unscale(value, scale, r.raw)?,
            None => value.clone(),
        };
        match r.raw {
            Raw::Iec(IecType::String(n)) => {
                raw.encode(IecType::String(n), &mut out);
                out.truncate(r.raw.len() as usize);
                r.order.apply(&mut out);
            }
            Raw::Ts48 => {
                let ms = (raw.as_f64() * 1000.0).round();
                if !(0.0..=TS48_MAX as f64).contains(&ms) {
                    return Err(EncodeError(format!(
                        "{} s is outside what TS48 holds (1970 to year 10889)",
                        raw.as_f64()
                    )));
                }
                out.extend_from_slice(&(ms as u64).to_be_bytes()[2..]);
                r.order.apply(&mut out);
            }
            Raw::Iec(raw_ty) if raw_ty.size() == 1 => {
                // One register; a negative SINT is sign-extended to 16 bits.
                let mut byte = Vec::with_capacity(1);
                raw.encode(raw_ty, &mut byte);
                let word = if raw_ty == IecType::Sint {
                    i16::from(byte[0] as i8) as u16
                } else {
                    u16::from(byte[0])
                };
                out.extend_from_slice(&word.to_be_bytes());
                r.order.apply(&mut out);
            }
            Raw::Iec(raw_ty) => {
                raw.encode(raw_ty, &mut out);
                out.reverse();
                r.order.apply(&mut out);
            }
        }
        Ok(out)
    }
}

/// A double in its shortest form within NUM_OF_DECIMALS (see the module).
fn shortest(x: f64, opts: &FormatOptions, out: &mut Vec<u8>) {
    let decimals = opts.decimals(IecType::Lreal);
    if x.is_finite() {
        // Rust prints the shortest decimal that reads back as `x`; never -0.
        let x = if x == 0.0 { 0.0 } else { x };
        let text = if opts.scient_notation {
            format!("{x:e}")
        } else {
            format!("{x}")
        };
        let (mantissa, exponent) = match text.split_once('e') {
            Some((m, e)) => (m, Some(e)),
            None => (text.as_str(), None),
        };
        if mantissa.split_once('.').map_or(0, |(_, f)| f.len()) <= decimals {
            out.extend_from_slice(mantissa.as_bytes());
            if let Some(exponent) = exponent {
                // glibc's form: a sign and at least two digits.
                let exponent: i32 = exponent.parse().unwrap_or(0);
                let sign = if exponent < 0 { '-' } else { '+' };
                out.extend_from_slice(format!("e{sign}{:02}", exponent.unsigned_abs()).as_bytes());
            }
            return;
        }
    }
    let start = out.len();
    Value::LReal(x).format(IecType::Lreal, opts, out);
    drop_trailing_zeros(out, start);
}

/// `22.3000000000` as `22.3`, `5.0000000000` as `5`, `2.5000e+01` as
/// `2.5e+01` (the number printed from `start` on); `-0` as `0`.
fn drop_trailing_zeros(out: &mut Vec<u8>, start: usize) {
    let text = &out[start..];
    let mantissa_end = text.iter().position(|&b| b == b'e').unwrap_or(text.len());
    if !text[..mantissa_end].contains(&b'.') {
        return;
    }
    let mut end = mantissa_end;
    while text[end - 1] == b'0' {
        end -= 1;
    }
    if text[end - 1] == b'.' {
        end -= 1;
    }
    let exponent = text[mantissa_end..].to_vec();
    out.truncate(start + end);
    out.extend_from_slice(&exponent);
    if out[start..] == *b"-0" {
        out.remove(start);
    }
}

/// The raw value whose scaled value is `value`; refused when it does not fit
/// the raw type.
fn unscale(value: &Value, scale: Scale, raw: Raw) -> Result<Value, EncodeError> {
    let x = (value.as_f64() - scale.offset) / scale.factor;
    let Raw::Iec(ty) = raw else {
        return Ok(Value::LReal(x));
    };
    let out_of_range = |lo: f64, hi: f64| {
        EncodeError(format!(
            "raw value {x} (({} - {}) / {}) is outside {ty} ({lo}..{hi})",
            value.as_f64(),
            scale.offset,
            scale.factor
        ))
    };
    if !x.is_finite() {
        return Err(out_of_range(f64::MIN, f64::MAX));
    }
    let (lo, hi) = match ty {
        IecType::Real => {
            let max = f64::from(f32::MAX);
            if x.abs() > max {
                return Err(out_of_range(-max, max));
            }
            return Ok(Value::Real(x as f32));
        }
        IecType::Lreal => return Ok(Value::LReal(x)),
        IecType::Byte | IecType::Usint => (0.0, f64::from(u8::MAX)),
        IecType::Word | IecType::Uint => (0.0, f64::from(u16::MAX)),
        IecType::Dword | IecType::Udint | IecType::Time | IecType::Tod => {
            (0.0, f64::from(u32::MAX))
        }
        IecType::Lword | IecType::Ulint => (0.0, u64::MAX as f64),
        IecType::Sint => (f64::from(i8::MIN), f64::from(i8::MAX)),
        IecType::Int => (f64::from(i16::MIN), f64::from(i16::MAX)),
        IecType::Dint => (f64::from(i32::MIN), f64::from(i32::MAX)),
        IecType::Lint => (i64::MIN as f64, i64::MAX as f64),
        IecType::Bool | IecType::String(_) | IecType::Date | IecType::Dt => {
            return Err(EncodeError(format!("{ty} cannot be scaled")));
        }
    };
    let rounded = x.round();
    if rounded < lo || rounded > hi {
        return Err(out_of_range(lo, hi));
    }
    Ok(if lo < 0.0 {
        Value::Signed(rounded as i64)
    } else {
        Value::Unsigned(rounded as u64)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn regs(raw: Raw, order: WordOrder) -> Codec {
        Codec::Registers(Registers {
            raw,
            order,
            scale: None,
        })
    }

    #[test]
    fn word_orders_of_a_dint() {
        // 0x11223344 in each order.
        let cases = [
            (WordOrder::Abcd, [0x11, 0x22, 0x33, 0x44]),
            (WordOrder::Cdab, [0x33, 0x44, 0x11, 0x22]),
            (WordOrder::Badc, [0x22, 0x11, 0x44, 0x33]),
            (WordOrder::Dcba, [0x44, 0x33, 0x22, 0x11]),
        ];
        for (order, wire) in cases {
            let codec = regs(Raw::Iec(IecType::Udint), order);
            assert_eq!(
                codec.decode(IecType::Udint, &wire),
                Value::Unsigned(0x1122_3344),
                "{order}"
            );
            assert_eq!(
                codec
                    .encode(IecType::Udint, &Value::Unsigned(0x1122_3344))
                    .unwrap(),
                wire,
                "{order}"
            );
        }
    }

    #[test]
    fn sixty_four_bits_and_reals() {
        let codec = regs(Raw::Iec(IecType::Lreal), WordOrder::Cdab);
        let mut wire = 1.5f64.to_be_bytes();
        WordOrder::Cdab.apply(&mut wire);
        assert_eq!(wire[..2], 1.5f64.to_be_bytes()[6..]);
        assert_eq!(codec.decode(IecType::Lreal, &wire), Value::LReal(1.5));
        let real = regs(Raw::Iec(IecType::Real), WordOrder::Abcd);
        assert_eq!(
            real.encode(IecType::Real, &Value::Real(-2.25)).unwrap(),
            (-2.25f32).to_be_bytes()
        );
    }

    #[test]
    fn small_types_take_one_register() {
        let codec = regs(Raw::Iec(IecType::Sint), WordOrder::Abcd);
        assert_eq!(codec.byte_len(IecType::Sint), 2);
        assert_eq!(
            codec.decode(IecType::Sint, &[0xFF, 0xFE]),
            Value::Signed(-2)
        );
        assert_eq!(
            codec.encode(IecType::Sint, &Value::Signed(-2)).unwrap(),
            [0xFF, 0xFE]
        );
        let int = regs(Raw::Iec(IecType::Int), WordOrder::Abcd);
        assert_eq!(
            int.decode(IecType::Int, &[0x80, 0x00]),
            Value::Signed(-32768)
        );
    }

    #[test]
    fn strings_two_characters_a_register() {
        let codec = regs(Raw::Iec(IecType::String(5)), WordOrder::Abcd);
        assert_eq!(codec.byte_len(IecType::String(5)), 6);
        let wire = codec
            .encode(IecType::String(5), &Value::Str(b"Hello".to_vec()))
            .unwrap();
        assert_eq!(wire, b"Hello\0");
        assert_eq!(
            codec.decode(IecType::String(5), b"Hi\0\0\0\0"),
            Value::Str(b"Hi".to_vec())
        );
        let swapped = regs(Raw::Iec(IecType::String(4)), WordOrder::Badc);
        assert_eq!(
            swapped.decode(IecType::String(4), b"eHll"),
            Value::Str(b"Hell".to_vec())
        );
    }

    #[test]
    fn ts48_is_milliseconds_high_word_first() {
        let codec = regs(Raw::Ts48, WordOrder::Abcd);
        // 2024-03-15 13:45:30.500 UTC.
        let ms: u64 = 1_710_510_330_500;
        let wire = &ms.to_be_bytes()[2..];
        assert_eq!(
            codec.decode(IecType::Dt, wire),
            Value::Date(1_710_510_330.5)
        );
        assert_eq!(
            codec
                .encode(IecType::Dt, &Value::Date(1_710_510_330.5))
                .unwrap(),
            wire
        );
        assert!(codec.encode(IecType::Dt, &Value::Date(-1.0)).is_err());
    }

    #[test]
    fn scale_and_offset_round_trip_and_refuse_what_does_not_fit() {
        let codec = Codec::Registers(Registers {
            raw: Raw::Iec(IecType::Int),
            order: WordOrder::Abcd,
            scale: Some(Scale {
                factor: 0.1,
                offset: -40.0,
            }),
        });
        // raw 650 -> 25.0
        assert_eq!(
            codec.decode(IecType::Lreal, &[0x02, 0x8A]),
            Value::LReal(25.0)
        );
        assert_eq!(
            codec.encode(IecType::Lreal, &Value::LReal(25.0)).unwrap(),
            [0x02, 0x8A]
        );
        // (4000 + 40) / 0.1 = 40400 > 32767
        assert!(codec.encode(IecType::Lreal, &Value::LReal(4000.0)).is_err());
    }

    fn printed(
        codec: &Codec,
        ty: IecType,
        decimals: Option<u8>,
        bytes: &[u8],
        opts: &FormatOptions,
    ) -> String {
        let mut out = b"DIFF:X,".to_vec();
        codec.format(ty, decimals, &codec.decode(ty, bytes), opts, &mut out);
        String::from_utf8(out).unwrap()
    }

    /// The user's `scale 0.1`: raw 223 is 22.3, not 22.299999.
    #[test]
    fn a_scaled_value_prints_short_or_with_its_decimals() {
        let tenths = |raw: Raw| {
            Codec::Registers(Registers {
                raw,
                order: WordOrder::Abcd,
                scale: Some(Scale {
                    factor: 0.1,
                    offset: 0.0,
                }),
            })
        };
        let int = tenths(Raw::Iec(IecType::Int));
        let opts = FormatOptions::default();
        let raw = |n: i16| n.to_be_bytes();
        let ty = IecType::Lreal;
        assert_eq!(printed(&int, ty, None, &raw(223), &opts), "DIFF:X,22.3");
        assert_eq!(printed(&int, ty, None, &raw(3), &opts), "DIFF:X,0.3");
        assert_eq!(printed(&int, ty, None, &raw(250), &opts), "DIFF:X,25");
        assert_eq!(printed(&int, ty, None, &raw(-5), &opts), "DIFF:X,-0.5");
        assert_eq!(printed(&int, ty, None, &raw(0), &opts), "DIFF:X,0");
        assert_eq!(printed(&int, ty, Some(1), &raw(250), &opts), "DIFF:X,25.0");
        assert_eq!(printed(&int, ty, Some(2), &raw(223), &opts), "DIFF:X,22.30");
        assert_eq!(printed(&int, ty, Some(0), &raw(226), &opts), "DIFF:X,23");
        // Within NUM_OF_DECIMALS: 2 decimals at most.
        let two = FormatOptions {
            num_of_decimals: 2,
            ..opts
        };
        let hundredths = Codec::Registers(Registers {
            raw: Raw::Iec(IecType::Int),
            order: WordOrder::Abcd,
            scale: Some(Scale {
                factor: 0.001,
                offset: 0.0,
            }),
        });
        assert_eq!(
            printed(&hundredths, ty, None, &raw(1234), &two),
            "DIFF:X,1.23"
        );
        assert_eq!(printed(&hundredths, ty, None, &raw(-1), &two), "DIFF:X,0");
        // A counter past what a REAL holds keeps its last digits.
        let udint = Codec::Registers(Registers {
            raw: Raw::Iec(IecType::Udint),
            order: WordOrder::Abcd,
            scale: Some(Scale {
                factor: 0.001,
                offset: 0.0,
            }),
        });
        let wire = u32::MAX.to_be_bytes();
        assert_eq!(
            printed(&udint, ty, None, &wire, &opts),
            "DIFF:X,4294967.295"
        );
        let scient = FormatOptions {
            scient_notation: true,
            ..opts
        };
        assert_eq!(
            printed(&int, ty, None, &raw(250), &scient),
            "DIFF:X,2.5e+01"
        );
    }

    #[test]
    fn decimals_apply_to_unscaled_reals_and_nothing_else() {
        let real = regs(Raw::Iec(IecType::Real), WordOrder::Abcd);
        let opts = FormatOptions::default();
        let wire = 22.3f32.to_be_bytes();
        assert_eq!(
            printed(&real, IecType::Real, None, &wire, &opts),
            "DIFF:X,22.299999"
        );
        assert_eq!(
            printed(&real, IecType::Real, Some(1), &wire, &opts),
            "DIFF:X,22.3"
        );
        assert_eq!(
            printed(&real, IecType::Real, Some(9), &wire, &opts),
            "DIFF:X,22.299999"
        );
        let lreal = regs(Raw::Iec(IecType::Lreal), WordOrder::Abcd);
        let wire = 1.25f64.to_be_bytes();
        assert_eq!(
            printed(&lreal, IecType::Lreal, Some(3), &wire, &opts),
            "DIFF:X,1.250"
        );
        assert_eq!(
            printed(&lreal, IecType::Lreal, None, &wire, &opts),
            "DIFF:X,1.2500000000"
        );
        let int = regs(Raw::Iec(IecType::Int), WordOrder::Abcd);
        assert_eq!(
            printed(&int, IecType::Int, Some(2), &[0, 7], &opts),
            "DIFF:X,7"
        );
        assert_eq!(
            printed(
                &Codec::Native,
                IecType::Real,
                None,
                &22.5f32.to_le_bytes(),
                &opts
            ),
            "DIFF:X,22.500000"
        );
    }

    #[test]
    fn native_is_the_types_own_layout() {
        let codec = Codec::Native;
        assert_eq!(codec.byte_len(IecType::Int), 2);
        assert_eq!(
            codec.encode(IecType::Int, &Value::Signed(258)).unwrap(),
            [2, 1]
        );
        assert_eq!(codec.decode(IecType::Int, &[2, 1]), Value::Signed(258));
    }
}
