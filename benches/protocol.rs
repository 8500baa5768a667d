//! Protocol crate hot paths: request classification and argument parsing,
//! value formatting per type, and wildcard mask matching.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use plccoms_protocol::request::{classify, parse_mask_delta, parse_set};
use plccoms_protocol::{FormatOptions, IecType, Mask, Value};

fn parse(c: &mut Criterion) {
    let mut group = c.benchmark_group("parse");
    let lines: [(&str, &[u8]); 5] = [
        ("classify_get", b"GET:T_ZONES_SET[0].TOPIT_TC"),
        ("classify_set", b"SET:TEPLOTA_TERIK,21.5"),
        ("classify_en_delta", b"EN:TEPLOTA* 0.5"),
        ("classify_continuation", b"  RO01_01  "),
        ("classify_unknown", b"FOO:bar"),
    ];
    for (name, line) in lines {
        group.bench_function(name, |b| b.iter(|| classify(black_box(line))));
    }
    group.bench_function("parse_set_args", |b| {
        b.iter(|| parse_set(black_box(b"TEXT , \"a, b: c\"")))
    });
    group.bench_function("parse_mask_delta_args", |b| {
        b.iter(|| parse_mask_delta(black_box(b"TEPLOTA* 0.25")))
    });
    group.finish();
}

fn format(c: &mut Criterion) {
    let mut group = c.benchmark_group("format");
    let opts = FormatOptions::default();
    let sci = FormatOptions {
        scient_notation: true,
        ..FormatOptions::default()
    };
    let cases: [(&str, IecType, Value, &FormatOptions); 8] = [
        ("real", IecType::Real, Value::Real(21.537), &opts),
        // Integral reals (0, counters, setpoints) are common in PLC data.
        ("real_integral", IecType::Real, Value::Real(1234.0), &opts),
        ("lreal_zero", IecType::Lreal, Value::LReal(0.0), &opts),
        ("real_sci", IecType::Real, Value::Real(-0.000_123_4), &sci),
        (
            "lreal",
            IecType::Lreal,
            Value::LReal(std::f64::consts::PI * 1e6),
            &opts,
        ),
        ("int", IecType::Int, Value::Signed(-12_345), &opts),
        (
            "udint",
            IecType::Udint,
            Value::Unsigned(4_000_000_000),
            &opts,
        ),
        (
            "string",
            IecType::String(80),
            Value::Str(b"Have a nice day, \"quoted\"".to_vec()),
            &opts,
        ),
    ];
    let mut out = Vec::with_capacity(128);
    for (name, ty, value, opts) in cases {
        group.bench_function(name, |b| {
            b.iter(|| {
                out.clear();
                black_box(&value).format(ty, opts, &mut out);
                black_box(out.len())
            })
        });
    }
    // Decode + format, as the fan-out does per changed variable.
    let raw = 21.5_f32.to_le_bytes();
    group.bench_function("real_decode_format", |b| {
        b.iter(|| {
            out.clear();
            Value::decode(IecType::Real, black_box(&raw)).format(IecType::Real, &opts, &mut out);
            black_box(out.len())
        })
    });
    group.finish();
}

fn masks(c: &mut Criterion) {
    let mut group = c.benchmark_group("mask");
    let names: Vec<Vec<u8>> = (0..10_000)
        .map(|i| format!("ZONE{:02}.ROOM{:03}.TEMP_{i}", i % 37, i % 211).into_bytes())
        .collect();
    group.throughput(Throughput::Elements(names.len() as u64));
    let masks = [
        ("all", Mask::new(b"*")),
        ("exact", Mask::new(b"zone05.room100.temp_5000")),
        ("prefix", Mask::new(b"ZONE1*")),
        ("infix", Mask::new(b"*ROOM1*TEMP*")),
        ("backtrack", Mask::new(b"*O*O*E*9")),
    ];
    for (name, mask) in masks {
        group.bench_function(format!("{name}_10k_names"), |b| {
            b.iter(|| names.iter().filter(|n| mask.matches(n)).count())
        });
    }
    group.finish();
}

criterion_group!(benches, parse, format, masks);
criterion_main!(benches);
