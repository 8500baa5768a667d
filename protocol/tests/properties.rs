//! Property tests: nothing panics on arbitrary input, values round-trip
//! through their text and memory forms, the decoder does not depend on how
//! the input is split.

use bytes::BytesMut;
use plccoms_protocol::request::{
    parse_block, parse_getmem, parse_mask_delta, parse_set, parse_setconf,
};
use plccoms_protocol::{
    classify, cp1250, parse_direct, write_error, Decoder, Delta, ErrorCode, FormatOptions, Frame,
    IecType, Mask, Value,
};
use proptest::prelude::*;

fn any_type() -> impl Strategy<Value = IecType> {
    prop_oneof![
        proptest::sample::select(&IecType::FIXED[..]),
        (1u16..=255).prop_map(IecType::String),
    ]
}

fn any_opts() -> impl Strategy<Value = FormatOptions> {
    (0u8..=20, any::<bool>(), any::<bool>(), any::<bool>()).prop_map(|(n, sci, dtd, lim)| {
        FormatOptions {
            num_of_decimals: n,
            scient_notation: sci,
            date_time_decimal: dtd,
            lim_of_decimals: lim,
        }
    })
}

/// Bytes biased towards the protocol's own characters and snippets.
fn protocol_bytes() -> impl Strategy<Value = Vec<u8>> {
    const SNIPPETS: [&[u8]; 16] = [
        b"WRITEFILE:a[3]=",
        b"writefileinfo: b[0]=",
        b"WRITEFILE:c[25]=",
        b"GET:x",
        b"SET:s,\"v\"",
        b"EN:t* 0.5",
        b"\r\n",
        b"\r\0",
        b"\n",
        b"\x04",
        b"\xff\xfb\x18",
        b"\xff\xfa\x18\x00",
        b"\xff\xf0",
        b"\xff\xff",
        b"%RW10",
        b"1e3",
    ];
    let piece = prop_oneof![
        any::<u8>().prop_map(|b| vec![b]),
        proptest::sample::select(
            &b" \t\r\n\0\x04\xff\xfa\xf0\xfb:,.*[]=\"%0123456789eE+-WRITEFILEGETSXRBWL"[..]
        )
        .prop_map(|b| vec![b]),
        proptest::sample::select(&SNIPPETS[..]).prop_map(|s| s.to_vec()),
    ];
    proptest::collection::vec(piece, 0..60).prop_map(|pieces| pieces.concat())
}

fn format(v: &Value, ty: IecType, opts: &FormatOptions) -> Vec<u8> {
    let mut out = Vec::new();
    v.format(ty, opts, &mut out);
    out
}

/// Reference matcher: plain recursion, fine for short inputs.
fn naive_match(p: &[u8], n: &[u8]) -> bool {
    match p.split_first() {
        None => n.is_empty(),
        Some((b'*', rest)) => (0..=n.len()).any(|i| naive_match(rest, &n[i..])),
        Some((&c, rest)) => n.first() == Some(&c) && naive_match(rest, &n[1..]),
    }
}

