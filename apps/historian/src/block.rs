//! Packed samples: a run of consecutive samples of a day file (by key: by
//! time, then variable) stored as one row of the `blocks` table, column by
//! column and zstd-compressed. A sample then takes a few bytes instead of
//! the 12 of a row plus its value (an 8-byte double, or the text).
//!
//! Encoding 1, before compression (varint: unsigned LEB128; zigzag: signed
//! mapped to unsigned, 0, -1, 1, -2 -> 0, 1, 2, 3). Samples are grouped by
//! variable (runs), each run in time order, so that a variable's successive
//! values and times sit side by side:
//!
//! ```text
//! u8       encoding (1)
//! varint   first_ms: the time of the block's first sample
//! varint   samples, runs
//! runs     varint (var id - previous run's var id), varint samples in the run
//! times    per sample: the first of a run varint(ms - first_ms of the block),
//!          the next zigzag(delta - previous delta): a steady rate is all zeros
//! kinds    per sample one byte: 0 NULL (a NaN real), 1 integer, 2 real, 3 text
//! integers zigzag(value - the run's previous integer), wrapping
//! reals    bits XOR the run's previous real's bits, as 8 byte planes (all
//!          most significant bytes, then the next ...)
//! texts    varint length, UTF-8 bytes
//! quality  per sample one byte: 0 good, 1 stale, 2 link_lost
//! stamps   varint count, then per stamp varint(sample index - previous
//!          index), zigzag(plc_time - time)
//! ```
//!
//! Times are ms since the day's start (`meta.day_start_ms`), as in the
//! sample keys.
//!
//! Stored, the block is sealed with a checksum, so a damaged block (a bad
//! sector, a bad copy: SQLite's `integrity_check` sees nothing of it) is
//! an error, never wrong values:
//!
//! ```text
//! u8       2: sealed
//! u32 LE   CRC-32 (ISO-HDLC, as zlib's crc32) of the zstd frame
//! ...      the zstd frame of the bytes above
//! ```
//!
//! Blocks written before (file version 2) are the bare zstd frame (it
//! begins with the zstd magic `28 B5 2F FD`); they are read as they are,
//! without a check.

use std::io::Read;

use super::sample::Stored;
use crate::key::{DAY_MS, VAR_BITS, VAR_MASK};

/// Samples per block at most: a block decodes to a few MB at most.
pub const MAX_ROWS: usize = 1 << 16;
/// The decoded bytes a block may have (`MAX_ROWS` of the longest texts a
/// PLC string can hold would not fit, so texts are bounded by it too).
const MAX_DECODED: u64 = 64 << 20;
const ENCODING: u8 = 1;
const ZSTD_LEVEL: i32 = 3;
/// The first byte of a sealed block, and its header's length.
const SEALED: u8 = 2;
const SEAL_LEN: usize = 5;
const ZSTD_MAGIC: [u8; 4] = [0x28, 0xB5, 0x2F, 0xFD];
const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// One sample as a day file holds it.
#[derive(Debug, Clone, PartialEq)]
pub struct Packed {
    /// `(ms since the day's start) << VAR_BITS | var id`.
    pub key: i64,
    pub value: Stored,
    /// 0 good, 1 stale, 2 link_lost.
    pub quality: u8,
    pub plc_time: Option<i64>,
}

/// What is damaged in a block; `len` 0: found before decoding.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("a packed block is damaged: {what}{}", if *len > 0 { format!(" (at byte {at} of its {len} decoded bytes)") } else { String::new() })]
pub struct BlockError {
    pub what: String,
    pub at: usize,
    pub len: usize,
}

