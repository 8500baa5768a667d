//! Variable values: PLC memory bytes <-> [`Value`] <-> the text of GET, SET
//! and DIFF lines, and the delta comparison that decides when a DIFF goes out.
//!
//! Text is cp1250 bytes throughout. Number formats follow what the shipping
//! server prints (C `printf` on glibc): `%.*f` for reals, `%.*e` with an
//! exponent of at least two digits in scientific notation.

use std::cmp::min;
use std::io::Write;

use thiserror::Error;

use crate::cp1250;
use crate::types::IecType;

/// Most decimals a REAL prints.
pub const REAL_MAX_DECIMALS: u8 = 6;
/// Most decimals an LREAL (and a decimal DATE/DT) prints.
pub const LREAL_MAX_DECIMALS: u8 = 15;

/// The ini settings that shape values (`NUM_OF_DECIMALS`, `SCIENT_NOTATION`,
/// `DATE_TIME_DECIMAL`, `LIM_OF_DECIMALS`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FormatOptions {
    pub num_of_decimals: u8,
    pub scient_notation: bool,
    pub date_time_decimal: bool,
    pub lim_of_decimals: bool,
}

impl Default for FormatOptions {
    fn default() -> Self {
        FormatOptions {
            num_of_decimals: 10,
            scient_notation: false,
            date_time_decimal: false,
            lim_of_decimals: false,
        }
    }
}

impl FormatOptions {
    /// Decimals printed for a real of type `ty` (REAL caps at 6, others at 15).
    pub fn decimals(&self, ty: IecType) -> usize {
        let cap = if ty == IecType::Real {
            REAL_MAX_DECIMALS
        } else {
            LREAL_MAX_DECIMALS
        };
        usize::from(min(self.num_of_decimals, cap))
    }
}

/// A variable's value. The variant follows the type: `Unsigned` for BYTE,
/// WORD, DWORD, LWORD, USINT, UINT, UDINT, ULINT; `Signed` for SINT, INT,
/// DINT, LINT; `Date` (seconds since 1970) for DATE and DT; `Time`
/// (milliseconds) for TIME and TOD. Functions given a variant that does not
/// fit the type convert it as `as` casts would; they never panic.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    Bool(bool),
    Unsigned(u64),
    Signed(i64),
    Real(f32),
    LReal(f64),
    /// cp1250 bytes without the terminating NUL.
    Str(Vec<u8>),
    Date(f64),
    Time(u32),
}

/// Why a value text or delta was refused (answered as ERROR 35).
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("{0}")]
pub struct ValueError(String);

impl ValueError {
    fn new(message: String) -> ValueError {
        ValueError(message)
    }

    pub fn message(&self) -> &str {
        &self.0
    }
}

/// The client's text for an error message, shortened so a hostile line cannot
/// make a huge log entry.
fn quote_text(text: &[u8]) -> String {
    const MAX: usize = 40;
    if text.len() > MAX {
        format!("'{}...'", cp1250::decode(&text[..MAX]))
    } else {
        format!("'{}'", cp1250::decode(text))
    }
}

/// A byte no STRING value may carry as it is on a line: C0 controls and DEL.
fn is_control(b: u8) -> bool {
    b < 0x20 || b == 0x7F
}

/// A string read from the PLC as a line may carry it: each control byte
/// (which a SET never writes, but a PLC program may) as `\xHH`, so that no
/// byte of a value can end or forge a line. Other bytes as they are.
fn write_printable(bytes: &[u8], out: &mut Vec<u8>) {
    let mut rest = bytes;
    while let Some(at) = rest.iter().position(|&b| is_control(b)) {
        out.extend_from_slice(&rest[..at]);
        let _ = write!(out, "\\x{:02X}", rest[at]);
        rest = &rest[at + 1..];
    }
    out.extend_from_slice(rest);
}

/// Inclusive range of an integer type, `None` for non-integers.
fn int_range(ty: IecType) -> Option<(i128, i128)> {
    Some(match ty {
        IecType::Byte | IecType::Usint => (0, u8::MAX.into()),
        IecType::Word | IecType::Uint => (0, u16::MAX.into()),
        IecType::Dword | IecType::Udint | IecType::Time | IecType::Tod => (0, u32::MAX.into()),
        IecType::Lword | IecType::Ulint => (0, u64::MAX.into()),
        IecType::Sint => (i8::MIN.into(), i8::MAX.into()),
        IecType::Int => (i16::MIN.into(), i16::MAX.into()),
        IecType::Dint => (i32::MIN.into(), i32::MAX.into()),
        IecType::Lint => (i64::MIN.into(), i64::MAX.into()),
        _ => return None,
    })
}

fn is_signed(ty: IecType) -> bool {
    matches!(
        ty,
        IecType::Sint | IecType::Int | IecType::Dint | IecType::Lint
    )
}

/// Parses `[+-]digits` exactly; the magnitude saturates far beyond any
/// 64-bit value so range checks stay exact. `None` if not of that form.
fn parse_decimal_integer(text: &[u8]) -> Option<i128> {
    let (negative, digits) = match text.first() {
        Some(b'-') => (true, &text[1..]),
        Some(b'+') => (false, &text[1..]),
        _ => (false, text),
    };
    if digits.is_empty() || !digits.iter().all(u8::is_ascii_digit) {
        return None;
    }
    const CAP: i128 = 1 << 100;
    let magnitude = digits
        .iter()
        .fold(0i128, |n, d| min(CAP, n * 10 + i128::from(d - b'0')));
    Some(if negative { -magnitude } else { magnitude })
}

/// The parts of a decimal number `[+-]digits[.digits][e[+-]digits]` (also
/// `.5`, `5.`), as [`scan_number`] finds them.
struct NumberParts<'a> {
    negative: bool,
    int_digits: &'a [u8],
    frac_digits: &'a [u8],
    /// Saturated to +-1_000_000, far beyond any finite f64.
    exponent: i64,
}