fn decode_in_chunks(input: &[u8], cuts: &[usize], max_line: usize, max_block: usize) -> Vec<Frame> {
    let mut decoder = Decoder::new(max_line, max_block);
    let mut src = BytesMut::new();
    let mut frames = Vec::new();
    let mut start = 0;
    let mut ends: Vec<usize> = cuts.iter().map(|c| c % (input.len() + 1)).collect();
    ends.sort_unstable();
    ends.push(input.len());
    for end in ends {
        src.extend_from_slice(&input[start..end.max(start)]);
        start = end.max(start);
        while let Some(frame) = decoder.decode(&mut src) {
            frames.push(frame);
        }
        assert!(src.is_empty(), "decoder left bytes it had scanned");
    }
    frames
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn parsers_never_panic(bytes in protocol_bytes()) {
        let _ = classify(&bytes);
        let _ = parse_set(&bytes);
        let _ = parse_mask_delta(&bytes);
        let _ = parse_getmem(&bytes);
        let _ = parse_setconf(&bytes);
        let _ = parse_block(&bytes);
        let _ = parse_direct(&bytes);
        let _ = Delta::parse(&bytes);
        let mask = Mask::new(&bytes);
        let _ = mask.matches(&cp1250::to_upper(&bytes));
        let mut out = Vec::new();
        write_error(&mut out, ErrorCode::BadRequest, &bytes);
        prop_assert!(!out.iter().any(|&b| b == b'\r' || b == b'\n' || b == 0));
    }

    #[test]
    fn values_never_panic(bytes in protocol_bytes(), ty in any_type(), opts in any_opts()) {
        if let Ok(v) = Value::parse(ty, &bytes, &opts) {
            let mut raw = Vec::new();
            v.encode(ty, &mut raw);
            prop_assert_eq!(raw.len(), ty.size());
            let text = format(&v, ty, &opts);
            prop_assert!(!text.contains(&0));
            let _ = v.exceeds(&Value::decode(ty, &raw), &Delta::ZERO, ty, &opts);
        }
        let v = Value::decode(ty, &bytes);
        let text = format(&v, ty, &opts);
        prop_assert!(!text.contains(&0));
        if let Ok(delta) = Delta::parse(&bytes) {
            let _ = v.exceeds(&Value::decode(ty, &[]), &delta, ty, &opts);
        }
    }

    #[test]
    fn decoder_never_panics_and_ignores_chunking(
        input in protocol_bytes(),
        cuts in proptest::collection::vec(any::<usize>(), 0..10),
        max_line in 0usize..40,
        max_block in 0usize..40,
    ) {
        let whole = decode_in_chunks(&input, &[], max_line, max_block);
        let split = decode_in_chunks(&input, &cuts, max_line, max_block);
        prop_assert_eq!(&whole, &split);
        for frame in &whole {
            match frame {
                Frame::Line(line) => {
                    prop_assert!(line.len() <= max_line);
                    prop_assert!(!line.iter().any(|&b| b == b'\r' || b == b'\n' || b == 0));
                }
                Frame::Block { header, data } => {
                    prop_assert!(header.len() <= max_line && data.len() <= max_block);
                }
                Frame::TooLong(prefix) => prop_assert!(prefix.len() <= 64),
                Frame::Close => {}
            }
        }
    }

    #[test]
    fn mask_agrees_with_reference(
        pattern in proptest::collection::vec(proptest::sample::select(&b"ab*"[..]), 0..8),
        name in proptest::collection::vec(proptest::sample::select(&b"AB"[..]), 0..10),
    ) {
        let mask = Mask::new(&pattern);
        let expected = pattern.is_empty() || naive_match(mask.pattern(), &name);
        prop_assert_eq!(mask.matches(&name), expected);
    }

    #[test]
    fn integers_round_trip(raw in any::<[u8; 8]>(), opts in any_opts()) {
        // Every fixed type but the floating-point ones.
        for ty in IecType::FIXED.into_iter().filter(|ty| {
            !matches!(ty, IecType::Real | IecType::Lreal | IecType::Date | IecType::Dt)
        }) {
            let v = Value::decode(ty, &raw);
            let text = format(&v, ty, &opts);
            prop_assert_eq!(Value::parse(ty, &text, &opts), Ok(v.clone()), "{}", ty);
            let mut back = Vec::new();
            v.encode(ty, &mut back);
            prop_assert_eq!(Value::decode(ty, &back), v);
            if ty != IecType::Bool {
                prop_assert_eq!(&back[..], &raw[..ty.size()]);
            }
        }
    }

    #[test]
    fn dates_round_trip(bits in any::<u64>(), opts in any_opts()) {
        for ty in [IecType::Date, IecType::Dt] {
            let v = Value::Date(f64::from_bits(bits));
            let plain = FormatOptions { date_time_decimal: false, ..opts };
            let text = format(&v, ty, &plain);
            prop_assert_eq!(text.clone(), bits.to_string().into_bytes());
            match Value::parse(ty, &text, &plain) {
                Ok(Value::Date(f)) => prop_assert_eq!(f.to_bits(), bits),
                other => prop_assert!(false, "{:?}", other),
            }
        }
    }

    #[test]
    fn strings_round_trip(
        bytes in proptest::collection::vec(1u8..=255, 0..=80),
        cap in 80u16..=255,
        opts in any_opts(),
    ) {
        let ty = IecType::String(cap);
        let v = Value::Str(bytes.clone());
        let text = format(&v, ty, &opts);
        // No byte of a printed value ends a line.
        prop_assert!(!text.contains(&b'\r') && !text.contains(&b'\n'));
        let control = bytes.iter().any(|&b| b < 0x20 || b == 0x7F);
        if control {
            // Printed escaped; a SET of such a string is refused.
            prop_assert!(Value::parse(ty, &text[1..text.len() - 1], &opts)
                .map_or(true, |parsed| parsed != v));
            let raw_set = [&b"\""[..], &bytes, b"\""].concat();
            prop_assert!(Value::parse(ty, &raw_set, &opts).is_err());
        } else {
            prop_assert_eq!(Value::parse(ty, &text, &opts), Ok(v.clone()));
        }
        let mut raw = Vec::new();
        v.encode(ty, &mut raw);
        prop_assert_eq!(raw.len(), usize::from(cap) + 1);
        prop_assert_eq!(Value::decode(ty, &raw), v);
    }

    #[test]
    fn reals_round_trip(x in any::<f32>(), y in any::<f64>(), sci in any::<bool>()) {
        prop_assume!(x.is_finite() && y.is_finite());
        let opts = FormatOptions { num_of_decimals: 15, scient_notation: sci, ..Default::default() };

        let text = format(&Value::Real(x), IecType::Real, &opts);
        let Ok(Value::Real(px)) = Value::parse(IecType::Real, &text, &opts) else {
            return Err(TestCaseError::fail(format!("REAL {x} -> {}", cp1250::decode(&text))));
        };
        // 6 decimals (fixed) or 7 significant digits (scientific), then f32 rounding.
        let tol = if sci { x.abs() * 1e-6 + f32::MIN_POSITIVE } else { 1e-6 + x.abs() * 2e-7 };
        prop_assert!((px - x).abs() <= tol, "REAL {} -> {} -> {}", x, cp1250::decode(&text), px);

        let text = format(&Value::LReal(y), IecType::Lreal, &opts);
        let Ok(Value::LReal(py)) = Value::parse(IecType::Lreal, &text, &opts) else {
            return Err(TestCaseError::fail(format!("LREAL {y} -> {}", cp1250::decode(&text))));
        };
        let tol = if sci { y.abs() * 1e-15 + f64::MIN_POSITIVE } else { 1e-15 + y.abs() * 5e-16 };
        prop_assert!((py - y).abs() <= tol, "LREAL {} -> {} -> {}", y, cp1250::decode(&text), py);

        // Memory form is exact.
        let mut raw = Vec::new();
        Value::Real(x).encode(IecType::Real, &mut raw);
        Value::LReal(y).encode(IecType::Lreal, &mut raw);
        prop_assert_eq!(Value::decode(IecType::Real, &raw[..4]), Value::Real(x));
        prop_assert_eq!(Value::decode(IecType::Lreal, &raw[4..]), Value::LReal(y));
    }

    #[test]
    fn integer_delta_is_exact(a in any::<u64>(), b in any::<u64>(), d in any::<u64>()) {
        let opts = FormatOptions::default();
        let delta = Delta::parse(d.to_string().as_bytes()).unwrap();
        let exceeds = Value::Unsigned(a).exceeds(&Value::Unsigned(b), &delta, IecType::Ulint, &opts);
        prop_assert_eq!(exceeds, a.abs_diff(b) > d);
        let half = Delta::parse(format!("{d}.5").as_bytes()).unwrap();
        let exceeds = Value::Unsigned(a).exceeds(&Value::Unsigned(b), &half, IecType::Ulint, &opts);
        prop_assert_eq!(exceeds, a.abs_diff(b) > d);
        let (sa, sb) = (a as i64, b as i64);
        let exceeds = Value::Signed(sa).exceeds(&Value::Signed(sb), &delta, IecType::Lint, &opts);
        prop_assert_eq!(exceeds, u128::from(sa.abs_diff(sb)) > u128::from(d));
    }
}
