//! What every fuzz target does with one input, with the properties it
//! asserts. Shared, unchanged, by the fuzz targets (`fuzz/fuzz_targets/`) and
//! by the stable regression tests (`tests/fuzz_regressions.rs` includes this
//! file with `#[path]`), so a crash input replays through the same code.
//!
//! It must compile in both places: only `plccoms`, `plccoms_protocol`, `bytes`
//! and `std`, and no `crate::` paths.

use std::cell::Cell;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

use bytes::BytesMut;
use plccoms_core::config::BrokerUrl;
use plccoms_core::driver::FileInfo;
use plccoms_core::vars::VarTable;
use plccoms_mqtt::spool::{decode_record, encode_record};
use plccoms_mqtt::topics::{level, unlevel};
use plccoms_plc::epsnet::codec::{decode_packet, encode_packet, EpsnetCodec};
use plccoms_plc::epsnet::frame::{Frame as EpsFrame, MAX_PACKET};
use plccoms_plc::epsnet::service::{answer_frame, decode_answer, PlcTime, Request, Response};
use plccoms_plc::epsnet::PLC_EPS_ADDR;
use plccoms_plc::MemoryMap;
use plccoms_protocol::request::{
    parse_block, parse_getmem, parse_mask_delta, parse_set, parse_setconf, trim,
};
use plccoms_protocol::{
    classify, cp1250, parse_direct, Area, Decoder, Delta, FormatOptions, Frame, IecType, Line,
    Mask, Value,
};
use plcsim::{Device, FileStore};

// ---------------------------------------------------------------------------
// Allocation accounting (for the decoder's memory bound).

/// A global allocator that counts the bytes live on each thread, so a check
/// can see what a piece of code holds on to without seeing other threads.
pub mod alloc_count {
    use std::alloc::{GlobalAlloc, Layout, System};
    use std::cell::Cell;

    pub struct Counting;

    thread_local! {
        static LIVE: Cell<isize> = const { Cell::new(0) };
    }

    fn add(n: isize) {
        // `try_with`: allocations during thread teardown are not counted.
        let _ = LIVE.try_with(|live| live.set(live.get() + n));
    }

    /// Bytes allocated and not yet freed by this thread (frees of memory
    /// another thread allocated count against it).
    pub fn live() -> isize {
        LIVE.try_with(Cell::get).unwrap_or(0)
    }

    unsafe impl GlobalAlloc for Counting {
        unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
            let p = System.alloc(layout);
            if !p.is_null() {
                add(layout.size() as isize);
            }
            p
        }

        unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
            let p = System.alloc_zeroed(layout);
            if !p.is_null() {
                add(layout.size() as isize);
            }
            p
        }

        unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
            System.dealloc(ptr, layout);
            add(-(layout.size() as isize));
        }

        unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
            let p = System.realloc(ptr, layout, new_size);
            if !p.is_null() {
                add(new_size as isize - layout.size() as isize);
            }
            p
        }
    }
}

// ---------------------------------------------------------------------------
// request_line

/// Every type: the fixed ones and strings of the smallest, default and
/// largest capacity.
pub fn all_types() -> impl Iterator<Item = IecType> {
    IecType::FIXED.into_iter().chain([
        IecType::String(1),
        IecType::String(80),
        IecType::String(255),
    ])
}

const OPTIONS: [FormatOptions; 2] = [
    FormatOptions {
        num_of_decimals: 10,
        scient_notation: false,
        date_time_decimal: false,
        lim_of_decimals: false,
    },
    FormatOptions {
        num_of_decimals: 0,
        scient_notation: true,
        date_time_decimal: true,
        lim_of_decimals: true,
    },
];

fn is_exact(ty: IecType) -> bool {
    !matches!(
        ty,
        IecType::Real | IecType::Lreal | IecType::Date | IecType::Dt
    )
}

/// `text` as a value of every type: what parses survives the memory form,
/// prints, and what it prints parses again (to the same value where the type
/// is exact).
fn values(text: &[u8]) {
    for ty in all_types() {
        // `text` as the PLC's memory: whatever a PLC program left there
        // prints on one line (no byte of it ends or forges a line).
        if text.len() >= ty.size() {
            let mut printed = Vec::new();
            Value::decode(ty, &text[..ty.size()]).format(ty, &OPTIONS[0], &mut printed);
            assert!(
                !printed.iter().any(|&b| b == b'\r' || b == b'\n' || b == 0),
                "{ty}: a line end or NUL in a printed value read from memory"
            );
        }
        for opts in &OPTIONS {
            let Ok(v) = Value::parse(ty, text, opts) else {
                continue;
            };
            let mut raw = Vec::new();
            v.encode(ty, &mut raw);
            assert_eq!(raw.len(), ty.size(), "{ty}: encoded size");
            let stored = Value::decode(ty, &raw);
            let mut printed = Vec::new();
            stored.format(ty, opts, &mut printed);
            assert!(!printed.contains(&0), "{ty}: NUL in printed value");
            assert!(
                !printed.iter().any(|&b| b == b'\r' || b == b'\n'),
                "{ty}: a line end in a printed value"
            );
            match Value::parse(ty, &printed, opts) {
                Ok(again) if is_exact(ty) => assert_eq!(again, stored, "{ty}: print/parse"),
                Ok(_) => {}
                Err(e) => panic!(
                    "{ty}: the server's own output {:?} does not parse: {e}",
                    String::from_utf8_lossy(&printed)
                ),
            }
        }
    }
}

fn deltas(text: &[u8]) {
    let Ok(delta) = Delta::parse(text) else {
        return;
    };
    let _ = delta.as_f64();
    let _ = delta.floor();
    let samples = [
        &[0u8; 8][..],
        &[0xff; 8],
        &[0x7f, 0, 0, 0x80, 1, 2, 3, 0xf0],
    ];
    for ty in all_types() {
        for opts in &OPTIONS {
            for (a, b) in samples.iter().zip(samples.iter().cycle().skip(1)) {
                let (a, b) = (Value::decode(ty, a), Value::decode(ty, b));
                let _ = a.exceeds(&b, &delta, ty, opts);
            }
        }
    }
}

/// Reference matcher for short masks: dynamic programming.
fn reference_match(p: &[u8], n: &[u8]) -> bool {
    // m[j]: pattern prefix matches name prefix of length j.
    let mut m = vec![false; n.len() + 1];
    m[0] = true;
    for &c in p {
        if c == b'*' {
            for j in 1..=n.len() {
                m[j] = m[j] || m[j - 1];
            }
        } else {
            for j in (1..=n.len()).rev() {
                m[j] = m[j - 1] && n[j - 1] == c;
            }
            m[0] = false;
        }
    }
    m[n.len()]
}