fn scan_number(text: &[u8]) -> Option<NumberParts<'_>> {
    let mut i = 0;
    let negative = match text.first() {
        Some(b'-') => {
            i += 1;
            true
        }
        Some(b'+') => {
            i += 1;
            false
        }
        _ => false,
    };
    let digits_from = |i: usize| {
        text[i..]
            .iter()
            .position(|b| !b.is_ascii_digit())
            .map_or(text.len(), |p| i + p)
    };
    let int_end = digits_from(i);
    let int_digits = &text[i..int_end];
    i = int_end;
    let mut frac_digits: &[u8] = &[];
    if text.get(i) == Some(&b'.') {
        let frac_end = digits_from(i + 1);
        frac_digits = &text[i + 1..frac_end];
        i = frac_end;
    }
    if int_digits.is_empty() && frac_digits.is_empty() {
        return None;
    }
    let mut exponent = 0i64;
    if matches!(text.get(i), Some(b'e' | b'E')) {
        i += 1;
        let exp_negative = match text.get(i) {
            Some(b'-') => {
                i += 1;
                true
            }
            Some(b'+') => {
                i += 1;
                false
            }
            _ => false,
        };
        let exp_end = digits_from(i);
        if exp_end == i {
            return None;
        }
        let magnitude = text[i..exp_end]
            .iter()
            .fold(0i64, |n, d| min(1_000_000, n * 10 + i64::from(d - b'0')));
        exponent = if exp_negative { -magnitude } else { magnitude };
        i = exp_end;
    }
    if i != text.len() {
        return None;
    }
    Some(NumberParts {
        negative,
        int_digits,
        frac_digits,
        exponent,
    })
}

/// Parses a decimal or scientific real (no `inf`/`nan`) as f64 or f32.
fn parse_real<T: std::str::FromStr>(text: &[u8]) -> Option<T> {
    scan_number(text)?;
    // scan_number admitted ASCII only, so this is valid UTF-8 and a form
    // Rust's correctly-rounding float parser accepts.
    std::str::from_utf8(text).ok()?.parse().ok()
}

/// `printf("%.*f")` / `printf("%.*e")` as glibc prints them.
fn format_float(x: f64, decimals: usize, scientific: bool, out: &mut Vec<u8>) {
    if x.is_nan() {
        out.extend_from_slice(if x.is_sign_negative() {
            b"-nan"
        } else {
            b"nan"
        });
        return;
    }
    if x.is_infinite() {
        out.extend_from_slice(if x < 0.0 { b"-inf" } else { b"inf" });
        return;
    }
    if !scientific {
        if print_short_binary(x, decimals, out) {
            return;
        }
        // Rust rounds the exact binary value half-to-even, as glibc does.
        let _ = write!(out, "{x:.decimals$}");
        return;
    }
    // Rust prints `1.2345e0`; glibc prints `1.2345e+00`.
    let text = format!("{x:.decimals$e}");
    let (mantissa, exponent) = text.split_once('e').unwrap_or((&text, "0"));
    let exponent: i32 = exponent.parse().unwrap_or(0);
    let sign = if exponent < 0 { '-' } else { '+' };
    let _ = write!(out, "{mantissa}e{sign}{:02}", exponent.unsigned_abs());
}

/// Prints `x` with `decimals` decimals when its binary value has at most
/// that many fractional bits (an integer, 21.5, 0.25): then its decimal
/// expansion ends within them and every digit is exact, with no rounding.
/// Rust's exact formatting takes its slowest path for these (2x a longer
/// value's time, 7x an integer's: `cargo bench --bench protocol --
/// format/`), and counters and setpoints are such values.
fn print_short_binary(x: f64, decimals: usize, out: &mut Vec<u8>) -> bool {
    // 5^k for k fractional bits fits a u128 beside the 53-bit fraction.
    const MOST_BITS: u32 = 20;
    if x.abs() >= 9.0e18 {
        return false;
    }
    let bits = x.to_bits();
    let biased = ((bits >> 52) & 0x7ff) as i32;
    let (mut mantissa, mut exponent) = match biased {
        0 => (bits & ((1 << 52) - 1), -1074),
        _ => ((bits & ((1 << 52) - 1)) | 1 << 52, biased - 1075),
    };
    if mantissa == 0 {
        exponent = 0;
    } else {
        let zeros = mantissa.trailing_zeros();
        mantissa >>= zeros;
        exponent += zeros as i32;
    }
    let (whole, fraction_bits, fraction) = if exponent >= 0 {
        (mantissa << exponent, 0, 0)
    } else {
        let k = exponent.unsigned_abs();
        if k > MOST_BITS || k as usize > decimals {
            return false;
        }
        (mantissa >> k, k, mantissa & ((1 << k) - 1))
    };
    if x.is_sign_negative() {
        out.push(b'-');
    }
    let _ = write!(out, "{whole}");
    if decimals > 0 {
        out.push(b'.');
        if fraction_bits > 0 {
            // fraction / 2^k = fraction * 5^k / 10^k: k digits exactly.
            let digits = u128::from(fraction) * 5u128.pow(fraction_bits);
            let _ = write!(out, "{digits:0width$}", width = fraction_bits as usize);
        }
        out.resize(out.len() + decimals - fraction_bits as usize, b'0');
    }
    true
}

impl Value {
    fn as_u64(&self) -> u64 {
        match self {
            Value::Bool(b) => u64::from(*b),
            Value::Unsigned(u) => *u,
            Value::Signed(i) => *i as u64,
            Value::Real(f) => *f as u64,
            Value::LReal(f) | Value::Date(f) => *f as u64,
            Value::Str(_) => 0,
            Value::Time(t) => u64::from(*t),
        }
    }

    fn as_i64(&self) -> i64 {
        match self {
            Value::Signed(i) => *i,
            Value::Real(f) => *f as i64,
            Value::LReal(f) | Value::Date(f) => *f as i64,
            other => other.as_u64() as i64,
        }
    }

