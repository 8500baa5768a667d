//! Property tests for the file parsers: the INI loader and the public-file
//! parser (with the variable table built from it). Arbitrary bytes never
//! panic; generated valid files load to exactly what was written.
//! (EPSNET frames have theirs in `epsnet_codec.rs`, the line protocol in
//! `protocol/tests/properties.rs`.)

use std::collections::HashSet;
use std::net::Ipv4Addr;
use std::path::Path;

use plccoms_core::config;
use plccoms_core::vars::VarTable;
use plccoms_plc::pubfile;
use plccoms_plc::value_codec::Codec;
use plccoms_plc::var::{Var, VarDef};
use plccoms_plc::MemoryMap;
use plccoms_protocol::{cp1250, Area, IecType};
use proptest::prelude::*;

const FIXED_PUB: &[u8] = include_bytes!("../conf/FIXED.pub");

// ---------------------------------------------------------------------------
// INI

/// Keys of both kinds of section, so generated text hits the real paths.
fn keys() -> Vec<&'static str> {
    config::global_keys()
        .chain(config::section_keys())
        .collect()
}

/// Ini-shaped text: section headers, known and unknown keys with values of
/// every kind, comments, quotes, stray bytes.
fn ini_like() -> impl Strategy<Value = String> {
    let value = prop_oneof![
        Just(String::new()),
        any::<u32>().prop_map(|n| n.to_string()),
        (0u64..70_000).prop_map(|n| n.to_string()),
        Just("-1".to_string()),
        Just("99999999999999999999999".to_string()),
        proptest::sample::select(&["Yes", "No", "yes", "NO", "1", "0", "maybe"][..])
            .prop_map(str::to_string),
        any::<[u8; 4]>().prop_map(|b| Ipv4Addr::from(b).to_string()),
        Just("192.168.1.300".to_string()),
        Just("\"quoted # not a comment\"".to_string()),
        Just("\"unterminated".to_string()),
        proptest::sample::select(&["demo", "idle", "DEMO", "other"][..]).prop_map(str::to_string),
        "[ -~]{0,12}",
        ".{0,6}",
    ];
    let line = prop_oneof![
        Just("[*]".to_string()),
        "[A-Za-z0-9_ *]{0,8}".prop_map(|name| format!("[{name}]")),
        Just("[unclosed".to_string()),
        (
            proptest::sample::select(keys()),
            "[ \t]{0,2}",
            value.clone(),
            "( *[#;].{0,8})?"
        )
            .prop_map(|(k, sp, v, c)| format!("{k}{sp}={sp}{v}{c}")),
        ("[A-Za-z_]{1,8}", value).prop_map(|(k, v)| format!("{k} = {v}")),
        "[#;].{0,10}",
        Just(String::new()),
        ".{0,12}",
    ];
    (
        proptest::collection::vec(line, 0..30),
        prop_oneof![Just("\n"), Just("\r\n"), Just("\r")],
        any::<bool>(),
    )
        .prop_map(|(lines, end, bom)| {
            let text = lines.join(end);
            if bom {
                format!("\u{feff}{text}")
            } else {
                text
            }
        })
}

/// One generated PLC section: what is written and what must load.
#[derive(Debug, Clone)]
struct GenSection {
    name: String,
    port: u16,
    ip: Option<Ipv4Addr>,
    epsaddr: Option<u8>,
    pubfile: Option<String>,
    crc: Option<bool>,
}

fn gen_sections() -> impl Strategy<Value = Vec<GenSection>> {
    proptest::collection::vec(
        (
            "[A-Za-z][A-Za-z0-9_]{0,10}",
            any::<Option<[u8; 4]>>(),
            proptest::option::of(1u8..=126),
            proptest::option::of("[A-Za-z0-9_]{1,8}\\.pub"),
            any::<Option<bool>>(),
        ),
        1..6,
    )
    .prop_map(|raw| {
        let mut names = HashSet::new();
        raw.into_iter()
            .filter(|(name, ..)| names.insert(name.to_ascii_uppercase()))
            .enumerate()
            .map(|(i, (name, ip, epsaddr, pubfile, crc))| GenSection {
                name,
                port: 20_000 + i as u16,
                ip: ip.map(Ipv4Addr::from),
                epsaddr,
                pubfile,
                crc,
            })
            .collect()
    })
}