/// Packs samples given in key order (keys unique); at most [`MAX_ROWS`].
pub fn encode(rows: &[Packed]) -> Vec<u8> {
    debug_assert!(rows.len() <= MAX_ROWS);
    debug_assert!(rows.windows(2).all(|w| w[0].key < w[1].key));
    let first_ms = rows.first().map_or(0, |r| r.key >> VAR_BITS);
    // Grouped by variable, each group in time order (a stable sort keeps
    // the key order inside a variable).
    let mut order: Vec<usize> = (0..rows.len()).collect();
    order.sort_by_key(|&i| rows[i].key & VAR_MASK);

    let mut out = Vec::with_capacity(rows.len() * 12 + 16);
    out.push(ENCODING);
    varint(&mut out, first_ms as u64);
    varint(&mut out, rows.len() as u64);
    let mut runs: Vec<(i64, usize)> = Vec::new();
    for &i in &order {
        let var = rows[i].key & VAR_MASK;
        match runs.last_mut() {
            Some((v, n)) if *v == var => *n += 1,
            _ => runs.push((var, 1)),
        }
    }
    varint(&mut out, runs.len() as u64);
    let mut previous_var = 0;
    for &(var, n) in &runs {
        varint(&mut out, (var - previous_var) as u64);
        varint(&mut out, n as u64);
        previous_var = var;
    }
    let mut ints = Vec::new();
    let mut reals: Vec<u64> = Vec::new();
    let mut texts = Vec::new();
    let mut kinds = Vec::with_capacity(rows.len());
    let mut qualities = Vec::with_capacity(rows.len());
    let mut stamps = Vec::new();
    let mut stamp_count = 0u64;
    let mut last_stamp = 0usize;
    let mut at = 0;
    for &(_, n) in &runs {
        let (mut previous_ms, mut previous_delta) = (0i64, 0i64);
        let (mut previous_int, mut previous_bits) = (0i64, 0u64);
        for (j, &i) in order[at..at + n].iter().enumerate() {
            let row = &rows[i];
            let ms = row.key >> VAR_BITS;
            if j == 0 {
                varint(&mut out, (ms - first_ms) as u64);
            } else {
                let delta = ms - previous_ms;
                zigzag(&mut out, delta.wrapping_sub(previous_delta));
                previous_delta = delta;
            }
            previous_ms = ms;
            match &row.value {
                Stored::Null => kinds.push(0),
                Stored::Int(v) => {
                    kinds.push(1);
                    zigzag(&mut ints, v.wrapping_sub(previous_int));
                    previous_int = *v;
                }
                Stored::Real(f) => {
                    kinds.push(2);
                    reals.push(f.to_bits() ^ previous_bits);
                    previous_bits = f.to_bits();
                }
                Stored::Text(s) => {
                    kinds.push(3);
                    varint(&mut texts, s.len() as u64);
                    texts.extend_from_slice(s.as_bytes());
                }
            }
            qualities.push(row.quality);
            if let Some(plc) = row.plc_time {
                let index = at + j;
                varint(&mut stamps, (index - last_stamp) as u64);
                zigzag(&mut stamps, plc.wrapping_sub(row.key >> VAR_BITS));
                last_stamp = index;
                stamp_count += 1;
            }
        }
        at += n;
    }
    out.extend_from_slice(&kinds);
    out.extend_from_slice(&ints);
    for plane in (0..8).rev() {
        out.extend(reals.iter().map(|bits| (bits >> (plane * 8)) as u8));
    }
    out.extend_from_slice(&texts);
    out.extend_from_slice(&qualities);
    varint(&mut out, stamp_count);
    out.extend_from_slice(&stamps);
    seal(&zstd::bulk::compress(&out, ZSTD_LEVEL).expect("zstd compresses any input into a Vec"))
}

/// A zstd frame as stored: with its checksum.
pub fn seal(frame: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(SEAL_LEN + frame.len());
    out.push(SEALED);
    out.extend_from_slice(&CRC32.checksum(frame).to_le_bytes());
    out.extend_from_slice(frame);
    out
}

/// The zstd frame of a stored block: checked when sealed, as it is when
/// written before blocks were sealed.
fn unseal(data: &[u8]) -> Result<&[u8], BlockError> {
    let damaged = |what: String| BlockError {
        what,
        at: 0,
        len: 0,
    };
    match data.first() {
        Some(&SEALED) if data.len() >= SEAL_LEN => {
            let frame = &data[SEAL_LEN..];
            let stored = u32::from_le_bytes(data[1..SEAL_LEN].try_into().expect("4 bytes"));
            let actual = CRC32.checksum(frame);
            if stored != actual {
                return Err(damaged(format!(
                    "checksum {actual:08x} of its {} bytes, not {stored:08x}",
                    frame.len()
                )));
            }
            Ok(frame)
        }
        _ if data.starts_with(&ZSTD_MAGIC) => Ok(data),
        _ => Err(damaged(format!(
            "neither sealed nor a zstd frame ({} bytes)",
            data.len()
        ))),
    }
}