    /// The value as a number (BOOL 0/1, DATE/DT in seconds, STRING 0).
    pub fn as_f64(&self) -> f64 {
        match self {
            Value::Bool(b) => f64::from(u8::from(*b)),
            Value::Unsigned(u) => *u as f64,
            Value::Signed(i) => *i as f64,
            Value::Real(f) => f64::from(*f),
            Value::LReal(f) | Value::Date(f) => *f,
            Value::Str(_) => 0.0,
            Value::Time(t) => f64::from(*t),
        }
    }

    /// Exact integer view for delta comparison.
    fn as_i128(&self) -> i128 {
        match self {
            Value::Signed(i) => i128::from(*i),
            Value::Real(f) => *f as i128,
            Value::LReal(f) | Value::Date(f) => *f as i128,
            other => i128::from(other.as_u64()),
        }
    }

    /// Decodes `ty.size()` little-endian bytes of PLC memory. For BOOL the
    /// caller has extracted the bit: any non-zero `raw[0]` is true. Missing
    /// bytes count as 0.
    pub fn decode(ty: IecType, raw: &[u8]) -> Value {
        let mut buf = [0u8; 8];
        let n = min(raw.len(), 8);
        buf[..n].copy_from_slice(&raw[..n]);
        let u = u64::from_le_bytes(buf);
        match ty {
            IecType::Bool => Value::Bool(buf[0] != 0),
            IecType::Byte | IecType::Usint => Value::Unsigned(u & 0xFF),
            IecType::Word | IecType::Uint => Value::Unsigned(u & 0xFFFF),
            IecType::Dword | IecType::Udint => Value::Unsigned(u & 0xFFFF_FFFF),
            IecType::Lword | IecType::Ulint => Value::Unsigned(u),
            IecType::Sint => Value::Signed(i64::from(u as u8 as i8)),
            IecType::Int => Value::Signed(i64::from(u as u16 as i16)),
            IecType::Dint => Value::Signed(i64::from(u as u32 as i32)),
            IecType::Lint => Value::Signed(u as i64),
            IecType::Real => Value::Real(f32::from_bits(u as u32)),
            IecType::Lreal => Value::LReal(f64::from_bits(u)),
            IecType::Date | IecType::Dt => Value::Date(f64::from_bits(u)),
            IecType::Time | IecType::Tod => Value::Time(u as u32),
            IecType::String(cap) => {
                let raw = &raw[..min(raw.len(), usize::from(cap))];
                let end = raw.iter().position(|&b| b == 0).unwrap_or(raw.len());
                Value::Str(raw[..end].to_vec())
            }
        }
    }

    /// Appends exactly `ty.size()` little-endian bytes. STRING: the bytes (at
    /// most the capacity), then NULs up to `n + 1`. BOOL: one byte, 0 or 1.
    pub fn encode(&self, ty: IecType, out: &mut Vec<u8>) {
        self.encode_with(ty, |bytes| out.extend_from_slice(bytes));
    }

    /// [`Value::encode`], the bytes handed to `put` in pieces: into a
    /// buffer of any kind (an inline one takes no allocation).
    pub fn encode_with(&self, ty: IecType, mut put: impl FnMut(&[u8])) {
        match ty {
            IecType::Real => {
                let f = match self {
                    Value::Real(f) => *f,
                    other => other.as_f64() as f32,
                };
                put(&f.to_le_bytes());
            }
            IecType::Lreal | IecType::Date | IecType::Dt => {
                put(&self.as_f64().to_le_bytes());
            }
            IecType::String(cap) => {
                let mut padding = ty.size();
                if let Value::Str(bytes) = self {
                    let bytes = &bytes[..min(bytes.len(), usize::from(cap))];
                    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
                    put(&bytes[..end]);
                    padding -= end;
                }
                const ZEROS: [u8; 64] = [0; 64];
                while padding > 0 {
                    let n = padding.min(ZEROS.len());
                    put(&ZEROS[..n]);
                    padding -= n;
                }
            }
            IecType::Bool => put(&[u8::from(self.as_u64() != 0)]),
            _ => {
                let bits = if is_signed(ty) {
                    self.as_i64() as u64
                } else {
                    self.as_u64()
                };
                put(&bits.to_le_bytes()[..ty.size()]);
            }
        }
    }

    /// Parses the value text of a SET (the caller trimmed surrounding spaces).
    pub fn parse(ty: IecType, text: &[u8], opts: &FormatOptions) -> Result<Value, ValueError> {
        match ty {
            IecType::Bool => match text {
                b"1" => Ok(Value::Bool(true)),
                b"0" => Ok(Value::Bool(false)),
                t if t.eq_ignore_ascii_case(b"true") => Ok(Value::Bool(true)),
                t if t.eq_ignore_ascii_case(b"false") => Ok(Value::Bool(false)),
                _ => Err(ValueError::new(format!(
                    "{} is not a BOOL (1, 0, true or false)",
                    quote_text(text)
                ))),
            },
            IecType::Real => {
                let x: f32 = parse_real(text).ok_or_else(|| not_a_number(text, ty))?;
                if x.is_finite() {
                    Ok(Value::Real(x))
                } else {
                    Err(ValueError::new(format!(
                        "value {} out of range for REAL",
                        quote_text(text)
                    )))
                }
            }
            IecType::Lreal => parse_lreal(text, ty).map(Value::LReal),
            IecType::Date | IecType::Dt if opts.date_time_decimal => {
                parse_lreal(text, ty).map(Value::Date)
            }
            IecType::Date | IecType::Dt => {
                let bits = parse_int(text, ty, (0, u64::MAX.into()))?;
                Ok(Value::Date(f64::from_bits(bits as u64)))
            }
            IecType::String(cap) => {
                let inner = match text {
                    [b'"', inner @ .., b'"'] => inner,
                    _ => text,
                };
                // A CR or LF would end the line of every client the value
                // is printed to (forged DIFF lines); no control character
                // has a place in a PLC string.
                if let Some(at) = inner.iter().position(|&b| is_control(b)) {
                    return Err(ValueError::new(format!(
                        "string for {ty} contains the control character 0x{:02X} at position {}",
                        inner[at],
                        at + 1
                    )));
                }
                if inner.len() > usize::from(cap) {
                    return Err(ValueError::new(format!(
                        "string of {} characters exceeds {ty}",
                        inner.len()
                    )));
                }
                Ok(Value::Str(inner.to_vec()))
            }
            IecType::Time | IecType::Tod => {
                let n = parse_int(text, ty, (0, u32::MAX.into()))?;
                Ok(Value::Time(n as u32))
            }
            _ => {
                let range = int_range(ty).unwrap_or((0, 0));
                let n = parse_int(text, ty, range)?;
                Ok(if is_signed(ty) {
                    Value::Signed(n as i64)
                } else {
                    Value::Unsigned(n as u64)
                })
            }
        }
    }