fn yes_no(b: bool) -> &'static str {
    if b {
        "Yes"
    } else {
        "No"
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn ini_arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        let text = String::from_utf8_lossy(&bytes);
        let _ = config::parse(Path::new("prop.ini"), &text);
    }

    #[test]
    fn ini_like_text_never_panics(text in ini_like()) {
        if let Ok(loaded) = config::parse(Path::new("prop.ini"), &text) {
            // Every section that loaded has the one required key.
            for section in &loaded.config.sections {
                prop_assert!(section.server_port >= 1);
            }
            for d in &loaded.diagnostics {
                let _ = d.to_string();
            }
        }
    }

    #[test]
    fn generated_ini_loads_as_written(
        sections in gen_sections(),
        num_of_decimals in 0u8..=15,
        net_connect_max in 1usize..=1024,
        crlf in any::<bool>(),
        sci in any::<bool>(),
        pad in "[ \t]{0,3}",
        line_end in prop_oneof![Just("\n"), Just("\r\n")],
    ) {
        let mut text = String::from("# generated\n[*]\n");
        text.push_str(&format!("NUM_OF_DECIMALS{pad}={pad}{num_of_decimals}\n"));
        text.push_str(&format!("NET_CONNECT_MAX = {net_connect_max} # comment\n"));
        text.push_str(&format!("END_LINE_CRLF = {}\n", yes_no(crlf)));
        text.push_str(&format!("SCIENT_NOTATION = {}\n\n", yes_no(sci)));
        for s in &sections {
            text.push_str(&format!("[{}]\n", s.name));
            if let Some(ip) = s.ip {
                text.push_str(&format!("IPADDR = {ip}\n"));
            }
            if let Some(a) = s.epsaddr {
                text.push_str(&format!("EPSADDR={a}\n"));
            }
            if let Some(p) = &s.pubfile {
                text.push_str(&format!("PUBFILE{pad}={pad}\"{p}\"\n"));
            }
            if let Some(c) = s.crc {
                text.push_str(&format!("PUBFILE_CRC = {}\n", yes_no(c)));
            }
            text.push_str(&format!("SERVER_PORT = {}\n", s.port));
        }
        let text = text.replace('\n', line_end);
        let loaded = match config::parse(Path::new("prop.ini"), &text) {
            Ok(loaded) => loaded,
            Err(e) => return Err(TestCaseError::fail(format!("{e}\n{text}"))),
        };
        let g = &loaded.config.global;
        prop_assert_eq!(g.num_of_decimals, num_of_decimals);
        prop_assert_eq!(g.net_connect_max, net_connect_max);
        prop_assert_eq!(g.end_line_crlf, crlf);
        prop_assert_eq!(g.scient_notation, sci);
        prop_assert_eq!(loaded.config.sections.len(), sections.len(), "{}", text);
        for (got, want) in loaded.config.sections.iter().zip(&sections) {
            prop_assert_eq!(&got.name, &want.name);
            prop_assert_eq!(got.server_port, want.port);
            prop_assert_eq!(got.ipaddr, want.ip);
            prop_assert_eq!(got.epsaddr, want.epsaddr);
            prop_assert_eq!(&got.pubfile, &want.pubfile);
            prop_assert_eq!(got.pubfile_crc, want.crc.unwrap_or(false));
        }
    }
}

// ---------------------------------------------------------------------------
// Public files

fn any_type() -> impl Strategy<Value = IecType> {
    prop_oneof![
        4 => proptest::sample::select(&IecType::FIXED[..]),
        1 => (1u16..=255).prop_map(IecType::String),
    ]
}