fn masks(pattern: &[u8]) {
    let mask = Mask::new(pattern);
    let _ = mask.has_wildcard();
    let _ = mask.is_all();
    let upper = cp1250::to_upper(pattern);
    assert!(mask.matches(&upper), "a mask matches its own text");
    let names: [&[u8]; 4] = [
        b"",
        b"TEST_1",
        b"T_ZONES_SET[0].TOPIT_TC",
        b"TEPLOTA_KUCHYN\xCC",
    ];
    for name in names.into_iter().chain([&upper[..upper.len() / 2]]) {
        let got = mask.matches(name);
        if pattern.len() <= 64 {
            let want = mask.pattern().is_empty() || reference_match(mask.pattern(), name);
            assert_eq!(got, want, "mask {:?} on {:?}", mask.pattern(), name);
        }
    }
}

fn direct(text: &[u8]) {
    if let Some(addr) = parse_direct(text) {
        assert!(!matches!(addr.bit, Some(b) if b >= 8));
        assert!(addr.bit.is_none() || addr.ty == IecType::Bool);
        let last = u64::from(addr.offset) + addr.ty.size() as u64 - 1;
        assert!(last <= u64::from(u32::MAX), "{addr:?} ends past 4 GiB");
    }
}

fn is_blank(b: &u8) -> bool {
    *b == b' ' || *b == b'\t'
}

fn trimmed(text: &[u8]) -> bool {
    !text.first().is_some_and(is_blank) && !text.last().is_some_and(is_blank)
}

/// One request line: classification, every argument grammar on its
/// arguments, and what the server then does with the pieces (names as direct
/// addresses and masks, values of every type, deltas).
pub fn request_line(line: &[u8]) {
    let args = match classify(line) {
        Line::Empty => {
            assert!(trim(line).is_empty());
            return;
        }
        Line::Command { args, .. } => args,
        Line::UnknownCommand => trim(line),
        Line::Continuation(text) => text,
    };
    assert!(trimmed(args), "arguments are trimmed");
    if let Ok((name, value)) = parse_set(args) {
        assert!(!name.is_empty() && trimmed(name) && trimmed(value));
        direct(name);
        values(value);
    }
    if let Ok((mask, delta)) = parse_mask_delta(args) {
        masks(mask);
        if let Some(delta) = delta {
            deltas(delta);
        }
    }
    if let Ok((name, _size)) = parse_getmem(args) {
        direct(name);
    }
    if let Ok((key, value)) = parse_setconf(args) {
        assert!(!key.is_empty() && trimmed(key) && trimmed(value));
    }
    if let Ok((name, len, data)) = parse_block(args) {
        assert!(!name.is_empty() && trimmed(name));
        let _ = (len, data);
    }
    direct(args);
    masks(args);
    values(args);
    deltas(args);
}

// ---------------------------------------------------------------------------
// input_decoder

/// Feeds `input` to a decoder in chunks whose sizes `next_chunk` gives,
/// checking after every chunk that the decoder consumed it and holds at most
/// its bound. Returns the frames.
fn decode_in_chunks(
    input: &[u8],
    max_line: usize,
    max_block: usize,
    mut next_chunk: impl FnMut() -> usize,
    mut abandon: impl FnMut() -> bool,
) -> Vec<Frame> {
    let base = alloc_count::live();
    let mut decoder = Decoder::new(max_line, max_block);
    let mut frames: Vec<Frame> = Vec::new();
    let mut rest = input;
    // Lines keep at most twice their limit (Vec growth) and blocks exactly
    // their length; the header of a block is the line it came from.
    let bound = 2 * (2 * max_line).max(8) + max_block + 256;
    while !rest.is_empty() {
        let take = next_chunk().clamp(1, rest.len());
        let mut src = BytesMut::from(&rest[..take]);
        rest = &rest[take..];
        while let Some(frame) = decoder.decode(&mut src) {
            frames.push(frame);
        }
        assert!(src.is_empty(), "decoder left bytes it had scanned");
        drop(src);
        if abandon() {
            decoder.abandon_block();
        }
        let returned: isize = (frames.capacity() * std::mem::size_of::<Frame>()
            + frames
                .iter()
                .map(|f| match f {
                    Frame::Line(v) | Frame::TooLong(v) => v.capacity(),
                    Frame::Block { header, data } => header.capacity() + data.capacity(),
                    Frame::Close => 0,
                })
                .sum::<usize>()) as isize;
        let held = alloc_count::live() - base - returned;
        assert!(
            held <= bound as isize,
            "decoder holds {held} bytes, bound {bound} (max_line {max_line}, max_block {max_block})"
        );
    }
    for frame in &frames {
        match frame {
            Frame::Line(line) => {
                assert!(line.len() <= max_line);
                assert!(!line.iter().any(|&b| b == b'\r' || b == b'\n' || b == 0));
            }
            Frame::Block { header, data } => {
                assert!(header.len() <= max_line && data.len() <= max_block);
                assert!(header.ends_with(b"]="));
            }
            Frame::TooLong(prefix) => assert!(prefix.len() <= 64),
            Frame::Close => {}
        }
    }
    frames
}

/// `data[0]` is the line limit, `data[1]` a third of the block limit,
/// `data[2]` seeds the chunk sizes; the rest is the client's input. The
/// frames must not depend on how the input is split, and the decoder's
/// memory stays within its bound after every chunk.
pub fn input_decoder(data: &[u8]) {
    let [max_line, block, seed, ref input @ ..] = *data else {
        return;
    };
    let (max_line, max_block) = (usize::from(max_line), usize::from(block) * 3);
    let whole = decode_in_chunks(input, max_line, max_block, || usize::MAX, || false);
    // xorshift32, seeded from the input: chunk sizes 1..=32, sometimes large.
    let state = Cell::new(u32::from(seed).wrapping_mul(0x9E37_79B9) | 1);
    let next = || {
        let mut x = state.get();
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        state.set(x);
        x
    };
    let chunk = || match next() % 16 {
        0 => 1 + (next() % 4096) as usize,
        _ => 1 + (next() % 32) as usize,
    };
    let split = decode_in_chunks(input, max_line, max_block, chunk, || false);
    assert_eq!(whole, split, "frames depend on the chunking");
    // Abandoning a block at a read boundary (the server's timeout) keeps the
    // bounds too.
    decode_in_chunks(input, max_line, max_block, chunk, || next() % 8 == 0);
}

// ---------------------------------------------------------------------------
// ini

/// The ini loader on lossily decoded text, as `config::load` does.
pub fn ini(data: &[u8]) {
    let text = String::from_utf8_lossy(data);
    match plccoms_core::config::parse(Path::new("fuzz.ini"), &text) {
        Ok(loaded) => {
            for d in &loaded.diagnostics {
                let _ = d.to_string();
            }
            let _ = format!("{:?}", loaded.config);
        }
        Err(e) => {
            let _ = e.to_string();
        }
    }
}