    /// Appends the text GET and DIFF print for this value of type `ty`.
    pub fn format(&self, ty: IecType, opts: &FormatOptions, out: &mut Vec<u8>) {
        match ty {
            IecType::Bool => out.push(if self.as_u64() != 0 { b'1' } else { b'0' }),
            IecType::Sint | IecType::Int | IecType::Dint | IecType::Lint => {
                let _ = write!(out, "{}", self.as_i64());
            }
            IecType::Real | IecType::Lreal => {
                format_float(self.as_f64(), opts.decimals(ty), opts.scient_notation, out)
            }
            IecType::Date | IecType::Dt if opts.date_time_decimal => {
                format_float(self.as_f64(), opts.decimals(ty), opts.scient_notation, out)
            }
            IecType::Date | IecType::Dt => {
                let _ = write!(out, "{}", self.as_f64().to_bits());
            }
            IecType::Time | IecType::Tod => {
                let _ = write!(out, "{}", self.as_u64() as u32);
            }
            IecType::String(_) => {
                out.push(b'"');
                if let Value::Str(bytes) = self {
                    write_printable(bytes, out);
                }
                out.push(b'"');
            }
            _ => {
                let _ = write!(out, "{}", self.as_u64());
            }
        }
    }

    /// Whether the change from `last` (the value last sent) to `self` is
    /// worth a DIFF: `|self - last| > delta`. Integers and times compare
    /// exactly; reals in f64 (rounded as displayed with `lim_of_decimals`);
    /// BOOL and STRING on any difference.
    pub fn exceeds(&self, last: &Value, delta: &Delta, ty: IecType, opts: &FormatOptions) -> bool {
        match ty {
            IecType::Bool => (self.as_u64() != 0) != (last.as_u64() != 0),
            IecType::String(_) => self != last,
            IecType::Real | IecType::Lreal | IecType::Date | IecType::Dt => {
                let (mut a, mut b) = (self.as_f64(), last.as_f64());
                let displayed_as_real = !ty_is_date(ty) || opts.date_time_decimal;
                if opts.lim_of_decimals && displayed_as_real {
                    a = round_as_displayed(a, ty, opts);
                    b = round_as_displayed(b, ty, opts);
                }
                if a.is_nan() || b.is_nan() {
                    return a.to_bits() != b.to_bits();
                }
                if a == b {
                    return false;
                }
                let diff = (a - b).abs();
                // inf - inf is excluded above; NaN here cannot happen.
                diff > delta.real
            }
            _ => {
                let diff = (self.as_i128() - last.as_i128()).unsigned_abs();
                diff > u128::from(delta.floor)
            }
        }
    }
}

fn ty_is_date(ty: IecType) -> bool {
    matches!(ty, IecType::Date | IecType::Dt)
}

/// The value as a client sees it printed, read back.
fn round_as_displayed(x: f64, ty: IecType, opts: &FormatOptions) -> f64 {
    if !x.is_finite() {
        return x;
    }
    let mut text = Vec::with_capacity(32);
    format_float(x, opts.decimals(ty), opts.scient_notation, &mut text);
    parse_real(&text).unwrap_or(x)
}

fn not_a_number(text: &[u8], ty: IecType) -> ValueError {
    ValueError::new(format!("{} is not a number ({ty})", quote_text(text)))
}

fn parse_lreal(text: &[u8], ty: IecType) -> Result<f64, ValueError> {
    let x: f64 = parse_real(text).ok_or_else(|| not_a_number(text, ty))?;
    if x.is_finite() {
        Ok(x)
    } else {
        Err(ValueError::new(format!(
            "value {} out of range for {ty}",
            quote_text(text)
        )))
    }
}

fn parse_int(text: &[u8], ty: IecType, (lo, hi): (i128, i128)) -> Result<i128, ValueError> {
    let n = parse_decimal_integer(text).ok_or_else(|| {
        ValueError::new(format!(
            "{} is not a decimal integer ({ty})",
            quote_text(text)
        ))
    })?;
    if n < lo || n > hi {
        // The text is digits only here; show it as given (shortened).
        let shown = if text.len() > 40 {
            format!("{}...", cp1250::decode(&text[..40]))
        } else {
            cp1250::decode(text).into_owned()
        };
        return Err(ValueError::new(format!(
            "value {shown} out of range for {ty} ({lo}..{hi})"
        )));
    }
    Ok(n)
}

/// The change a variable must exceed before a DIFF goes out (`EN:name delta`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Delta {
    /// The delta as a real, for REAL, LREAL, DATE, DT.
    real: f64,
    /// floor(delta), exact from the text, saturated: for integer types
    /// `|a - b| > delta` is exactly `|a - b| > floor(delta)`.
    floor: u64,
}

impl Default for Delta {
    fn default() -> Self {
        Delta::ZERO
    }
}

impl Delta {
    pub const ZERO: Delta = Delta {
        real: 0.0,
        floor: 0,
    };