fn any_area() -> impl Strategy<Value = Area> {
    proptest::sample::select(&Area::ALL[..])
}

/// Names as PLC programs write them: letters, digits, `_`, `.`, `[`, `]`,
/// and cp1250 letters.
fn any_name() -> impl Strategy<Value = Vec<u8>> {
    let first = proptest::sample::select(
        &b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz_\xC8\xE8\xCC\xEC\x8A\x9A"[..],
    );
    let rest = proptest::sample::select(
        &b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_.[]\xC8\xE8\xCC\xEC\xDD\xFD"[..],
    );
    (first, proptest::collection::vec(rest, 0..24)).prop_map(|(f, mut r)| {
        r.insert(0, f);
        r
    })
}

/// A generated variable and how its line is written.
#[derive(Debug, Clone)]
struct GenVar {
    name: Vec<u8>,
    area: Area,
    offset: u32,
    bit: Option<u8>,
    ty: IecType,
    kind_f: bool,
    glue_bit: bool,
    flag: Option<&'static str>,
    sep: &'static str,
    comment: bool,
}

fn gen_var() -> impl Strategy<Value = GenVar> {
    (
        any_name(),
        any_area(),
        any::<u32>(),
        proptest::option::of(0u8..8),
        any_type(),
        any::<[bool; 3]>(),
        proptest::option::of(proptest::sample::select(
            &["PUB_IN", "PUB_OUT", "PUB_INOUT", "pub_inout"][..],
        )),
        proptest::sample::select(&[" ", "\t", "  ", " \t "][..]),
    )
        .prop_map(
            |(name, area, offset, bit, ty, [kind_f, glue_bit, comment], flag, sep)| {
                // Offsets inside the area (the table skips the others), so the
                // variable table must hold every one of them too.
                let size = MemoryMap::FOXTROT.size(area) - ty.size() as u32;
                GenVar {
                    name,
                    area,
                    offset: offset % (size + 1),
                    bit: if ty == IecType::Bool { bit } else { None },
                    ty,
                    kind_f,
                    glue_bit,
                    flag,
                    sep,
                    comment,
                }
            },
        )
}