// ---------------------------------------------------------------------------
// history_time

/// A time of `plccoms history --from/--to`: parsed against two "now"s, and
/// an accepted time written out; relative times are never after now.
pub fn history_time(data: &[u8]) {
    let text = String::from_utf8_lossy(data);
    for now in [0, 1_700_000_000_000, i64::MAX] {
        match plccoms_historian::time::parse(&text, now) {
            Ok(t) => {
                if text.trim_start().starts_with('-') {
                    assert!(t <= now, "{text:?} -> {t} after now {now}");
                }
                let mut out = Vec::new();
                plccoms_historian::time::iso(t, &mut out);
            }
            Err(message) => assert!(!message.is_empty()),
        }
    }
}

/// A packed history block: the first byte chooses whether the rest is the
/// stored form (sealed or a bare zstd frame), or the packed form before
/// compression, stored as a bare frame (file version 2) or sealed with its
/// checksum. Damage is an error; what decodes packs again to the same
/// samples.
pub fn history_block(data: &[u8]) {
    use plccoms_historian::block;
    use plccoms_historian::sample::Stored;
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let stored = match mode % 3 {
        0 => rest.to_vec(),
        1 => zstd::bulk::compress(rest, 1).expect("compress"),
        _ => block::seal(&zstd::bulk::compress(rest, 1).expect("compress")),
    };
    let Ok(rows) = block::decode(&stored) else {
        return;
    };
    assert!(rows.len() <= block::MAX_ROWS);
    let again = block::decode(&block::encode(&rows)).expect("a block packed again decodes");
    assert_eq!(rows.len(), again.len());
    for (a, b) in rows.iter().zip(&again) {
        assert_eq!(
            (a.key, a.quality, a.plc_time),
            (b.key, b.quality, b.plc_time)
        );
        match (&a.value, &b.value) {
            (Stored::Real(x), Stored::Real(y)) => assert_eq!(x.to_bits(), y.to_bits()),
            (x, y) => assert_eq!(x, y),
        }
    }
}

// ---------------------------------------------------------------------------
// pubfile

/// The fixed public file the server ships.
pub const FIXED_PUB: &[u8] = include_bytes!("../../conf/FIXED.pub");

/// A public file, then the variable table a section builds from it with the
/// fixed file, and with it as the fixed file.
pub fn pubfile(data: &[u8]) {
    let parsed = plccoms_plc::pubfile::parse(data);
    let _ = plccoms_plc::pubfile::crc_of(plccoms_plc::pubfile::crc_content(data));
    let lines = data.split(|&b| b == b'\n').count();
    let mut names = HashSet::new();
    assert!(parsed.vars.len() <= plccoms_plc::pubfile::MAX_VARS);
    // What a link keeps of the file instead of its bytes (a refused file's
    // parse stops at the bound).
    if parsed.too_many.is_none() {
        assert_eq!(plccoms_plc::pubfile::crc_trailer(data), parsed.crc);
    }
    for def in &parsed.vars {
        let v = &def.var;
        assert!(!v.name.is_empty());
        assert!(v.name.len() <= plccoms_plc::pubfile::MAX_NAME, "{v:?}");
        assert!(
            def.line >= 1 && def.line <= lines,
            "line {} of {lines}",
            def.line
        );
        assert_eq!(v.codec, plccoms_plc::value_codec::Codec::Native, "{v:?}");
        assert!(v.writable, "{v:?}");
        assert_eq!(v.bit.is_some(), v.ty == IecType::Bool, "{v:?}");
        assert!(!matches!(v.bit, Some(b) if b >= 8));
        assert!(
            names.insert(cp1250::to_upper(&v.name)),
            "duplicate kept: {v:?}"
        );
    }
    for w in &parsed.warnings {
        // A warning quotes the start of a field, never all of it.
        assert!(w.message.len() <= 1024, "{} bytes", w.message.len());
    }

    let map = MemoryMap::FOXTROT;
    let fixed = plccoms_plc::pubfile::parse(FIXED_PUB);
    let mut warnings = Vec::new();
    let built = VarTable::build(
        "FIXED.pub",
        &fixed,
        Some(("fuzz.pub", &parsed)),
        &map,
        &mut warnings,
    );
    if parsed.too_many.is_some() {
        assert!(built.is_err(), "a file past the variable bound is refused");
        return;
    }
    let table = built.expect("the shipped fixed file defines __PLC_RUN and __PF_CRC");
    assert!(table.len() <= fixed.vars.len() + parsed.vars.len());
    // On a name clash the fixed file's variable wins: a name the fixed file
    // defines is a fixed variable.
    let fixed_names: Vec<Vec<u8>> = fixed
        .vars
        .iter()
        .map(|def| plccoms_protocol::cp1250::to_upper(&def.var.name))
        .collect();
    for (id, var) in table.vars().iter().enumerate() {
        assert!(map.contains(var.area, var.offset, var.byte_len()));
        assert_eq!(table.lookup(&var.name), Some(id as u32));
        assert_eq!(
            table.is_fixed(id as u32),
            fixed_names.iter().any(|n| n[..] == var.name[..])
        );
    }
    let mut warnings = Vec::new();
    if let Ok(table) = VarTable::build("fuzz.pub", &parsed, None, &map, &mut warnings) {
        assert_eq!(table.fixed_count(), table.len());
    }
}

// ---------------------------------------------------------------------------
// epsnet_client

/// One request of every kind; `len` for the reads.
fn every_request(len: u16) -> Vec<Request> {
    let info = FileInfo {
        size: 1,
        attributes: 0x20,
        created: 2,
        modified: 3,
    };
    vec![
        Request::Ident,
        Request::Status,
        Request::SetTime(PlcTime {
            year: 2024,
            month: 3,
            day: 15,
            hour: 13,
            minute: 45,
            second: 30,
            weekday: 5,
        }),
        Request::Read {
            area: Area::R,
            offset: 100,
            len,
        },
        Request::Write {
            area: Area::R,
            offset: 100,
            data: vec![1, 2],
        },
        Request::WriteBits {
            area: Area::S,
            offset: 2,
            mask: 4,
            value: 4,
        },
        Request::FileInfo {
            path: b"a.txt".to_vec(),
        },
        Request::FileRead {
            path: b"a.txt".to_vec(),
            offset: 0,
            len,
        },
        Request::FileWrite {
            path: b"a.txt".to_vec(),
            offset: 0,
            last: true,
            data: vec![b'x'],
        },
        Request::FileWriteInfo {
            path: b"a.txt".to_vec(),
            info,
        },
        Request::DirList {
            path: b"/".to_vec(),
            start: 0,
        },
    ]
}

