//! The S7 fuzz targets' checks (`fuzz/src/s7_checks.rs`) on the stable
//! toolchain: ordinary inputs, and generated ones (valid frames cut and
//! flipped; tag files built from the address and type grammar).

#[path = "../fuzz/src/s7_checks.rs"]
mod s7_checks;

use bytes::{Bytes, BytesMut};
use plccoms_plc::s7::codec::TpktCodec;
use plccoms_plc::s7::frame::{Answer, Item, Job, Tpdu, Tsaps};
use plccoms_plc::s7::{Region, ReturnCode};
use proptest::prelude::*;
use tokio_util::codec::Encoder;

/// A stream of valid frames: a connect confirm, then jobs and answers.
fn valid_stream(seed: u16) -> Vec<u8> {
    let mut out = BytesMut::new();
    let mut pdu = BytesMut::new();
    let item = Item::bytes(Region::Db(seed), u32::from(seed % 100), seed % 30 + 1);
    let frames = [
        Tpdu::ConnectConfirm(Tsaps::rack_slot(0, 1)),
        {
            Job::Setup { jobs: 1, pdu: 480 }.encode(1, &mut pdu);
            Tpdu::Data(pdu.split().freeze())
        },
        {
            Job::Read(vec![item; usize::from(seed % 5) + 1]).encode(2, &mut pdu);
            Tpdu::Data(pdu.split().freeze())
        },
        {
            Job::Write(vec![(item, Bytes::from(vec![7; usize::from(item.len)]))])
                .encode(3, &mut pdu);
            Tpdu::Data(pdu.split().freeze())
        },
        {
            Answer::Read(vec![
                Ok(Bytes::from(vec![1; usize::from(seed % 9)])),
                Err(ReturnCode::NO_OBJECT),
            ])
            .encode(2, &mut pdu);
            Tpdu::Data(pdu.split().freeze())
        },
        {
            Answer::Write(vec![Ok(()), Err(ReturnCode::ACCESS_DENIED)]).encode(3, &mut pdu);
            Tpdu::Data(pdu.split().freeze())
        },
        {
            Job::ReadSzl {
                id: 0x424,
                index: 0,
            }
            .encode(4, &mut pdu);
            Tpdu::Data(pdu.split().freeze())
        },
    ];
    for frame in frames {
        TpktCodec.encode(frame, &mut out).unwrap();
    }
    out.to_vec()
}

#[test]
fn ordinary_inputs() {
    s7_checks::s7_stream(&valid_stream(3));
    s7_checks::s7_stream(&[3, 0, 0, 7, 2, 0xF0, 0x80]);
    s7_checks::s7_stream(&[3, 0, 0, 0xFF]);
    s7_checks::s7_tags(b"name,address,type\nA,DB1.DBW0,INT\nB,DB1.DBX2.0,BOOL\nS,DB1.DBS4.10\nT,MB0,DTL\nU,IB0,DATE_AND_TIME\nV,QW0,S5TIME\nW,MD0,WSTRING[3]\nX,DB9.DBW0,ARRAY[0..3] OF TIME\n");
}

fn fragment() -> impl Strategy<Value = &'static str> {
    proptest::sample::select(vec![
        "DB1.DBX0.0",
        "DB65534.DBB65535",
        "DB65535.DBB0",
        "DB2.DBW65534",
        "DB3.DBD4",
        "DB1.DBS10.20",
        "M10.1",
        "MB0",
        "MW2",
        "MD4",
        "I0.0",
        "E1.7",
        "IW64",
        "Q0.0",
        "A0.1",
        "QW2",
        "AW2",
        "T5",
        "DB0.DBB0",
        "DB1.DBS0.254",
        ",",
        "\n",
        "\"",
        "INT",
        "BOOL",
        "STRING[20]",
        "WSTRING[254]",
        "DTL",
        "DATE_AND_TIME",
        "S5TIME",
        "LREAL",
        "ARRAY[0..9] OF INT",
        "ARRAY[-5..5] OF BOOL",
        "ARRAY[0..65535] OF STRING[254]",
        "ro",
        "rw",
        "x",
        "é",
        "#",
        "",
    ])
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    /// Valid frames cut anywhere and with bytes flipped: errors, never a
    /// panic, and what parses encodes back to itself.
    #[test]
    fn frames_cut_and_flipped(seed in 1u16..200, cut in 0usize..400, flips in proptest::collection::vec((0usize..400, any::<u8>()), 0..4)) {
        let mut bytes = valid_stream(seed);
        for (at, value) in flips {
            if let Some(b) = bytes.get_mut(at) {
                *b = value;
            }
        }
        bytes.truncate(cut.max(1));
        s7_checks::s7_stream(&bytes);
    }

    #[test]
    fn any_bytes_as_a_stream(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let mut framed = vec![3, 0, 0, (bytes.len() + 4).min(255) as u8];
        framed.extend_from_slice(&bytes);
        s7_checks::s7_stream(&framed);
        s7_checks::s7_stream(&bytes);
    }

    #[test]
    fn tag_files_from_the_grammar(lines in proptest::collection::vec(proptest::collection::vec(fragment(), 0..7), 0..12)) {
        let mut text = String::from("name,address,type,unit,description,access\n");
        for (i, line) in lines.iter().enumerate() {
            text.push_str(&format!("t{i},"));
            text.push_str(&line.join(","));
            text.push('\n');
        }
        s7_checks::s7_tags(text.as_bytes());
    }
}