    /// Parses a non-negative decimal number: `10`, `0.5`, `1e3`, `+2`.
    pub fn parse(text: &[u8]) -> Result<Delta, ValueError> {
        let bad = || {
            ValueError::new(format!(
                "{} is not a non-negative number (delta)",
                quote_text(text)
            ))
        };
        let parts = scan_number(text).ok_or_else(bad)?;
        if parts.negative {
            return Err(bad());
        }
        let real: f64 = parse_real(text).ok_or_else(bad)?;
        if !real.is_finite() {
            return Err(bad());
        }
        // floor: the digits with the decimal point shifted by the exponent.
        let digits = parts.int_digits.iter().chain(parts.frac_digits);
        let point = parts.int_digits.len() as i64 + parts.exponent;
        let mut floor: u64 = 0;
        let mut taken: i64 = 0;
        for &d in digits {
            if taken >= point {
                break;
            }
            floor = floor.saturating_mul(10).saturating_add(u64::from(d - b'0'));
            taken += 1;
        }
        // Zeros the exponent appends past the last digit.
        while taken < point && floor != 0 && floor != u64::MAX {
            floor = floor.saturating_mul(10);
            taken += 1;
        }
        Ok(Delta { real, floor })
    }

    pub fn is_zero(&self) -> bool {
        self.real == 0.0 && self.floor == 0
    }

    /// The delta as a real.
    pub fn as_f64(&self) -> f64 {
        self.real
    }