/// The server's side of an answer datagram: `data[0..2]` is the length of
/// the read requests it answers (big-endian), the rest the datagram. Every
/// frame is read as the answer to every kind of request; what decodes must
/// survive re-encoding.
pub fn epsnet_client(data: &[u8]) {
    let [hi, lo, ref datagram @ ..] = *data else {
        return;
    };
    let mut codec = EpsnetCodec;
    let mut src = BytesMut::from(datagram);
    let _ = tokio_util_decode(&mut codec, &mut src);

    let Ok(packet) = decode_packet(datagram) else {
        return;
    };
    assert!(!packet.frames.is_empty());
    let bytes = encode_packet(&packet).expect("a decoded packet re-encodes");
    assert!(bytes.len() <= MAX_PACKET);
    assert_eq!(decode_packet(&bytes).as_ref(), Ok(&packet));

    let requests = every_request(u16::from_be_bytes([hi, lo]));
    for frame in &packet.frames {
        for request in &requests {
            let Ok(answer) = decode_answer(request, frame) else {
                continue;
            };
            let Ok(response) = answer else { continue };
            let (da, sa) = match frame {
                EpsFrame::Data(f) => (f.da, f.sa),
                EpsFrame::Ack => (1, PLC_EPS_ADDR),
            };
            // What the PLC side would send for this response reads back the same.
            let again = answer_frame(da, sa, request.code(), &Ok(response.clone()));
            assert_eq!(
                decode_answer(request, &again),
                Ok(Ok(response)),
                "{request:?}"
            );
        }
    }
}

/// A serial line's bytes: `data[0]` is the size of the chunks they arrive
/// in, the rest the bytes. The decoder never holds more than one frame's
/// worth while waiting, consumes everything by EOF, and every frame it
/// yields re-encodes to bytes that decode to the same frame.
pub fn epsnet_stream(data: &[u8]) {
    use plccoms_plc::epsnet::stream::{self, StreamCodec, StreamItem, MAX_FRAME};
    use tokio_util::codec::Decoder as _;
    let [chunk, ref line @ ..] = *data else {
        return;
    };
    let mut codec = StreamCodec;
    let mut src = BytesMut::new();
    let mut items = Vec::new();
    for piece in line.chunks(usize::from(chunk).max(1)) {
        src.extend_from_slice(piece);
        while let Some(item) = codec
            .decode(&mut src)
            .expect("the stream decoder never fails")
        {
            items.push(item);
        }
        assert!(src.len() <= MAX_FRAME, "{} bytes held", src.len());
    }
    while let Some(item) = codec.decode_eof(&mut src).expect("never fails") {
        items.push(item);
    }
    assert!(src.is_empty());
    for item in items {
        match item {
            StreamItem::Frame(frame) => {
                let bytes = stream::encode(&frame).expect("a decoded frame re-encodes");
                let mut again = BytesMut::from(&bytes[..]);
                assert_eq!(
                    codec.decode(&mut again).expect("never fails"),
                    Some(StreamItem::Frame(frame))
                );
            }
            StreamItem::Skipped { bytes, .. } => assert!(bytes > 0),
        }
    }
}

fn tokio_util_decode(codec: &mut EpsnetCodec, src: &mut BytesMut) -> bool {
    use tokio_util::codec::Decoder as _;
    codec.decode(src).is_ok()
}

// ---------------------------------------------------------------------------
// epsnet_device

/// Separates datagrams in an `epsnet_device` input.
pub const NEXT: &[u8] = b"NEXT";

fn device_root() -> PathBuf {
    std::env::temp_dir().join(format!(
        "plccoms-fuzz-device-{}-{:?}",
        std::process::id(),
        std::thread::current().id()
    ))
}

/// A fresh simulated PLC: the demo map, file services on an empty
/// directory with one file and one subdirectory.
fn fresh_device() -> Device {
    let root = device_root();
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(root.join("d")).expect("create the device's file root");
    std::fs::write(root.join("a.txt"), b"This is test string 1.").expect("seed file");
    std::fs::write(root.join("d").join("b.bin"), [0u8, 1, 2, 0xff]).expect("seed file");
    let mut device = Device::new(MemoryMap::FOXTROT);
    device.files = Some(FileStore::open(&root).expect("open the device's file root"));
    device
}

/// The simulated PLC's side: datagrams separated by [`NEXT`], each handled
/// by one device in turn. An answer, when there is one, is a valid datagram
/// with one frame per request frame, and the server's side accepts every
/// answer frame as the answer to its request.
pub fn epsnet_device(data: &[u8]) {
    let mut device = fresh_device();
    let mut clock_offset = 0.0;
    let mut rest = data;
    loop {
        let (datagram, next) = match rest.windows(NEXT.len()).position(|w| w == NEXT) {
            Some(at) => (&rest[..at], Some(&rest[at + NEXT.len()..])),
            None => (rest, None),
        };
        one_datagram(datagram, &mut device, &mut clock_offset);
        match next {
            Some(next) => rest = next,
            None => break,
        }
    }
    let _ = std::fs::remove_dir_all(device_root());
}

fn one_datagram(datagram: &[u8], device: &mut Device, clock_offset: &mut f64) {
    let answer = plcsim::server::handle_datagram(datagram, device, clock_offset);
    let Ok(request) = decode_packet(datagram) else {
        assert!(answer.is_none(), "answered a datagram that does not decode");
        return;
    };
    let addressed = request
        .frames
        .iter()
        .all(|f| matches!(f, EpsFrame::Data(d) if d.da == PLC_EPS_ADDR));
    if !addressed {
        assert!(answer.is_none(), "answered a datagram not for this PLC");
        return;
    }
    let Some(answer) = answer else {
        return;
    };
    assert!(answer.len() <= MAX_PACKET);
    let packet = decode_packet(&answer).expect("the PLC's answer decodes");
    assert_eq!(packet.mesi, request.mesi);
    assert_eq!(packet.frames.len(), request.frames.len());
    for (asked, answered) in request.frames.iter().zip(&packet.frames) {
        let EpsFrame::Data(asked) = asked else {
            unreachable!("checked above")
        };
        if let EpsFrame::Data(a) = answered {
            assert_eq!(a.da, asked.sa);
            assert_eq!(a.sa, PLC_EPS_ADDR);
        }
        if let Ok(req) = Request::decode(asked.fc, &asked.data) {
            let decoded = decode_answer(&req, answered);
            assert!(
                decoded.is_ok(),
                "the server would refuse the PLC's answer to {req:?}: {decoded:?}"
            );
            if let (Request::Read { len, .. }, Ok(Ok(Response::Data(d)))) = (&req, &decoded) {
                assert_eq!(d.len(), usize::from(*len));
            }
        }
    }
}

