//! Where a 100,000-variable section's memory goes in the core, counted by
//! a global allocator: the table (variables, names, index), the slots, a
//! poll that changes every variable (how many copies of the slots live at
//! once), a subscription to everything. Bounds per variable keep what was
//! cut from coming back; `cargo test --test memory_per_var --
//! --nocapture` prints the breakdown.
//!
//! Bytes are counted as glibc's malloc spends them (a chunk of the request
//! plus 8, rounded up to 16, at least 32), so a small allocation per
//! variable shows what it really costs.

use std::alloc::{GlobalAlloc, Layout, System};
use std::fmt::Write as _;
use std::sync::atomic::{AtomicIsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use plccoms_core::changes::{PollStamp, Publisher};
use plccoms_core::vars::{VarId, VarTable};
use plccoms_protocol::value::FormatOptions;

struct Counting;

static LIVE: AtomicIsize = AtomicIsize::new(0);

fn chunk(size: usize) -> isize {
    ((size + 8).div_ceil(16) * 16).max(32) as isize
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        LIVE.fetch_add(chunk(layout.size()), Ordering::Relaxed);
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        LIVE.fetch_sub(chunk(layout.size()), Ordering::Relaxed);
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        LIVE.fetch_add(chunk(layout.size()), Ordering::Relaxed);
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        LIVE.fetch_add(chunk(new_size) - chunk(layout.size()), Ordering::Relaxed);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn live() -> isize {
    LIVE.load(Ordering::Relaxed)
}

const VARS: usize = 100_000;

/// The public file `loadgen genpub --vars 100000` writes.
fn public_file() -> Vec<u8> {
    plcsim::genpub::plain(VARS)
}

/// The bytes of variable `id` at poll `n`: every poll changes every value.
fn value(table: &VarTable, id: VarId, n: u64) -> Vec<u8> {
    let var = table.var(id);
    let len = var.byte_len().max(1) as usize;
    if var.ty.is_string() {
        let mut bytes = format!("s{}", n * 7 + u64::from(id)).into_bytes();
        bytes.resize(len, 0);
        return bytes;
    }
    if var.bit.is_some() {
        return vec![if n.is_multiple_of(2) { 0 } else { 0xff }];
    }
    if var.ty == plccoms_protocol::IecType::Real {
        return (n as f32 + id as f32 / 8.0).to_le_bytes().to_vec();
    }
    if var.ty == plccoms_protocol::IecType::Lreal {
        return (n as f64 + id as f64 / 8.0).to_le_bytes().to_vec();
    }
    (n * 3 + u64::from(id % 1000)).to_le_bytes()[..len.min(8)].to_vec()
}

fn per_var(bytes: isize) -> f64 {
    bytes as f64 / VARS as f64
}

fn poll(publisher: &mut Publisher, table: &VarTable, n: u64) {
    let stamp = PollStamp::now();
    for id in 0..table.len() as VarId {
        publisher.update(id, &value(table, id, n), stamp.unix_ms);
    }
}

#[test]
fn a_100000_variable_section_costs_what_its_parts_say() {
    let mut report = String::new();
    let mut line = |what: &str, bytes: isize| {
        let _ = writeln!(report, "{what:<58} {:>8.1} B/var", per_var(bytes));
        per_var(bytes)
    };
    let text = public_file();
    let file_bytes = text.len() as isize;
    line("public file text (read, parsed, then let go)", file_bytes);

    let start = live();
    let parsed = plccoms_plc::pubfile::parse(&text);
    let parse = line("parse of the file (while loading)", live() - start);
    drop(parsed);

    let start = live();
    let table = VarTable::from_public_text("big.pub", &text).expect("table");
    let table_bytes = live() - start;
    // The last few lie past the Foxtrot's R area and are skipped.
    assert!(table.len() > VARS * 99 / 100, "{}", table.len());
    let vars_vec = (table.vars().len() * std::mem::size_of_val(&table.vars()[0])) as isize;
    let names: isize = table.vars().iter().map(|v| chunk(v.name.len())).sum();
    line("table: the variables (Var inline)", vars_vec);
    line("table: their names", names);
    line("table: the name index", table_bytes - vars_vec - names);
    let table_total = line("table in all", table_bytes);
    let table = Arc::new(table);

    let start = live();
    let (publisher, stream) = Publisher::new(
        table.clone(),
        FormatOptions::default(),
        Duration::from_secs(60),
    );
    let mut publisher = publisher.with_diff_block(b"\r\n");
    let empty_slots = line("slots before any value, and interest", live() - start);

    let start = live();
    poll(&mut publisher, &table, 1);
    publisher.publish_poll(PollStamp::now());
    let first = line("first poll: values' text, DIFF block", live() - start);

    // A session holds the latest snapshot while the next poll writes.
    let held = stream.latest();
    let start = live();
    poll(&mut publisher, &table, 2);
    let writing = line("next poll, all changed, before its publish", live() - start);
    publisher.publish_poll(PollStamp::now());
    let both = line("  ... published, the old one still held", live() - start);
    drop(held);
    let after = line("  ... the old snapshot let go", live() - start);

    // The same values read again: what a poll copies when nothing changed
    // (a follower's queue holds that much per such poll).
    let held = stream.latest();
    let start = live();
    poll(&mut publisher, &table, 2);
    let unchanged = line(
        "a poll that changes nothing, before its publish",
        live() - start,
    );
    publisher.publish_poll(PollStamp::now());
    drop(held);

    let start = live();
    let _subscription = stream.subscribe(&["*"]);
    let sub = line("a subscription to every variable", live() - start);

    let at_rest = table_total + empty_slots + first + after;
    line(
        "at rest after polls (table, slots, texts, block)",
        (at_rest * VARS as f64) as isize,
    );
    println!(
        "Var {} B, Slot {} B inline\n{report}",
        std::mem::size_of::<plccoms_core::vars::Var>(),
        std::mem::size_of::<plccoms_core::changes::Slot>()
    );

    // What was cut stays cut (before: table 169, at rest 293, a poll 97,
    // with the old snapshot held 120, a poll that changes nothing 64, a
    // subscription 21).
    assert!(
        table_total <= 125.0,
        "table {table_total:.1} B/var\n{report}"
    );
    assert!(at_rest <= 230.0, "at rest {at_rest:.1} B/var\n{report}");
    assert!(writing <= 70.0, "a poll {writing:.1} B/var\n{report}");
    assert!(both <= 95.0, "{both:.1} B/var\n{report}");
    assert!(unchanged <= 2.0, "{unchanged:.1} B/var\n{report}");
    assert!(sub <= 16.0, "subscription {sub:.1} B/var\n{report}");
    assert!(parse > 0.0);
}