fn write_line(v: &GenVar, out: &mut Vec<u8>) {
    let sep = v.sep.as_bytes();
    out.extend_from_slice(sep);
    out.extend_from_slice(&v.name);
    for field in [
        v.area.letter().to_string(),
        (if v.kind_f { "F" } else { "B" }).to_string(),
    ] {
        out.extend_from_slice(sep);
        out.extend_from_slice(field.as_bytes());
    }
    out.extend_from_slice(sep);
    out.extend_from_slice(v.offset.to_string().as_bytes());
    if let Some(bit) = v.bit {
        if !v.glue_bit {
            out.extend_from_slice(sep);
        }
        out.extend_from_slice(format!(".{bit}").as_bytes());
    }
    out.extend_from_slice(sep);
    out.extend_from_slice(v.ty.to_string().as_bytes());
    if let Some(flag) = v.flag {
        out.extend_from_slice(sep);
        out.extend_from_slice(flag.as_bytes());
    }
    if v.comment {
        out.extend_from_slice(b" ; note: x R B 0 INT");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn pubfile_arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..800)) {
        let parsed = pubfile::parse(&bytes);
        let _ = pubfile::crc_of(pubfile::crc_content(&bytes));
        let fixed = pubfile::parse(FIXED_PUB);
        let mut warnings = Vec::new();
        let table = VarTable::build("FIXED.pub", &fixed, Some(("prop.pub", &parsed)), &MemoryMap::FOXTROT, &mut warnings);
        prop_assert!(table.is_ok());
        let _ = VarTable::build("prop.pub", &parsed, None, &MemoryMap::FOXTROT, &mut warnings);
    }

    #[test]
    fn pubfile_like_lines_never_panic(
        lines in proptest::collection::vec(
            prop_oneof![
                gen_var().prop_map(|v| { let mut out = Vec::new(); write_line(&v, &mut out); out }),
                "[ -~]{0,30}".prop_map(String::into_bytes),
                proptest::collection::vec(
                    proptest::sample::select(&b" \t.;*\"[]0123456789RSXYBFL_PUBINTSTRG\r\xff"[..]),
                    0..30,
                ),
            ],
            0..20,
        ),
    ) {
        let bytes = lines.join(&b"\n"[..]);
        let parsed = pubfile::parse(&bytes);
        for def in &parsed.vars {
            prop_assert_eq!(def.var.bit.is_some(), def.var.ty == IecType::Bool);
        }
    }

    /// A valid generated public file loads to exactly its variables, in
    /// order, and the variable table holds each at its address and type.
    #[test]
    fn generated_pubfile_round_trips(
        raw in proptest::collection::vec(gen_var(), 0..40),
        crlf in any::<bool>(),
        with_crc in any::<bool>(),
    ) {
        // Names are unique case-insensitively (a duplicate is skipped).
        let mut seen = HashSet::new();
        let vars: Vec<GenVar> = raw
            .into_iter()
            .filter(|v| seen.insert(cp1250::to_upper(&v.name)))
            .filter(|v| !matches!(&cp1250::to_upper(&v.name)[..], b"__PLC_RUN" | b"__PF_CRC"))
            .collect();
        let end: &[u8] = if crlf { b"\r\n" } else { b"\n" };
        let mut bytes = b"; generated public file".to_vec();
        bytes.extend_from_slice(end);
        for v in &vars {
            write_line(v, &mut bytes);
            bytes.extend_from_slice(end);
        }
        let crc = pubfile::crc_of(&bytes);
        if with_crc {
            bytes.extend_from_slice(format!(";* Crc=\"{crc:08X}\"").as_bytes());
            bytes.extend_from_slice(end);
        }

        let parsed = pubfile::parse(&bytes);
        prop_assert!(parsed.warnings.is_empty(), "{:?}", parsed.warnings);
        prop_assert_eq!(parsed.crc, with_crc.then_some(crc));
        prop_assert_eq!(pubfile::crc_of(pubfile::crc_content(&bytes)), crc);
        let expected: Vec<VarDef> = vars
            .iter()
            .enumerate()
            .map(|(i, v)| VarDef {
                var: Var {
                    name: v.name.clone().into_boxed_slice(),
                    area: v.area,
                    offset: v.offset,
                    bit: if v.ty == IecType::Bool { Some(v.bit.unwrap_or(0)) } else { None },
                    ty: v.ty,
                    codec: Codec::Native,
                    writable: true,
                    info: None,
                },
                line: i + 2,
            })
            .collect();
        prop_assert_eq!(&parsed.vars, &expected);

        let fixed = pubfile::parse(FIXED_PUB);
        let mut warnings = Vec::new();
        let table = VarTable::build(
            "FIXED.pub",
            &fixed,
            Some(("gen.pub", &parsed)),
            &MemoryMap::FOXTROT,
            &mut warnings,
        )
        .unwrap();
        prop_assert!(warnings.is_empty(), "{:?}", warnings);
        prop_assert_eq!(table.len(), fixed.vars.len() + vars.len());
        for want in expected.iter().map(|def| &def.var) {
            let id = table.lookup(&want.name);
            prop_assert!(id.is_some(), "{:?} missing", want.name);
            let id = id.unwrap();
            let var = table.var(id);
            prop_assert_eq!(&var.name[..], &cp1250::to_upper(&want.name)[..]);
            prop_assert_eq!(var.area, want.area);
            prop_assert_eq!(var.offset, want.offset);
            prop_assert_eq!(var.bit, want.bit);
            prop_assert_eq!(var.ty, want.ty);
            prop_assert!(!table.is_fixed(id));
        }
    }
}
