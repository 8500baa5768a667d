//! The public-file parser on a generated 50,000-variable project (the same
//! layout `loadgen genpub` writes for the load tests).

use std::fmt::Write as _;
use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};

/// A 50,000-line public file: mixed types, packed R-area offsets, CRC line.
fn project(count: usize) -> Vec<u8> {
    let types = [
        "BOOL",
        "INT",
        "DINT",
        "UDINT",
        "REAL",
        "LREAL",
        "WORD",
        "STRING[16]",
    ];
    let sizes = [0usize, 2, 4, 4, 4, 8, 2, 17];
    let mut text = String::with_capacity(count * 48);
    let (mut offset, mut bit) = (0usize, 0u8);
    for i in 0..count {
        let k = i % types.len();
        if k == 0 {
            let _ = writeln!(text, " VAR_{i:05} R B {offset} .{bit} BOOL PUB_INOUT");
            bit += 1;
            if bit == 8 {
                bit = 0;
                offset += 1;
            }
            continue;
        }
        if bit != 0 {
            bit = 0;
            offset += 1;
        }
        let kind = if types[k].contains("REAL") { "F" } else { "B" };
        let _ = writeln!(text, " VAR_{i:05} R {kind} {offset} {} PUB_INOUT", types[k]);
        offset += sizes[k];
    }
    let mut bytes = text.into_bytes();
    let crc = plccoms::pubfile::crc_of(plccoms::pubfile::crc_content(&bytes));
    bytes.extend_from_slice(format!(";* Crc=\"{crc:08X}\"\r\n").as_bytes());
    bytes
}

fn parse(c: &mut Criterion) {
    let bytes = project(50_000);
    let mut group = c.benchmark_group("pubfile");
    group.throughput(Throughput::Bytes(bytes.len() as u64));
    group.sample_size(20);
    group.bench_function("parse_50k_vars", |b| {
        b.iter(|| {
            let file = plccoms::pubfile::parse(black_box(&bytes));
            assert_eq!(file.vars.len(), 50_000);
            black_box(file.warnings.len())
        })
    });
    group.finish();
}

criterion_group!(benches, parse);
criterion_main!(benches);