/// Unpacks a block, in key order. Damaged data is an error, never a panic,
/// and never decodes to more than [`MAX_ROWS`] samples.
pub fn decode(data: &[u8]) -> Result<Vec<Packed>, BlockError> {
    let frame = unseal(data)?;
    let mut raw = Vec::new();
    let read = zstd::stream::read::Decoder::new(frame)
        .and_then(|d| d.take(MAX_DECODED + 1).read_to_end(&mut raw));
    if let Err(e) = read {
        return Err(BlockError {
            what: format!("not zstd data ({e})"),
            at: 0,
            len: raw.len(),
        });
    }
    if raw.len() as u64 > MAX_DECODED {
        return Err(BlockError {
            what: format!("over {MAX_DECODED} bytes"),
            at: 0,
            len: raw.len(),
        });
    }
    Reader { data: &raw, at: 0 }.block()
}

struct Reader<'a> {
    data: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn error(&self, what: impl Into<String>) -> BlockError {
        BlockError {
            what: what.into(),
            at: self.at,
            len: self.data.len(),
        }
    }

    fn byte(&mut self, what: &str) -> Result<u8, BlockError> {
        let b = *self
            .data
            .get(self.at)
            .ok_or_else(|| self.error(format!("ends inside {what}")))?;
        self.at += 1;
        Ok(b)
    }

    fn bytes(&mut self, n: usize, what: &str) -> Result<&[u8], BlockError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&end| end <= self.data.len())
            .ok_or_else(|| self.error(format!("ends inside {what}")))?;
        let slice = &self.data[self.at..end];
        self.at = end;
        Ok(slice)
    }

    fn varint(&mut self, what: &str) -> Result<u64, BlockError> {
        let mut value = 0u64;
        for shift in (0..64).step_by(7) {
            let b = self.byte(what)?;
            value |= u64::from(b & 0x7f) << shift;
            if b & 0x80 == 0 {
                return Ok(value);
            }
        }
        Err(self.error(format!("{what}: a number longer than 64 bits")))
    }

    fn zigzag(&mut self, what: &str) -> Result<i64, BlockError> {
        let u = self.varint(what)?;
        Ok((u >> 1) as i64 ^ -((u & 1) as i64))
    }

    /// A count no larger than `max`.
    fn count(&mut self, max: usize, what: &str) -> Result<usize, BlockError> {
        let n = self.varint(what)?;
        if n > max as u64 {
            return Err(self.error(format!("{what} {n} over {max}")));
        }
        Ok(n as usize)
    }

    fn block(mut self) -> Result<Vec<Packed>, BlockError> {
        let encoding = self.byte("the encoding")?;
        if encoding != ENCODING {
            return Err(self.error(format!("encoding {encoding}, not {ENCODING}")));
        }
        let first_ms = self.count(DAY_MS as usize, "the first time")? as i64;
        let n = self.count(MAX_ROWS, "samples")?;
        let run_count = self.count(n, "runs")?;
        let mut runs = Vec::with_capacity(run_count);
        let (mut var, mut total) = (0i64, 0usize);
        for k in 0..run_count {
            let step = self.varint("a run's variable")?;
            if k > 0 && step == 0 {
                return Err(self.error("two runs of one variable"));
            }
            var = var
                .checked_add_unsigned(step)
                .filter(|v| *v <= VAR_MASK)
                .ok_or_else(|| self.error("a variable id over 32,767"))?;
            let len = self.count(n - total, "a run's samples")?;
            if len == 0 {
                return Err(self.error("an empty run"));
            }
            total += len;
            runs.push((var, len));
        }
        if total != n {
            return Err(self.error(format!("runs of {total} samples for {n}")));
        }
        // Times in run order; keys once the whole block is read.
        let mut rows: Vec<Packed> = Vec::with_capacity(n);
        for &(_, len) in &runs {
            let (mut ms, mut delta) = (0i64, 0i64);
            for j in 0..len {
                if j == 0 {
                    let offset = self.count(DAY_MS as usize, "a time")?;
                    ms = first_ms + offset as i64;
                } else {
                    delta = delta.wrapping_add(self.zigzag("a time")?);
                    ms = ms.wrapping_add(delta);
                }
                rows.push(Packed {
                    key: ms,
                    value: Stored::Null,
                    quality: 0,
                    plc_time: None,
                });
            }
        }
        let kinds = self.bytes(n, "the kinds")?.to_vec();
        // (sample, run) of each real, decoded after the integers.
        let mut reals = Vec::new();
        let mut i = 0;
        for (run, &(_, len)) in runs.iter().enumerate() {
            let mut previous_int = 0i64;
            for _ in 0..len {
                rows[i].value = match kinds[i] {
                    0 => Stored::Null,
                    1 => {
                        previous_int = previous_int.wrapping_add(self.zigzag("an integer")?);
                        Stored::Int(previous_int)
                    }
                    2 => {
                        reals.push((i, run));
                        Stored::Real(0.0)
                    }
                    3 => Stored::Text(String::new()),
                    other => return Err(self.error(format!("value kind {other}"))),
                };
                i += 1;
            }
        }
        let count = reals.len();
        let planes = self.bytes(count * 8, "the reals")?;
        let (mut current_run, mut bits) = (usize::MAX, 0u64);
        for (k, &(i, run)) in reals.iter().enumerate() {
            let xor = (0..8).fold(0u64, |acc, plane| {
                (acc << 8) | u64::from(planes[plane * count + k])
            });
            if run != current_run {
                (current_run, bits) = (run, 0);
            }
            bits ^= xor;
            rows[i].value = Stored::Real(f64::from_bits(bits));
        }
        for (i, &kind) in kinds.iter().enumerate() {
            if kind == 3 {
                let len = self.count(MAX_DECODED as usize, "a text's length")?;
                let text = String::from_utf8(self.bytes(len, "a text")?.to_vec())
                    .map_err(|_| self.error("a text that is not UTF-8"))?;
                rows[i].value = Stored::Text(text);
            }
        }
        let qualities = self.bytes(n, "the qualities")?.to_vec();
        for (row, q) in rows.iter_mut().zip(qualities) {
            if q > 2 {
                return Err(self.error(format!("quality {q}")));
            }
            row.quality = q;
        }
        let stamps = self.count(n, "stamps")?;
        let mut index = 0usize;
        for k in 0..stamps {
            let step = self.count(n, "a stamp's sample")?;
            index += step;
            if (k > 0 && step == 0) || index >= n {
                return Err(self.error("a stamp of no sample"));
            }
            let offset = self.zigzag("a stamp")?;
            rows[index].plc_time = Some(rows[index].key.wrapping_add(offset));
        }
        if self.at != self.data.len() {
            return Err(self.error("bytes after the end"));
        }
        // Times to keys, then key order.
        let mut k = 0;
        for &(var, len) in &runs {
            for row in &mut rows[k..k + len] {
                if !(0..DAY_MS).contains(&row.key) {
                    return Err(self.error(format!("a time {} ms into the day", row.key)));
                }
                row.key = (row.key << VAR_BITS) | var;
            }
            k += len;
        }
        rows.sort_unstable_by_key(|r| r.key);
        if rows.windows(2).any(|w| w[0].key == w[1].key) {
            return Err(self.error("two samples of a variable at one time"));
        }
        Ok(rows)
    }
}