/// A files root for `local_path`: a file, a folder, a hidden file, and a
/// link that leads out of the root.
fn files_root() -> &'static Path {
    static ROOT: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    ROOT.get_or_init(|| {
        let base = std::env::temp_dir().join(format!("plccoms-fuzz-files-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&base);
        let root = base.join("root");
        std::fs::create_dir_all(root.join("d")).expect("create the files root");
        std::fs::write(root.join("a.txt"), b"a").expect("seed file");
        std::fs::write(root.join(".hidden"), b"h").expect("seed file");
        std::fs::write(base.join("outside.txt"), b"o").expect("seed file");
        let _ = std::os::unix::fs::symlink(base.join("outside.txt"), root.join("out"));
        std::fs::write(root.join("own.ini"), b"[*]").expect("seed file");
        plccoms_core::localfs::protect(&root.join("own.ini"), true);
        root
    })
}

/// The path rules for local files and for SETCONF:pubfile names: a name a
/// client sends never resolves outside the root, to a hidden name, to the
/// server's own files, or (for writes) to the root itself; a pubfile name
/// that passes has no way up and is not absolute.
pub fn local_path(data: &[u8]) {
    use plccoms_core::localfs::{resolve_for, Access};
    let root = files_root();
    let canonical = std::fs::canonicalize(root).expect("root");
    for access in [Access::Read, Access::Write] {
        if let Ok(path) = resolve_for(root, data, access, &[]) {
            let relative = path.strip_prefix(&canonical).unwrap_or_else(|_| {
                panic!(
                    "{:?} resolved outside the root: {path:?}",
                    String::from_utf8_lossy(data)
                )
            });
            assert!(
                !relative
                    .components()
                    .any(|c| c.as_os_str().to_string_lossy().starts_with('.')),
                "hidden name reached: {path:?}"
            );
            assert!(
                path != canonical.join("own.ini"),
                "own file reached: {path:?}"
            );
            if access == Access::Write {
                assert!(
                    !relative.as_os_str().is_empty(),
                    "the root itself for writing"
                );
            }
        }
    }
    let text = String::from_utf8_lossy(data);
    if plccoms_core::link::tables::check_client_name(&text).is_ok() {
        let rest = text.strip_prefix("//").unwrap_or(&text);
        assert!(!rest.starts_with(['/', '\\']), "absolute: {text:?}");
        assert!(
            !rest.split(['/', '\\']).any(|part| part == ".."),
            "a way up: {text:?}"
        );
    }
}

// ---------------------------------------------------------------------------
// web_query

/// The web page's history query string (`/api/history?...`): parsed or
/// refused with a message, never a panic; a parsed query is usable.
pub fn web_query(data: &[u8]) {
    let text = String::from_utf8_lossy(data);
    match plccoms_web::history::parse_query(&text, 1_800_000_000_000) {
        Ok((query, _format)) => {
            assert!(!query.section.is_empty());
            assert!(query.from_ms <= query.to_ms, "{query:?}");
            assert!(!query.masks.is_empty());
            assert!(query.masks.iter().all(|m| !m.is_empty()), "{query:?}");
        }
        Err(message) => assert!(!message.is_empty()),
    }
}

// ---------------------------------------------------------------------------
// MQTT.

/// Records of the MQTT on-disk queue (`apps/mqtt/src/spool.rs`), one after
/// another: never a panic; every record decoded encodes back to its bytes
/// (records of the format before the sync marker: to the same message).
pub fn mqtt_spool(data: &[u8]) {
    let mut at = 0;
    while at < data.len() {
        match decode_record(&data[at..]) {
            Ok(Some((seq, message, used))) => {
                let mut again = Vec::new();
                encode_record(seq, &message, &mut again);
                if data[at..].starts_with(&again[..4]) {
                    assert_eq!(again, &data[at..at + used], "record {seq} re-encoded");
                }
                let decoded = decode_record(&again).map(|r| r.map(|(s, m, _)| (s, m)));
                assert_eq!(decoded, Ok(Some((seq, message))), "record {seq} re-decoded");
                at += used;
            }
            Ok(None) | Err(_) => break,
        }
    }
}

/// MQTT text: a broker URL (MQTT_URL) and a topic level (a `/set` topic's
/// variable name). Never a panic; a level naming a variable is written back
/// to a level naming the same one.
pub fn mqtt_text(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(url) = BrokerUrl::parse(text) {
        assert!(!url.host.is_empty() && url.port > 0, "{text}: {url:?}");
    }
    // MQTT_URL's list: never empty, bounded, no URL twice, and each one
    // what it parses to alone.
    if let Ok(list) = BrokerUrl::parse_list(text) {
        assert!(
            !list.is_empty() && list.len() <= BrokerUrl::MAX_LIST,
            "{text}"
        );
        for (n, url) in list.iter().enumerate() {
            assert!(!list[..n].contains(url), "{text}: {url:?} twice");
        }
        let again: Vec<String> = list
            .iter()
            .map(|u| {
                let host = match u.host.contains(':') {
                    true => format!("[{}]", u.host),
                    false => u.host.clone(),
                };
                let scheme = if u.tls { "mqtts" } else { "mqtt" };
                format!("{scheme}://{host}:{}", u.port)
            })
            .collect();
        assert_eq!(BrokerUrl::parse_list(&again.join(", ")), Ok(list), "{text}");
    }
    if let Ok(name) = unlevel(text) {
        let again = level(&name);
        assert!(!again.contains(['/', '+', '#']), "{again}");
        assert_eq!(unlevel(&again).as_deref(), Ok(&name[..]), "{text}");
    }
}

// ---------------------------------------------------------------------------
// sparkplug_command

/// An NCMD/DCMD payload from any client of the broker
/// (`sparkplug::command::decode`): never a panic; a decoded command has at
/// most `MAX_METRICS` metrics, and each one's value, for a variable of any
/// type, is either refused or a text `present::protocol_text` takes or
/// names as wrong.
pub fn sparkplug_command(data: &[u8]) {
    use plccoms_mqtt::sparkplug::{command, metric};
    let Ok(payload) = command::decode(data) else {
        return;
    };
    assert!(payload.metrics.len() <= command::MAX_METRICS);
    let _ = command::asks_rebirth(&payload, 2);
    let opts = plccoms_protocol::value::FormatOptions::default();
    for m in &payload.metrics {
        let _ = command::target(m);
        for ty in all_types() {
            if let Ok(text) = metric::command_text(ty, command::value(m)) {
                let _ = plccoms_core::present::protocol_text(ty, text.as_bytes(), &opts);
            }
        }
    }
}

// ---------------------------------------------------------------------------
// user_value

/// A value as a user writes it over MQTT or the web API
/// (`present::protocol_text`), for every type: never a panic; a text
/// accepted for a time type is protocol text that reads back, and what it
/// reads back as, written again, gives the same protocol text.
pub fn user_value(data: &[u8]) {
    use plccoms_core::present::{protocol_text, Presented};
    let opts = plccoms_protocol::value::FormatOptions::default();
    lreal_prints_exactly(data);
    for ty in all_types() {
        let Ok(text) = protocol_text(ty, data, &opts) else {
            continue;
        };
        if !matches!(
            ty,
            IecType::Date | IecType::Dt | IecType::Tod | IecType::Time
        ) {
            continue;
        }
        let shown = Presented::of(ty, &text, &opts);
        assert!(
            !matches!(shown, Presented::Text(_)),
            "{ty}: {:?} -> {:?} does not read back",
            String::from_utf8_lossy(data),
            String::from_utf8_lossy(&text)
        );
        let shown_text = shown.text();
        let again = protocol_text(ty, shown_text.as_bytes(), &opts).expect("its own form");
        assert_eq!(again, text, "{ty}: {shown:?}");
    }
}

/// An LREAL prints as Rust's exact formatting does (which rounds as
/// glibc's printf), and so do its integral part and its nearest 64th:
/// the own path of values with few fractional bits gives the same digits.
fn lreal_prints_exactly(data: &[u8]) {
    let Some((bits, rest)) = data.split_first_chunk::<8>() else {
        return;
    };
    let x = f64::from_le_bytes(*bits);
    if !x.is_finite() {
        return;
    }
    let opts = FormatOptions {
        num_of_decimals: rest.first().map_or(6, |d| d % 41),
        ..FormatOptions::default()
    };
    let decimals = opts.decimals(IecType::Lreal);
    for x in [x, x.trunc(), (x * 64.0).round() / 64.0] {
        let mut out = Vec::new();
        Value::LReal(x).format(IecType::Lreal, &opts, &mut out);
        assert_eq!(out, format!("{x:.decimals$}").into_bytes(), "{x:e}");
    }
}

// ---------------------------------------------------------------------------
// modbus_tags

/// A tag file: every tag lies inside the Modbus layout and is named as a
/// public-file name is; the table builds from them; every tag's codec
/// decodes any bytes, and a value it decoded encodes to bytes that decode
/// to the same value.
pub fn modbus_tags(data: &[u8]) {
    use plccoms_core::vars::VarFile;
    use plccoms_plc::modbus::{tags, MAP};

    let file = tags::parse(data);
    assert!(file.tags.len() <= plccoms_plc::pubfile::MAX_VARS);
    for tag in &file.tags {
        let (area, offset, bit) = tag.place();
        assert!(
            MAP.contains(area, offset, tag.codec.byte_len(tag.ty)),
            "{tag:?}"
        );
        assert!(!tag.name.is_empty());
        assert_eq!(bit.is_some(), tag.ty == IecType::Bool);
        let len = tag.codec.byte_len(tag.ty) as usize;
        for fill in [0u8, 0x41, 0xFF] {
            let value = tag.codec.decode(tag.ty, &vec![fill; len]);
            if tag.ty == IecType::Bool || value_is_nan(&value) {
                continue;
            }
            if let Ok(bytes) = tag.codec.encode(tag.ty, &value) {
                assert_eq!(bytes.len(), len);
                let again = tag.codec.decode(tag.ty, &bytes);
                if !matches!(tag.codec, plccoms_plc::value_codec::Codec::Registers(r) if r.scale.is_some())
                {
                    assert_eq!(again, value, "{tag:?}");
                }
            }
        }
    }
    let table = tag_table(&VarFile::from(&file), &MAP);
    assert_eq!(table.len(), 2 + file.tags.len());
}

/// The table of the standard fixed file and a tag file's variables.
fn tag_table(user: &plccoms_core::vars::VarFile, map: &MemoryMap) -> VarTable {
    let fixed = plccoms_plc::pubfile::parse(
        b" __PLC_RUN S B 2 .2 BOOL PUB_INOUT\r\n __PF_CRC S B 70 DWORD PUB_INOUT\r\n",
    );
    let mut warnings = Vec::new();
    VarTable::build_from(
        "FIXED.pub",
        &plccoms_core::vars::VarFile::from(&fixed),
        Some(("fuzz.csv", user)),
        map,
        &mut warnings,
    )
    .expect("the standard fixed file defines the system variables")
}

fn value_is_nan(value: &Value) -> bool {
    match value {
        Value::Real(x) => x.is_nan(),
        Value::LReal(x) | Value::Date(x) => x.is_nan(),
        _ => false,
    }
}

// ---------------------------------------------------------------------------
// opcua_tags, opcua_node_id

/// An OPC UA tag file (`OPCUA_TAGS`, and the list the backend serves): it
/// parses without panic within the bounds, writes back to a file that
/// parses to the same tags, its variables lie inside the OPC UA map one
/// after another, and the table builds from them.
pub fn opcua_tags(data: &[u8]) {
    use plccoms_core::vars::VarFile;
    use plccoms_plc::opcua::{tags, MAP};

    let file = tags::parse(data);
    assert!(file.tags.len() <= plccoms_plc::pubfile::MAX_VARS);
    // The backend writes UTF-8; a cp1250 file's names may not map back.
    if std::str::from_utf8(data).is_ok() {
        let again = tags::parse(&tags::write(&file.tags));
        assert_eq!(again.tags.len(), file.tags.len(), "{:?}", again.warnings);
        for (a, b) in again.tags.iter().zip(&file.tags) {
            assert_eq!(
                (&a.name, &a.node, a.ty, a.writable, a.index, &a.field),
                (&b.name, &b.node, b.ty, b.writable, b.index, &b.field)
            );
        }
    }
    let vars = tags::vars(&file.tags);
    let mut end = 0;
    for var in &vars {
        assert_eq!(var.offset, end);
        end += var.ty.size() as u32;
        assert!(MAP.contains(var.area, var.offset, var.ty.size() as u32));
    }
    let table = tag_table(&VarFile::from(&file), &MAP);
    assert_eq!(table.len(), 2 + vars.len());
}

/// A node id's text: parsed or refused without panic; what parses prints
/// to a text that parses to the same node id.
pub fn opcua_client_node_id(data: &[u8]) {
    use plccoms_plc::opcua::nodeid;

    let text = String::from_utf8_lossy(data);
    if let Ok(node) = nodeid::parse(&text) {
        let printed = node.to_string();
        assert_eq!(nodeid::parse(&printed).as_ref(), Ok(&node), "{printed}");
    }
    // And as a browse name: the name it makes is one the protocol carries.
    let name = plccoms_plc::opcua::path_name(&[text.as_ref(), "x"]);
    assert!(!name
        .bytes()
        .any(|b| b <= b' ' || matches!(b, b',' | b':' | b'*' | b'"' | b';')));
    assert!(!name.starts_with(['%', '#']));
}

// ---------------------------------------------------------------------------
// opcua_structure

/// A structure definition from the front of `data` (what a server's
/// DataTypeDefinition could say: any built-in id, nesting, shapes), taken
/// off it.
fn structure_of(data: &mut &[u8], depth: usize) -> plccoms_plc::opcua::structure::Structure {
    use plccoms_plc::opcua::structure::{Field, Kind, Shape, Structure};
    use std::sync::Arc;

    fn next(data: &mut &[u8]) -> u8 {
        let (&b, rest) = data.split_first().unwrap_or((&0, &[]));
        *data = rest;
        b
    }
    let n = next(data) % 6;
    let mut fields = Vec::new();
    for i in 0..n {
        let (kind, shape, size) = (next(data), next(data), next(data));
        let kind = if kind >= 23 && depth < 10 {
            Kind::Structure(Arc::new(structure_of(data, depth + 1)))
        } else {
            Kind::Builtin(kind % 25)
        };
        let shape = match shape % 6 {
            0 | 1 => Shape::Scalar,
            2 => Shape::Fixed(vec![u32::from(size % 5)]),
            3 => Shape::Fixed(vec![2, u32::from(size % 4)]),
            4 => Shape::Open(1),
            _ => Shape::Open(2),
        };
        fields.push(Field {
            name: format!("F{i}"),
            kind,
            shape,
        });
    }
    Structure { fields }
}

/// A structure's body walked by its definition (both from `data`): no
/// panic, no hang; the leaves found lie inside the body, in order, one per
/// leaf the definition names; a leaf replaced by its own bytes is the same
/// body.
pub fn opcua_structure(data: &[u8]) {
    use plccoms_plc::opcua::structure::replace;

    let mut rest = data;
    let structure = structure_of(&mut rest, 0);
    let body = rest;
    let Ok(spans) = structure.spans(body) else {
        return;
    };
    let mut end = 0;
    for span in &spans {
        assert!(span.start >= end && span.end >= span.start && span.end <= body.len());
        end = span.end;
    }
    if let Ok(leaves) = structure.leaves() {
        assert_eq!(leaves.len(), spans.len());
    }
    if let Some(span) = spans.first() {
        let same = replace(body, span.clone(), &body[span.clone()]).expect("in the body");
        assert_eq!(same, body);
    }
}

// ---------------------------------------------------------------------------
// modbus_answer

/// The server's side of a Modbus TCP stream: `data[0..2]` is the count the
/// reads asked for, the rest the bytes the device sent. Every ADU is read
/// as the answer to every kind of request; what decodes has the count
/// asked for, and the device's side re-encodes it to the same PDU.
pub fn modbus_answer(data: &[u8]) {
    use plccoms_plc::modbus::codec::{decode_response, encode_response, AduDecoder};
    use plccoms_plc::modbus::frame::Request;
    use tokio_util::codec::Decoder as _;

    let [hi, lo, ref stream @ ..] = *data else {
        return;
    };
    let count = u16::from_be_bytes([hi, lo]).clamp(1, 2000);
    let requests = [
        Request::ReadCoils { address: 0, count },
        Request::ReadDiscreteInputs { address: 1, count },
        Request::ReadHoldingRegisters {
            address: 2,
            count: count.min(125),
        },
        Request::ReadInputRegisters {
            address: 3,
            count: count.min(125),
        },
        Request::WriteSingleCoil {
            address: 4,
            value: true,
        },
        Request::WriteSingleRegister {
            address: 5,
            value: count,
        },
        Request::WriteMultipleCoils {
            address: 6,
            values: vec![true; usize::from(count.min(1968))],
        },
        Request::WriteMultipleRegisters {
            address: 7,
            values: vec![count; usize::from(count.min(123))],
        },
        Request::MaskWriteRegister {
            address: 8,
            and_mask: count,
            or_mask: !count,
        },
    ];
    let mut src = BytesMut::from(stream);
    let mut decoder = AduDecoder;
    while let Ok(Some(adu)) = decoder.decode(&mut src) {
        assert!(adu.pdu.len() <= plccoms_plc::modbus::codec::MAX_PDU);
        for request in &requests {
            let Ok(outcome) = decode_response(request, &adu.pdu) else {
                continue;
            };
            if let Ok(response) = &outcome {
                use plccoms_plc::modbus::frame::Response;
                match (request, response) {
                    (
                        Request::ReadCoils { count, .. }
                        | Request::ReadDiscreteInputs { count, .. },
                        Response::Bits(bits),
                    ) => {
                        assert_eq!(bits.len(), usize::from(*count))
                    }
                    (
                        Request::ReadHoldingRegisters { count, .. }
                        | Request::ReadInputRegisters { count, .. },
                        Response::Registers(r),
                    ) => {
                        assert_eq!(r.len(), usize::from(*count))
                    }
                    (_, Response::Written) => assert!(request.is_write()),
                    other => panic!("answer of the wrong kind: {other:?}"),
                }
            }
            let mut again = Vec::new();
            encode_response(
                adu.header,
                request.function(),
                Some(request),
                &outcome,
                &mut again,
            );
            let reread = decoder
                .decode(&mut BytesMut::from(&again[..]))
                .expect("re-encoded ADU frames")
                .expect("whole");
            assert_eq!(decode_response(request, &reread.pdu), Ok(outcome));
        }
    }
}

// ---------------------------------------------------------------------------
// OPC UA (apps/opcua): what of a client's or a file's text is parsed by
// our code rather than the stack's.

/// A NodeId string against section names: `data` is lines, the last the
/// id, the others (at most 4) the section names. Never a panic; an id read
/// as ours is made again the same by `ids::variable`/`ids::property`.
pub fn opcua_node_id(data: &[u8]) {
    use plccoms_opcua::ids::{self, Ours};
    let text = String::from_utf8_lossy(data);
    let mut lines: Vec<&str> = text.split('\n').collect();
    let id = lines.pop().unwrap_or_default();
    lines.truncate(4);
    let names = lines;
    match ids::parse(id, &names) {
        Ok(Ours::Root) => assert_eq!(id, ids::ROOT),
        Ok(Ours::Section { section }) => assert_eq!(id, names[section]),
        Ok(Ours::SectionProperty { section, property }) => {
            assert_eq!(ids::property(names[section], property), id)
        }
        Ok(Ours::Variable { section, variable }) => {
            assert!(!variable.is_empty());
            assert_eq!(ids::variable(names[section], variable), id)
        }
        Ok(Ours::VariableProperty {
            section,
            variable,
            property,
        }) => assert_eq!(
            ids::property(&ids::variable(names[section], variable), property),
            id
        ),
        Err(e) => assert!(!e.to_string().is_empty()),
    }
}

/// An OPCUA_USERS file: never a panic; an error names its line (within
/// the text); a file read checks a password without panicking.
pub fn opcua_users(data: &[u8]) {
    use plccoms_opcua::users::{Users, MAX_USERS};
    let text = String::from_utf8_lossy(data);
    match Users::parse(&text) {
        Ok(users) => {
            assert!(users.len() <= MAX_USERS);
            // Hashes cost MIN_ITERATIONS at least: check one name only.
            if let Some(name) = text.split_whitespace().next() {
                let _ = users.role(name);
            }
        }
        Err(e) => {
            assert!(e.line >= 1 && e.line <= text.lines().count().max(1), "{e}");
            assert!(!e.problem.is_empty());
        }
    }
}

/// A written value (the Variant a client sends) for each IEC type: never a
/// panic; a text made for SET reads back as a value of the type, and that
/// value is again a Variant.
pub fn opcua_write(data: &[u8]) {
    use plccoms_opcua::convert::{variant, write_text};
    use plccoms_opcua::opcua::types::{DateTime, UAString, Variant};
    use plccoms_protocol::value::{FormatOptions, Value};
    use plccoms_protocol::IecType;
    let mut bytes = [0u8; 8];
    for (i, b) in data.iter().take(8).enumerate() {
        bytes[i] = *b;
    }
    let n = u64::from_le_bytes(bytes);
    let text = String::from_utf8_lossy(data.get(8..).unwrap_or_default()).into_owned();
    let variants = [
        Variant::Boolean(n & 1 == 1),
        Variant::SByte(n as i8),
        Variant::Byte(n as u8),
        Variant::Int16(n as i16),
        Variant::UInt16(n as u16),
        Variant::Int32(n as i32),
        Variant::UInt32(n as u32),
        Variant::Int64(n as i64),
        Variant::UInt64(n),
        Variant::Float(f32::from_bits(n as u32)),
        Variant::Double(f64::from_bits(n)),
        Variant::String(UAString::from(text.as_str())),
        Variant::DateTime(Box::new(DateTime::from(n as i64))),
    ];
    let opts = FormatOptions::default();
    let types = IecType::FIXED
        .iter()
        .copied()
        .chain([IecType::String(40), IecType::String(255)]);
    for ty in types {
        for v in &variants {
            if let Ok(set_text) = write_text(ty, v, &opts) {
                if let Ok(value) = Value::parse(ty, &set_text, &opts) {
                    let _ = variant(ty, &value);
                }
            }
        }
    }
}

/// ADS: an AMS/TCP stream through the codec, each packet's data through
/// every answer decoder, the notification and sum decoders, and the symbol
/// and data type upload and tag file parsers; a decoded packet encodes to
/// its bytes.
pub fn ads_stream(data: &[u8]) {
    use plccoms_plc::ads::command::{
        decode_notification, decode_sum_read, decode_sum_read_write, Request as AdsRequest,
        Response as AdsResponse,
    };
    use plccoms_plc::ads::frame::{AmsCodec, CommandId};
    use plccoms_plc::ads::symbols::{parse_data_types, parse_symbols, Layout};
    use tokio_util::codec::{Decoder as _, Encoder as _};

    let tags = plccoms_plc::ads::tags::parse(data);
    assert!(tags.tags.len() <= plccoms_plc::pubfile::MAX_VARS);
    assert!(tags.warnings.len() <= plccoms_plc::pubfile::MAX_WARNINGS);
    let symbols = parse_symbols(data).unwrap_or_default();
    let types = parse_data_types(data).unwrap_or_default();
    let layout = Layout::expand(&symbols, &types);
    assert!(layout.leaves.len() <= plccoms_plc::pubfile::MAX_VARS);
    let file = plccoms_plc::pubfile::parse(&layout.public_file("fuzz"));
    assert_eq!(file.vars.len(), layout.leaves.len());

    let mut buf = BytesMut::from(data);
    let mut codec = AmsCodec;
    while let Ok(Some(packet)) = codec.decode(&mut buf) {
        for id in 0..=10 {
            let command = CommandId(id);
            let _ = AdsResponse::decode(command, &packet.data);
            if let Ok(request) = AdsRequest::decode(command, &packet.data) {
                assert_eq!(AdsRequest::decode(command, &request.encode()), Ok(request));
            }
        }
        let _ = decode_notification(&packet.data);
        let sizes: Vec<u32> = packet.data.iter().take(8).map(|&b| u32::from(b)).collect();
        let _ = decode_sum_read(&packet.data, &sizes);
        let _ = decode_sum_read_write(&packet.data, sizes.len());
        let mut out = BytesMut::new();
        codec.encode(packet.clone(), &mut out).unwrap();
        assert_eq!(codec.decode(&mut out).unwrap(), Some(packet));
    }
}

/// Modbus RTU framing, both sides, the stream cut in pieces of the first
/// byte's size: every byte is either in a frame (whose CRC is good and whose
/// bytes encode back the same) or skipped with a reason; the buffer never
/// holds more than one frame.
pub fn modbus_rtu(data: &[u8]) {
    use plccoms_plc::modbus::codec::decode_request;
    use plccoms_plc::modbus::rtu::{RtuDecoder, RtuItem, Side, CRC, MAX_FRAME};
    use tokio_util::codec::Decoder as _;

    let [piece, ref stream @ ..] = *data else {
        return;
    };
    let piece = usize::from(piece).max(1);
    for side in [Side::Responses, Side::Requests] {
        let mut decoder = RtuDecoder::new(side);
        let mut src = BytesMut::new();
        let mut accounted = 0;
        let mut items = Vec::new();
        for chunk in stream.chunks(piece) {
            src.extend_from_slice(chunk);
            while let Some(item) = decoder.decode(&mut src).expect("decoding never fails") {
                items.push(item);
            }
            assert!(src.len() < MAX_FRAME + piece, "{} bytes held", src.len());
        }
        items.extend(decoder.abandon_partial(&mut src));
        assert!(src.is_empty());
        for item in items {
            match item {
                RtuItem::Frame(frame) => {
                    let mut wire = vec![frame.unit];
                    wire.extend_from_slice(&frame.pdu);
                    let crc = CRC.checksum(&wire);
                    wire.extend_from_slice(&crc.to_le_bytes());
                    assert_eq!(
                        &stream[accounted..accounted + wire.len()],
                        &wire[..],
                        "a frame is the bytes it came from"
                    );
                    accounted += wire.len();
                    if side == Side::Requests {
                        let _ = decode_request(&frame.pdu);
                    }
                }
                RtuItem::Skipped { bytes, why } => {
                    assert!(bytes > 0);
                    assert!(!why.to_string().is_empty());
                    accounted += bytes;
                }
            }
        }
        assert_eq!(
            accounted,
            stream.len(),
            "every byte is a frame's or skipped"
        );
    }
}
