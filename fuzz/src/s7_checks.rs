//! The S7 fuzz targets' checks (`fuzz/fuzz_targets/s7_*.rs`), shared with
//! the stable property test `tests/s7_fuzz.rs` (which includes this file
//! with `#[path]`). Only `plccoms_plc`, `plccoms_protocol`, `bytes` and
//! `std`; no `crate::` paths.

use bytes::BytesMut;
use plccoms_plc::s7::codec::{decode_all, TpktCodec, MAX_TPKT};
use plccoms_plc::s7::frame::{Answer, Job, Tpdu};
use plccoms_plc::s7::{tags, MAP};
use plccoms_protocol::{IecType, Value};
use tokio_util::codec::Encoder;

/// Any bytes as a stream from an S7 server (or client): framing never
/// panics, a frame decoded encodes to a frame of at most [`MAX_TPKT`], and
/// answers and jobs parsed encode and parse back to themselves.
pub fn s7_stream(data: &[u8]) {
    let Ok(tpdus) = decode_all(data) else {
        return;
    };
    for tpdu in tpdus {
        let mut out = BytesMut::new();
        if TpktCodec.encode(tpdu.clone(), &mut out).is_ok() {
            assert!(out.len() <= MAX_TPKT);
        }
        let Tpdu::Data(pdu) = tpdu else { continue };
        if let Ok((n, answer)) = Answer::parse(&pdu) {
            let mut again = BytesMut::new();
            answer.encode(n, &mut again);
            // Refused items lose their transport size, a short read item
            // its bit length: compare what was parsed, not the bytes.
            if let Ok((m, back)) = Answer::parse(&again) {
                assert_eq!(m, n);
                if !matches!(answer, Answer::Szl(Err(_)) | Answer::Refused(_)) {
                    assert_eq!(back, answer);
                }
            }
        }
        if let Ok((n, job)) = Job::parse(&pdu) {
            let mut again = BytesMut::new();
            job.encode(n, &mut again);
            if let Ok((m, back)) = Job::parse(&again) {
                assert_eq!((m, back), (n, job));
            }
        }
    }
}

/// Any bytes as an S7 tag file: every tag inside the layout, its bytes
/// decoded and encoded back to as many bytes, and the same value again.
pub fn s7_tags(data: &[u8]) {
    let file = tags::parse(data);
    assert!(file.tags.len() <= plccoms_plc::pubfile::MAX_VARS);
    for tag in &file.tags {
        let var = tag.var();
        assert!(
            MAP.contains(var.area, var.offset, var.byte_len()),
            "{tag:?}"
        );
        assert!(!tag.name.is_empty());
        assert_eq!(var.bit.is_some(), var.ty == IecType::Bool);
        if var.ty == IecType::Bool {
            continue;
        }
        let len = var.byte_len() as usize;
        for fill in [0u8, 0x09, 0x41, 0xFF] {
            let value = var.decode(&vec![fill; len]);
            if matches!(value, Value::Real(x) if x.is_nan())
                || matches!(value, Value::LReal(x) if x.is_nan())
            {
                continue;
            }
            if let Ok(plccoms_plc::WriteData::Bytes(bytes)) = var.encode(&value) {
                assert_eq!(bytes.len(), len, "{tag:?}");
                assert_eq!(var.decode(&bytes), value, "{tag:?}");
            }
        }
    }
}
