//! The public-file parser on a generated 50,000-variable project (the same
//! layout `loadgen genpub` writes for the load tests).

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};

/// A project of `count` mixed-type variables packed in the R area, with
/// a CRC line.
fn project(count: usize) -> Vec<u8> {
    plcsim::genpub::generate(&plcsim::genpub::Layout {
        vars: count,
        animated: 0,
        setvars: 0,
    })
}

fn parse(c: &mut Criterion) {
    let bytes = project(50_000);
    let mut group = c.benchmark_group("pubfile");
    group.throughput(Throughput::Bytes(bytes.len() as u64));
    group.sample_size(20);
    group.bench_function("parse_50k_vars", |b| {
        b.iter(|| {
            let file = plccoms_plc::pubfile::parse(black_box(&bytes));
            assert_eq!(file.vars.len(), 50_000);
            black_box(file.warnings.len())
        })
    });
    group.finish();
}

criterion_group!(benches, parse);
criterion_main!(benches);