    /// floor(delta), saturated at `u64::MAX`.
    pub fn floor(&self) -> u64 {
        self.floor
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fmt(v: &Value, ty: IecType, opts: &FormatOptions) -> String {
        let mut out = Vec::new();
        v.format(ty, opts, &mut out);
        String::from_utf8(out).unwrap()
    }

    fn fmt_default(v: &Value, ty: IecType) -> String {
        fmt(v, ty, &FormatOptions::default())
    }

    fn parse(ty: IecType, text: &str) -> Result<Value, ValueError> {
        Value::parse(ty, text.as_bytes(), &FormatOptions::default())
    }

    fn delta(text: &str) -> Delta {
        Delta::parse(text.as_bytes()).unwrap()
    }

    #[test]
    fn bool_values() {
        assert_eq!(fmt_default(&Value::Bool(true), IecType::Bool), "1");
        assert_eq!(fmt_default(&Value::Bool(false), IecType::Bool), "0");
        for (text, v) in [
            ("1", true),
            ("0", false),
            ("true", true),
            ("TRUE", true),
            ("False", false),
        ] {
            assert_eq!(parse(IecType::Bool, text), Ok(Value::Bool(v)), "{text}");
        }
        for text in ["2", "yes", "", " 1", "01", "truex"] {
            assert!(parse(IecType::Bool, text).is_err(), "{text}");
        }
    }

    #[test]
    fn integer_parse_and_ranges() {
        assert_eq!(parse(IecType::Usint, "255"), Ok(Value::Unsigned(255)));
        assert_eq!(parse(IecType::Usint, "+7"), Ok(Value::Unsigned(7)));
        assert_eq!(parse(IecType::Usint, "-0"), Ok(Value::Unsigned(0)));
        assert_eq!(
            parse(IecType::Usint, "300").unwrap_err().message(),
            "value 300 out of range for USINT (0..255)"
        );
        assert_eq!(
            parse(IecType::Uint, "-1").unwrap_err().message(),
            "value -1 out of range for UINT (0..65535)"
        );
        assert_eq!(parse(IecType::Sint, "-128"), Ok(Value::Signed(-128)));
        assert!(parse(IecType::Sint, "128").is_err());
        assert!(parse(IecType::Sint, "-129").is_err());
        assert_eq!(parse(IecType::Int, "-32768"), Ok(Value::Signed(-32768)));
        assert_eq!(
            parse(IecType::Dint, "2147483647"),
            Ok(Value::Signed(i32::MAX.into()))
        );
        assert!(parse(IecType::Dint, "2147483648").is_err());
        assert_eq!(
            parse(IecType::Udint, "4294967295"),
            Ok(Value::Unsigned(u32::MAX.into()))
        );
        assert!(parse(IecType::Dword, "4294967296").is_err());
        assert!(parse(IecType::Ulint, "18446744073709551616").is_err());
        assert!(parse(IecType::Ulint, &"9".repeat(500)).is_err());
        for text in ["1.5", "1e3", "0x10", "", "-", "+", "1 2", "12a", "٣"] {
            assert!(parse(IecType::Int, text).is_err(), "{text}");
        }
        assert_eq!(
            parse(IecType::Int, "1.5").unwrap_err().message(),
            "'1.5' is not a decimal integer (INT)"
        );
    }

    #[test]
    fn integers_print_plain_decimal() {
        assert_eq!(fmt_default(&Value::Unsigned(123), IecType::Byte), "123");
        assert_eq!(fmt_default(&Value::Signed(-5), IecType::Int), "-5");
        assert_eq!(
            fmt_default(&Value::Unsigned(u64::MAX), IecType::Lword),
            "18446744073709551615"
        );
        assert_eq!(
            fmt_default(&Value::Time(86_399_999), IecType::Tod),
            "86399999"
        );
        // Unsigned types never print negative, whatever the memory holds.
        let v = Value::decode(IecType::Uint, &[0xFF, 0xFF]);
        assert_eq!(fmt_default(&v, IecType::Uint), "65535");
        let v = Value::decode(IecType::Int, &[0xFF, 0xFF]);
        assert_eq!(fmt_default(&v, IecType::Int), "-1");
    }

    #[test]
    fn ulint_and_lint_extremes_round_trip() {
        let opts = FormatOptions::default();
        for (ty, v) in [
            (IecType::Ulint, Value::Unsigned(u64::MAX)),
            (IecType::Lword, Value::Unsigned(u64::MAX)),
            (IecType::Lint, Value::Signed(i64::MIN)),
            (IecType::Lint, Value::Signed(i64::MAX)),
        ] {
            let text = fmt(&v, ty, &opts);
            assert_eq!(Value::parse(ty, text.as_bytes(), &opts), Ok(v.clone()));
            let mut raw = Vec::new();
            v.encode(ty, &mut raw);
            assert_eq!(raw.len(), 8);
            assert_eq!(Value::decode(ty, &raw), v);
        }
        assert_eq!(
            fmt_default(&Value::Signed(i64::MIN), IecType::Lint),
            "-9223372036854775808"
        );
    }

    #[test]
    fn real_formats() {
        let opts = FormatOptions::default();
        assert_eq!(fmt(&Value::Real(1.2345), IecType::Real, &opts), "1.234500");
        assert_eq!(
            fmt(&Value::LReal(1.2345), IecType::Lreal, &opts),
            "1.2345000000"
        );
        let zero = FormatOptions {
            num_of_decimals: 0,
            ..opts
        };
        assert_eq!(fmt(&Value::Real(3.2), IecType::Real, &zero), "3");
        assert_eq!(fmt(&Value::LReal(2.5), IecType::Lreal, &zero), "2");
        let two = FormatOptions {
            num_of_decimals: 2,
            ..opts
        };
        assert_eq!(fmt(&Value::LReal(0.125), IecType::Lreal, &two), "0.12");
        assert_eq!(fmt(&Value::LReal(2.675), IecType::Lreal, &two), "2.67");
        assert_eq!(fmt(&Value::LReal(-0.001), IecType::Lreal, &two), "-0.00");
        let many = FormatOptions {
            num_of_decimals: 40,
            ..opts
        };
        assert_eq!(fmt(&Value::Real(0.1), IecType::Real, &many), "0.100000");
        assert_eq!(
            fmt(&Value::LReal(0.1), IecType::Lreal, &many),
            "0.100000000000000"
        );
        assert_eq!(
            fmt(&Value::LReal(1e21), IecType::Lreal, &two),
            "1000000000000000000000.00"
        );
    }

    #[test]
    fn short_binary_reals_print_as_the_exact_formatting_does() {
        let mut values = vec![
            0.0,
            -0.0,
            1.0,
            -1.0,
            16_777_216.0,
            9_007_199_254_740_992.0,
            9_007_199_254_740_994.0,
            -9_007_199_254_740_994.0,
            8.999_999_999_999_998e18,
            -8.999_999_999_999_998e18,
            9.0e18,
            1e21,
        ];
        let mut n: u64 = 1;
        while n < 1 << 62 {
            values.extend([
                n as f64,
                -(n as f64),
                f64::from(n as f32),
                (n * 7 + 3) as f64,
            ]);
            n = n * 3 + 1;
        }
        // Few fractional bits (21.5, -0.25, 1/2^20, 3 + 2^-21) and many.
        for k in 0..=22 {
            let step = 0.5f64.powi(k);
            for whole in [0.0, 21.0, -3.0, 123_456.0, 4_503_599_627_370_495.0] {
                values.extend([whole + step, whole - step, step * 3.0]);
            }
        }
        values.extend([21.537, f64::from(21.537f32), 1e-300, 5e-324, 0.1]);
        // The own path is taken where it can be, and only there.
        let short = |x: f64, decimals| print_short_binary(x, decimals, &mut Vec::new());
        for (x, decimals) in [(1234.0, 0), (-0.0, 2), (21.5, 6), (0.0625, 4)] {
            assert!(short(x, decimals), "{x} with {decimals} decimals");
        }
        for (x, decimals) in [(21.537, 6), (-0.125, 2), (9.5e18, 2), (5e-324, 40)] {
            assert!(!short(x, decimals), "{x} with {decimals} decimals");
        }
        for x in values {
            for decimals in [0, 1, 2, 6, 10, 15, 40] {
                let mut out = Vec::new();
                format_float(x, decimals, false, &mut out);
                assert_eq!(
                    String::from_utf8(out).unwrap(),
                    format!("{x:.decimals$}"),
                    "{x} with {decimals} decimals"
                );
            }
        }
        let two = FormatOptions {
            num_of_decimals: 2,
            ..FormatOptions::default()
        };
        assert_eq!(fmt(&Value::LReal(-0.0), IecType::Lreal, &two), "-0.00");
        assert_eq!(fmt(&Value::Real(-1234.0), IecType::Real, &two), "-1234.00");
        assert_eq!(fmt(&Value::Real(21.5), IecType::Real, &two), "21.50");
        assert_eq!(fmt(&Value::Real(-0.125), IecType::Real, &two), "-0.12");
    }

    #[test]
    fn real_scientific_like_glibc() {
        let sci = FormatOptions {
            scient_notation: true,
            ..FormatOptions::default()
        };
        assert_eq!(
            fmt(&Value::Real(1.2345), IecType::Real, &sci),
            "1.234500e+00"
        );
        assert_eq!(
            fmt(&Value::LReal(-3.1e-7), IecType::Lreal, &sci),
            "-3.1000000000e-07"
        );
        assert_eq!(
            fmt(&Value::LReal(123456789.98765433), IecType::Lreal, &sci),
            "1.2345678999e+08"
        );
        assert_eq!(
            fmt(&Value::LReal(1e300), IecType::Lreal, &sci),
            "1.0000000000e+300"
        );
        let zero = FormatOptions {
            num_of_decimals: 0,
            ..sci
        };
        assert_eq!(fmt(&Value::LReal(1234.0), IecType::Lreal, &zero), "1e+03");
        assert_eq!(fmt(&Value::LReal(0.0), IecType::Lreal, &zero), "0e+00");
    }

    #[test]
    fn nan_and_infinity_like_glibc() {
        let opts = FormatOptions::default();
        assert_eq!(fmt(&Value::Real(f32::NAN), IecType::Real, &opts), "nan");
        assert_eq!(fmt(&Value::Real(-f32::NAN), IecType::Real, &opts), "-nan");
        assert_eq!(
            fmt(&Value::LReal(f64::INFINITY), IecType::Lreal, &opts),
            "inf"
        );
        assert_eq!(
            fmt(&Value::LReal(f64::NEG_INFINITY), IecType::Lreal, &opts),
            "-inf"
        );
    }

    #[test]
    fn real_parse() {
        assert_eq!(parse(IecType::Real, "1.5"), Ok(Value::Real(1.5)));
        assert_eq!(parse(IecType::Real, "-2"), Ok(Value::Real(-2.0)));
        assert_eq!(parse(IecType::Real, ".5"), Ok(Value::Real(0.5)));
        assert_eq!(parse(IecType::Real, "5."), Ok(Value::Real(5.0)));
        assert_eq!(parse(IecType::Lreal, "1.5E-3"), Ok(Value::LReal(0.0015)));
        assert_eq!(parse(IecType::Lreal, "2e+2"), Ok(Value::LReal(200.0)));
        assert!(parse(IecType::Real, "1e39").is_err());
        assert!(parse(IecType::Real, "3.5e38").is_err());
        assert_eq!(parse(IecType::Real, "3.4e38"), Ok(Value::Real(3.4e38)));
        assert!(parse(IecType::Lreal, "1e309").is_err());
        for text in [
            "inf", "nan", "NaN", "infinity", "", ".", "e5", "1e", "1,5", "1.2.3", " 1", "0x1",
        ] {
            assert!(parse(IecType::Lreal, text).is_err(), "{text}");
        }
    }

    #[test]
    fn strings() {
        let ty = IecType::String(80);
        let v = Value::Str(b"Have a nice day".to_vec());
        assert_eq!(fmt_default(&v, ty), "\"Have a nice day\"");
        assert_eq!(parse(ty, "\"Have a nice day\""), Ok(v.clone()));
        assert_eq!(parse(ty, "Have a nice day"), Ok(v));
        assert_eq!(parse(ty, "\"a,b:c\""), Ok(Value::Str(b"a,b:c".to_vec())));
        assert_eq!(parse(ty, "\"\""), Ok(Value::Str(Vec::new())));
        assert_eq!(parse(ty, "\""), Ok(Value::Str(b"\"".to_vec())));
        assert_eq!(parse(ty, "\"x"), Ok(Value::Str(b"\"x".to_vec())));
        assert_eq!(parse(ty, "\"\"\""), Ok(Value::Str(b"\"".to_vec())));
        assert_eq!(parse(ty, &"x".repeat(80)), Ok(Value::Str(b"x".repeat(80))));
        assert_eq!(
            parse(ty, &"x".repeat(90)).unwrap_err().message(),
            "string of 90 characters exceeds STRING[80]"
        );
        assert!(parse(IecType::String(3), "\"abcd\"").is_err());
        // Control characters are refused, whoever writes: a CR/LF would
        // forge lines for every client the value is printed to.
        let forged = parse(ty, "\"0\r\nDIFF:SETPOINT,99.000000\"").unwrap_err();
        assert_eq!(
            forged.message(),
            "string for STRING[80] contains the control character 0x0D at position 2"
        );
        assert!(parse(ty, "\"a\tb\"").is_err());
        assert!(parse(ty, "\"a\x7Fb\"").is_err());
        // Read from a PLC, they print escaped: nothing ends the line.
        let from_plc = Value::Str(b"0\r\nDIFF:X,1\x07".to_vec());
        assert_eq!(fmt_default(&from_plc, ty), "\"0\\x0D\\x0ADIFF:X,1\\x07\"");
        assert!(parse(ty, "a\0b").is_err());
        // cp1250 passes unchanged and is not case-folded.
        let czech = cp1250::encode("\"Příliš žluťoučký\"");
        let v = Value::parse(ty, &czech, &FormatOptions::default()).unwrap();
        let mut out = Vec::new();
        v.format(ty, &FormatOptions::default(), &mut out);
        assert_eq!(out, czech.as_ref());
    }

    #[test]
    fn string_memory_layout() {
        let ty = IecType::String(5);
        let mut raw = Vec::new();
        Value::Str(b"abc".to_vec()).encode(ty, &mut raw);
        assert_eq!(raw, b"abc\0\0\0");
        assert_eq!(Value::decode(ty, &raw), Value::Str(b"abc".to_vec()));
        assert_eq!(
            Value::decode(ty, b"abcdefgh"),
            Value::Str(b"abcde".to_vec())
        );
        assert_eq!(Value::decode(ty, b"ab"), Value::Str(b"ab".to_vec()));
        let mut raw = Vec::new();
        Value::Str(b"abcdefgh".to_vec()).encode(ty, &mut raw);
        assert_eq!(raw, b"abcde\0");
    }

    #[test]
    fn memory_layout_little_endian() {
        let mut raw = Vec::new();
        Value::Unsigned(0x1234).encode(IecType::Word, &mut raw);
        Value::Signed(-2).encode(IecType::Sint, &mut raw);
        Value::Real(1.0).encode(IecType::Real, &mut raw);
        Value::Bool(true).encode(IecType::Bool, &mut raw);
        Value::Time(1000).encode(IecType::Time, &mut raw);
        assert_eq!(
            raw,
            [0x34, 0x12, 0xFE, 0x00, 0x00, 0x80, 0x3F, 0x01, 0xE8, 0x03, 0x00, 0x00]
        );
        assert_eq!(Value::decode(IecType::Word, &[0x34]), Value::Unsigned(0x34));
        assert_eq!(Value::decode(IecType::Lreal, &[]), Value::LReal(0.0));
        assert_eq!(Value::decode(IecType::Bool, &[4]), Value::Bool(true));
        for ty in [
            IecType::Bool,
            IecType::Lint,
            IecType::String(7),
            IecType::Dt,
        ] {
            let mut raw = Vec::new();
            Value::Str(b"x".to_vec()).encode(ty, &mut raw);
            assert_eq!(raw.len(), ty.size(), "{ty}");
        }
    }

    #[test]
    fn date_and_time() {
        let dt = Value::Date(1_600_000_000.5);
        let bits = 1_600_000_000.5f64.to_bits();
        assert_eq!(fmt_default(&dt, IecType::Dt), bits.to_string());
        assert_eq!(parse(IecType::Dt, &bits.to_string()), Ok(dt.clone()));
        assert!(parse(IecType::Date, "1.5").is_err());
        let decimal = FormatOptions {
            date_time_decimal: true,
            ..FormatOptions::default()
        };
        assert_eq!(fmt(&dt, IecType::Date, &decimal), "1600000000.5000000000");
        assert_eq!(
            Value::parse(IecType::Date, b"1600000000.5", &decimal),
            Ok(dt)
        );
        assert_eq!(
            parse(IecType::Time, "4294967295"),
            Ok(Value::Time(u32::MAX))
        );
        assert!(parse(IecType::Tod, "4294967296").is_err());
        assert!(parse(IecType::Time, "-5").is_err());
    }

    #[test]
    fn delta_parse() {
        assert!(Delta::ZERO.is_zero());
        assert!(delta("0").is_zero());
        assert!(delta("0.0").is_zero());
        assert_eq!(delta("10").floor(), 10);
        assert_eq!(delta("0.5").floor(), 0);
        assert_eq!(delta("0.5").as_f64(), 0.5);
        assert!(!delta("0.5").is_zero());
        assert_eq!(delta("1e3").floor(), 1000);
        assert_eq!(delta("1.5e2").floor(), 150);
        assert_eq!(delta("12345e-2").floor(), 123);
        assert_eq!(delta("+2").floor(), 2);
        assert_eq!(delta("99999999999999999999999").floor(), u64::MAX);
        assert_eq!(delta("9007199254740993").floor(), 9007199254740993);
        assert_eq!(delta("1e300").floor(), u64::MAX);
        assert_eq!(delta("0e300").floor(), 0);
        for text in ["a", "-1", "-0.5", "nan", "inf", "", "1e999", "1 2", "0x5"] {
            assert!(Delta::parse(text.as_bytes()).is_err(), "{text}");
        }
    }

    #[test]
    fn exceeds_integers_exactly() {
        let opts = FormatOptions::default();
        let a = Value::Unsigned(9_007_199_254_740_993);
        let b = Value::Unsigned(9_007_199_254_740_992);
        // In f64 both are 2^53; the comparison must not go through a double.
        assert!(a.exceeds(&b, &Delta::ZERO, IecType::Ulint, &opts));
        assert!(!a.exceeds(&a, &Delta::ZERO, IecType::Ulint, &opts));
        let big = Value::Unsigned(1 << 63);
        let big1 = Value::Unsigned((1 << 63) + 1);
        assert!(big1.exceeds(&big, &Delta::ZERO, IecType::Ulint, &opts));
        assert!(!big1.exceeds(&big, &delta("1"), IecType::Ulint, &opts));
        assert!(big1.exceeds(&big, &delta("0.5"), IecType::Ulint, &opts));
        assert!(Value::Unsigned(u64::MAX).exceeds(
            &Value::Unsigned(0),
            &delta("18446744073709551614"),
            IecType::Ulint,
            &opts
        ));
        assert!(Value::Signed(i64::MAX).exceeds(
            &Value::Signed(i64::MIN),
            &delta("18446744073709551614"),
            IecType::Lint,
            &opts
        ));
        let d = delta("10");
        assert!(!Value::Signed(10).exceeds(&Value::Signed(0), &d, IecType::Int, &opts));
        assert!(Value::Signed(11).exceeds(&Value::Signed(0), &d, IecType::Int, &opts));
        assert!(Value::Signed(-11).exceeds(&Value::Signed(0), &d, IecType::Int, &opts));
        assert!(!Value::Time(100).exceeds(&Value::Time(95), &d, IecType::Time, &opts));
        assert!(Value::Time(100).exceeds(&Value::Time(89), &d, IecType::Tod, &opts));
    }

    #[test]
    fn exceeds_reals_bools_strings() {
        let opts = FormatOptions::default();
        let d = delta("0.5");
        assert!(!Value::Real(1.5).exceeds(&Value::Real(1.0), &d, IecType::Real, &opts));
        assert!(Value::Real(1.6).exceeds(&Value::Real(1.0), &d, IecType::Real, &opts));
        assert!(Value::LReal(1e-12).exceeds(
            &Value::LReal(0.0),
            &Delta::ZERO,
            IecType::Lreal,
            &opts
        ));
        let lim = FormatOptions {
            lim_of_decimals: true,
            num_of_decimals: 2,
            ..opts
        };
        assert!(!Value::LReal(1e-12).exceeds(
            &Value::LReal(0.0),
            &Delta::ZERO,
            IecType::Lreal,
            &lim
        ));
        assert!(Value::LReal(0.006).exceeds(
            &Value::LReal(0.0),
            &Delta::ZERO,
            IecType::Lreal,
            &lim
        ));
        let nan = Value::LReal(f64::NAN);
        assert!(nan.exceeds(&Value::LReal(1.0), &d, IecType::Lreal, &opts));
        assert!(!nan.exceeds(&nan, &d, IecType::Lreal, &opts));
        let inf = Value::LReal(f64::INFINITY);
        assert!(!inf.exceeds(&inf, &d, IecType::Lreal, &opts));
        assert!(inf.exceeds(&Value::LReal(0.0), &d, IecType::Lreal, &opts));
        let big = delta("1000");
        assert!(Value::Bool(true).exceeds(&Value::Bool(false), &big, IecType::Bool, &opts));
        assert!(!Value::Bool(true).exceeds(&Value::Bool(true), &big, IecType::Bool, &opts));
        let ty = IecType::String(10);
        assert!(Value::Str(b"a".to_vec()).exceeds(&Value::Str(b"A".to_vec()), &big, ty, &opts));
        assert!(!Value::Str(b"a".to_vec()).exceeds(&Value::Str(b"a".to_vec()), &big, ty, &opts));
        let day = delta("86400");
        let t0 = Value::Date(1_600_000_000.0);
        assert!(!Value::Date(1_600_086_400.0).exceeds(&t0, &day, IecType::Dt, &opts));
        assert!(Value::Date(1_600_086_400.5).exceeds(&t0, &day, IecType::Dt, &opts));
    }
}
