//! EPSNET codec properties: round trips, and no panic on any input.

use plccoms_plc::epsnet::codec::{decode_packet, encode_packet};
use plccoms_plc::epsnet::frame::{DataFrame, Frame, Packet, MAX_PACKET};
use plccoms_plc::epsnet::service::{decode_answer, Request, FC_REQUEST};
use proptest::prelude::*;

fn frame() -> impl Strategy<Value = Frame> {
    prop_oneof![
        Just(Frame::Ack),
        (
            any::<u8>(),
            any::<u8>(),
            any::<u8>(),
            prop::collection::vec(any::<u8>(), 0..400)
        )
            .prop_map(|(da, sa, fc, data)| Frame::Data(DataFrame { da, sa, fc, data })),
    ]
}

proptest! {
    #[test]
    fn packets_round_trip(mesi in any::<u16>(), frames in prop::collection::vec(frame(), 1..4)) {
        let packet = Packet { mesi, frames };
        let bytes = encode_packet(&packet).unwrap();
        prop_assert_eq!(bytes.len() % 2, 0);
        prop_assert!(bytes.len() <= MAX_PACKET);
        prop_assert_eq!(decode_packet(&bytes).unwrap(), packet);
    }

    #[test]
    fn decoding_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..1600)) {
        let _ = decode_packet(&bytes);
    }

    #[test]
    fn corrupted_packets_never_panic(
        frames in prop::collection::vec(frame(), 1..3),
        at in any::<prop::sample::Index>(),
        xor in 1u8..,
    ) {
        let mut bytes = encode_packet(&Packet { mesi: 1, frames }).unwrap();
        let i = at.index(bytes.len());
        bytes[i] ^= xor;
        let _ = decode_packet(&bytes);
    }

    #[test]
    fn request_and_answer_parsers_never_panic(
        fc in any::<u8>(),
        data in prop::collection::vec(any::<u8>(), 0..300),
        answer in frame(),
    ) {
        let _ = Request::decode(fc, &data);
        if let Ok(request) = Request::decode(FC_REQUEST, &data) {
            let _ = decode_answer(&request, &answer);
            prop_assert_eq!(Request::decode(FC_REQUEST, &request.encode()), Ok(request));
        }
    }
}