fn varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push(v as u8 | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn zigzag(out: &mut Vec<u8>, v: i64) {
    varint(out, ((v << 1) ^ (v >> 63)) as u64);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(ms: i64, var: i64, value: Stored) -> Packed {
        Packed {
            key: (ms << VAR_BITS) | var,
            value,
            quality: 0,
            plc_time: None,
        }
    }

    #[test]
    fn every_kind_round_trips_exactly() {
        let mut rows = Vec::new();
        for cycle in 0..200i64 {
            let ms = 1000 + cycle * 100 + (cycle % 7);
            rows.push(row(ms, 0, Stored::Int(cycle % 2)));
            rows.push(row(ms, 1, Stored::Int(i64::MIN + cycle)));
            rows.push(row(ms, 3, Stored::Real((cycle as f64 * 0.01).sin())));
            if cycle % 3 == 0 {
                rows.push(row(ms, 4, Stored::Text(format!("count {cycle} žluťoučký"))));
            }
            if cycle % 50 == 0 {
                rows.push(row(ms, 5, Stored::Null));
                rows.push(row(ms, 6, Stored::Real(f64::NEG_INFINITY)));
            }
        }
        rows[7].quality = 2;
        rows[8].quality = 1;
        rows[9].plc_time = Some(-5);
        rows[400].plc_time = Some(DAY_MS * 3);
        let packed = encode(&rows);
        let back = decode(&packed).unwrap();
        assert_eq!(back.len(), rows.len());
        for (a, b) in rows.iter().zip(&back) {
            assert_eq!(a.key, b.key);
            assert_eq!(a.quality, b.quality);
            assert_eq!(a.plc_time, b.plc_time);
            match (&a.value, &b.value) {
                (Stored::Real(x), Stored::Real(y)) => assert_eq!(x.to_bits(), y.to_bits()),
                (x, y) => assert_eq!(x, y),
            }
        }
    }

    #[test]
    fn an_empty_block_and_one_sample() {
        assert_eq!(decode(&encode(&[])).unwrap(), vec![]);
        let one = vec![row(DAY_MS - 1, VAR_MASK, Stored::Real(-0.0))];
        assert_eq!(decode(&encode(&one)).unwrap(), one);
    }

    /// The layout of the module's documentation, byte by byte (the fuzz
    /// seed of `fuzz/seed.sh`).
    #[test]
    fn the_documented_layout() {
        let raw: &[u8] = &[
            1, 0x64, 3, 2, 0, 2, 5, 1, // encoding, first_ms 100, 3 samples, runs (0: 2, 5: 1)
            0, 0xC8, 0x01, 0, // times: 100, 100 + 100, 100
            1, 2, 3, 14, // kinds; the integer 7
            0x3F, 0xF8, 0, 0, 0, 0, 0, 0, // 1.5 by planes
            2, b'a', b'b', 0, 2, 0, // the text; qualities
            1, 0, 9, // one stamp: sample 0, 5 ms before
        ];
        let rows = decode(&zstd::bulk::compress(raw, 1).unwrap()).unwrap();
        let mut expected = vec![
            row(100, 0, Stored::Int(7)),
            row(100, 5, Stored::Text("ab".into())),
            row(200, 0, Stored::Real(1.5)),
        ];
        expected[0].plc_time = Some(95);
        expected[2].quality = 2;
        assert_eq!(rows, expected);
    }

    #[test]
    fn damage_is_named() {
        assert!(decode(b"not zstd").unwrap_err().what.contains("zstd"));
        let raw = |bytes: &[u8]| zstd::bulk::compress(bytes, 1).unwrap();
        assert!(decode(&raw(&[2])).unwrap_err().what.contains("encoding 2"));
        // A million samples claimed.
        let err = decode(&raw(&[1, 0, 0x80, 0x80, 0x40])).unwrap_err();
        assert!(err.what.contains("over 65536"), "{err}");
        // One sample, one run, then nothing.
        let err = decode(&raw(&[1, 0, 1, 1, 0, 1])).unwrap_err();
        assert!(err.what.contains("ends inside a time"), "{err}");
        let sealed = encode(&[row(5, 1, Stored::Int(3))]);
        let mut good = zstd::bulk::decompress(&sealed[SEAL_LEN..], 1 << 10).unwrap();
        good.push(0);
        assert!(decode(&raw(&good))
            .unwrap_err()
            .what
            .contains("after the end"));
    }

    /// A flipped bit anywhere in a sealed block is an error; a block of
    /// file version 2 (the bare zstd frame) is read without a check.
    #[test]
    fn a_sealed_block_is_checked_and_an_unsealed_one_still_read() {
        let rows: Vec<Packed> = (0..300i64)
            .map(|i| row(i * 10, i % 3, Stored::Real(i as f64 / 7.0)))
            .collect();
        let sealed = encode(&rows);
        assert_eq!(sealed[0], SEALED);
        for at in [1, 4, SEAL_LEN, sealed.len() / 2, sealed.len() - 1] {
            let mut damaged = sealed.clone();
            damaged[at] ^= 0x01;
            let err = decode(&damaged).unwrap_err();
            assert!(err.what.contains("checksum"), "byte {at}: {err}");
        }
        assert!(decode(&sealed[..3]).is_err());
        assert_eq!(decode(&sealed[SEAL_LEN..]).unwrap(), rows);
        assert_eq!(decode(&seal(&sealed[SEAL_LEN..])).unwrap(), rows);
    }

    #[test]
    fn a_steady_real_takes_a_few_bytes() {
        let rows: Vec<Packed> = (0..MAX_ROWS as i64)
            .map(|i| {
                let (cycle, var) = (i / 100, i % 100);
                row(
                    cycle * 100,
                    var,
                    Stored::Real(
                        ((cycle as f64 * 0.01 + var as f64 * 0.5).sin() * 100.0) as f32 as f64,
                    ),
                )
            })
            .collect();
        let bytes = encode(&rows).len() as f64 / rows.len() as f64;
        assert!(bytes < 6.0, "{bytes} bytes per REAL sample");
    }
}
