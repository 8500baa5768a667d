//! Inputs the fuzz targets (`fuzz/`) found or need, replayed on the stable
//! toolchain through the very checks the targets run (`fuzz/src/checks.rs`,
//! included here), so every crash found stays fixed.

#[path = "../fuzz/src/checks.rs"]
#[allow(dead_code)]
mod checks;

#[global_allocator]
static ALLOC: checks::alloc_count::Counting = checks::alloc_count::Counting;

/// Every target on a few ordinary inputs, so the shared checks build and run
/// in the normal test suite.
#[test]
fn every_target_runs_on_ordinary_input() {
    for line in [
        &b"GET:test_*"[..],
        b"SET:test_1,-32768",
        b"EN:t* 0.5",
        b"GETMEM:%R100 16",
        b"WRITEFILE:a.txt[3]=abc",
        b"SETCONF: pubfile, Test.pub",
        b"",
        b"x",
    ] {
        checks::request_line(line);
    }
    checks::input_decoder(b"\x10\x02\x07GET:x\r\nWRITEFILE:a[3]=abc\r\n\xff\xfb\x18\x04");
    checks::ini(include_bytes!("data/vendor/PLCComS.ini"));
    checks::pubfile(include_bytes!("../conf/demo.pub"));
    // Fields of megabytes: names past MAX_NAME, quoted short in warnings.
    let long = "N".repeat(1 << 20);
    checks::pubfile(
        format!(" {long} R B 0 BYTE\r\n x {long} B 0 BYTE\r\n;* crc=\"{long}\"").as_bytes(),
    );
    for name in [
        &b"./a.txt"[..],
        b"./d/../a.txt",
        b"./out",
        b"./.hidden",
        b"./own.ini",
        b"./",
        b"//../x.pub",
        b"/etc/passwd",
        b"C:\\x",
    ] {
        checks::local_path(name);
    }
    checks::web_query(
        b"section=Demo&vars=SIN*,%20counter&from=0&to=2026-11-30T12:00:00%2B01:00&format=csv",
    );
    checks::web_query(b"section=Demo&from=9&to=8&vars=,,");
    for id in [
        &b"Hala\nHala.2\nHala.2.TEMP#EURange"[..],
        b"Hala\nHala.",
        b"Hala\nHala#",
        b"Hala\nplccoms",
        b"\n\n",
        b"",
        b"A\nA.B#C#D",
    ] {
        checks::opcua_node_id(id);
    }
    checks::opcua_users(b"# none\n\nhmi write pbkdf2-sha256:1000:00112233445566778899:00");
    checks::opcua_users(b"a read pbkdf2-sha256:99999999999:zz:zz\nb");
    checks::opcua_write(b"\x01\x02\x03\x04\x05\x06\x07\x08PT1H");
    checks::opcua_write(b"\xff\xff\xff\xff\xff\xff\xef\x7f2026-11-25T10:15:00Z");
    checks::web_query(b"section=%ZZ&&=&format=\xff");
    for time in [
        "-7d",
        "2026-05-01T12:00:00.123Z",
        "2026-05-01",
        "now",
        "-9999999999999999w",
        "x",
    ] {
        checks::history_time(time.as_bytes());
    }
    // A packed history block (the seed of fuzz/seed.sh), whole and cut.
    let block: &[u8] = b"\x01\x01\x64\x03\x02\x00\x02\x05\x01\x00\xc8\x01\x00\x01\x02\x03\x0e\
        \x3f\xf8\x00\x00\x00\x00\x00\x00\x02ab\x00\x02\x00\x01\x00\x09";
    for end in [block.len(), block.len() - 3, 1, 0] {
        checks::history_block(&block[..end]);
        // Sealed with its checksum (file version 3).
        let mut sealed = block[..end].to_vec();
        if let Some(mode) = sealed.first_mut() {
            *mode = 2;
        }
        checks::history_block(&sealed);
    }
    checks::history_block(b"\x00\x28\xb5\x2f\xfd garbage");
    // A sealed block whose checksum does not match, and one cut short.
    checks::history_block(b"\x00\x02\x00\x00\x00\x00\x28\xb5\x2f\xfd");
    checks::history_block(b"\x00\x02\x01");
    // READN answer of 2 bytes, then the same datagram as a request.
    let answer = [
        0x00, 0x02, 0x00, 0x07, 0x02, 0x00, 0x00, 0x0D, 0x68, 0x07, 0x07, 0x68, 0x7D, 0x00, 0x08,
        0x10, 0x00, 0xAA, 0xBB, 0xFA, 0x16, 0x00,
    ];
    checks::epsnet_client(&answer);
    // The same frame on a serial line, after noise, one byte at a time.
    let mut line = vec![1, 0x00, 0x16, 0x68, 0x07];
    line.extend_from_slice(&answer[6..21]);
    checks::epsnet_stream(&line);
    let mut record = Vec::new();
    plccoms_mqtt::spool::encode_record(
        7,
        &plccoms_mqtt::spool::Message {
            topic: "plccoms/Demo/A%2FB".into(),
            payload: b"42".to_vec(),
            qos: 1,
            retain: true,
        },
        &mut record,
    );
    checks::mqtt_spool(&record);
    for text in [
        "mqtt://broker.lan:1883",
        "mqtts://[::1]",
        "mqtt://a:1883, mqtt://b:1883 mqtts://[::1]:8884",
        "mqtt://a, mqtt://a:1883",
        " , ",
        "A%2FB",
        "TEPLOTA_KUCHYNĚ",
        "%zz",
    ] {
        checks::mqtt_text(text.as_bytes());
    }
    for text in [
        "2026-11-25T10:15:00.123Z",
        "2026-11-25T11:15:00+01:00",
        "2026-11-25",
        "10:15:00.123",
        "PT1H2M3.456S",
        "P1DT0.25S",
        "P49D",
        "9999-12-31T23:59:59.999+14:00",
        "5.0",
        "",
        "\u{ff}",
        // A DATE chrono took and no face prints back (fuzz, 2026-11-28).
        "+23220-6-5",
    ] {
        checks::user_value(text.as_bytes());
    }
    // LREALs as bytes: integral (0, -0, 2^53 + 2, -1234), of few fractional
    // bits (21.5, -0.125), longer, and one past the own path of those.
    for (x, decimals) in [
        (0.0, 2),
        (-0.0, 0),
        (9_007_199_254_740_994.0, 40),
        (-1234.0, 2),
        (-1234.567, 2),
        (21.5, 6),
        (-0.125, 2),
        (9.5e18, 2),
    ] {
        let mut data = f64::to_le_bytes(x).to_vec();
        data.push(decimals);
        checks::user_value(&data);
    }
    // A DCMD of COUNTER = 42 by alias 21 (Int16 in int_value), an NCMD
    // rebirth by name, an empty payload, and a truncated varint.
    checks::sparkplug_command(&[0x12, 0x06, 0x10, 0x15, 0x20, 0x02, 0x50, 0x2a]);
    checks::sparkplug_command(&[
        0x12, 0x18, 0x0a, 0x14, b'N', b'o', b'd', b'e', b' ', b'C', b'o', b'n', b't', b'r', b'o',
        b'l', b'/', b'R', b'e', b'b', b'i', b'r', b't', b'h', 0x70, 0x01,
    ]);
    checks::sparkplug_command(b"");
    checks::sparkplug_command(&[0x12, 0x80]);
    // IDENT request from 0x7D.
    checks::modbus_tags(include_bytes!("../conf/demo-modbus.csv"));
    checks::modbus_tags(
        b"name,type,table,address,bit,order,scale,offset\nx,INT,holding,65535,,,0.5,1\n",
    );
    checks::opcua_tags(
        b"name,node,type,access,unit\nspeed,\"ns=3;s=\"\"DB\"\".\"\"x\"\"\",REAL,rw,rpm\nb,i=1,BOOL\nu,ns=1;i=2\n",
    );
    checks::opcua_client_node_id(b"nsu=http://x/;g=09087e75-8e5e-499b-954f-f2a9603db28a");
    // A Double, a String and a UInt16[2], then their body.
    checks::opcua_structure(
        b"\x03\x0b\x00\x00\x0c\x00\x00\x05\x02\x02\
          \x00\x00\x00\x00\x00\x00\xf8\x3f\x02\x00\x00\x00ab\x02\x00\x00\x00\x07\x00\x08\x00",
    );
    // FC 3 answer of two registers, then an exception, then half an ADU.
    checks::modbus_answer(&[
        0, 2, 0, 1, 0, 0, 0, 7, 1, 3, 4, 0xBE, 0xEF, 0, 1, 0, 2, 0, 0, 0, 3, 1, 0x83, 2, 0, 3, 0,
    ]);
    // An AMS/TCP Read answer of two bytes, then half a header.
    checks::ads_stream(&[
        0, 0, 42, 0, 0, 0, 10, 0, 0, 1, 1, 1, 0x89, 0x80, 5, 1, 2, 3, 1, 1, 0x53, 3, 2, 0, 5, 0,
        10, 0, 0, 0, 0, 0, 0, 0, 7, 0, 0, 0, 0, 0, 0, 0, 2, 0, 0, 0, 0xBE, 0xEF, 0, 0, 9,
    ]);
    // A read answer from unit 1, a damaged copy, noise, half a frame.
    checks::modbus_rtu(&[
        3, 1, 3, 4, 0, 5, 0, 6, 0x5B, 0xF0, 1, 3, 4, 0, 5, 0, 7, 0x5B, 0xF0, 0x42, 1, 3,
    ]);
    checks::epsnet_device(&[
        0x00, 0x01, 0x02, 0x00, 0x00, 0x0A, 0x68, 0x04, 0x04, 0x68, 0x00, 0x7D, 0x63, 0x01, 0xE1,
        0x16,
    ]);
}

proptest::proptest! {
    /// Sparkplug commands: metrics of every value field with and without
    /// alias and name, then cut or with a byte flipped anywhere.
    #[test]
    fn sparkplug_commands_never_panic(
        metrics in proptest::collection::vec(
            (proptest::option::of(0u64..1 << 40), proptest::option::of("[A-Z_/ ]{0,12}"), 10u8..17, proptest::collection::vec(proptest::num::u8::ANY, 0..12)),
            0..6,
        ),
        cut in proptest::num::usize::ANY,
        flip in proptest::option::of((proptest::num::usize::ANY, proptest::num::u8::ANY)),
    ) {
        let mut bytes = Vec::new();
        for (alias, name, field, raw) in &metrics {
            let mut m = Vec::new();
            if let Some(name) = name {
                m.extend([0x0a, name.len() as u8]);
                m.extend(name.as_bytes());
            }
            if let Some(alias) = alias {
                m.push(0x10);
                varint(*alias, &mut m);
            }
            // The value's field: varints for 10, 11, 14; fixed for 12, 13;
            // length-delimited for 15, 16.
            match field {
                12 => { m.push(12 << 3 | 5); m.extend(raw.iter().chain([0; 4].iter()).take(4)); }
                13 => { m.push(13 << 3 | 1); m.extend(raw.iter().chain([0; 8].iter()).take(8)); }
                15 | 16 => { m.extend([field << 3 | 2, raw.len() as u8]); m.extend(raw); }
                _ => { m.push(field << 3); varint(raw.iter().fold(0u64, |a, b| a << 8 | u64::from(*b)), &mut m); }
            }
            bytes.push(0x12);
            varint(m.len() as u64, &mut bytes);
            bytes.extend(m);
        }
        checks::sparkplug_command(&bytes);
        if let Some((at, byte)) = flip {
            if !bytes.is_empty() {
                let at = at % bytes.len();
                bytes[at] ^= byte;
            }
        }
        checks::sparkplug_command(&bytes);
        let keep = if bytes.is_empty() { 0 } else { cut % bytes.len() };
        checks::sparkplug_command(&bytes[..keep]);
    }

    /// The RTU decoder over any bytes, cut anywhere.
    #[test]
    fn modbus_rtu_framing_holds_for_any_bytes(data in proptest::collection::vec(proptest::num::u8::ANY, 0..600)) {
        checks::modbus_rtu(&data);
    }

    /// OPC UA tag files and node ids built from the pieces that matter.
    #[test]
    fn opcua_tag_files_and_node_ids(
        rows in proptest::collection::vec(
            (
                proptest::sample::select(vec!["a", "A", "b.c", "x y", "%x", "\"q\"", "é", ""]),
                proptest::sample::select(vec!["i=1", "ns=2;s=a;b", "ns=70000;i=1", "nsu=u;i=5", "g=1", "b=AA==", "s=", "ns=1;x=2"]),
                proptest::sample::select(vec!["", "BOOL", "STRING[80]", "LREAL", "FLOAT", "STRING[0]"]),
                proptest::sample::select(vec!["", "ro", "rw", "RW", "w"]),
            ),
            0..12,
        ),
        header in proptest::sample::select(vec!["name,node,type,access", "NODE,Name", "name,type", "node,name,access,type,unit"]),
    ) {
        let mut text = format!("{header}\n");
        for (name, node, ty, access) in &rows {
            text.push_str(&format!("{name},\"{}\",{ty},{access}\n", node.replace('"', "\"\"")));
            checks::opcua_client_node_id(node.as_bytes());
        }
        checks::opcua_tags(text.as_bytes());
    }

    /// Structure bodies walked by definitions, both from random bytes
    /// (the first bytes the definition, see `checks::opcua_structure`).
    #[test]
    fn opcua_structures_walk_any_body(data in proptest::collection::vec(proptest::num::u8::ANY, 0..400)) {
        checks::opcua_structure(&data);
    }

    /// Valid definitions of nested, array and string fields over bodies
    /// that are mostly small lengths, so the walk goes deep.
    #[test]
    fn opcua_structures_walk_plausible_bodies(
        definition in proptest::collection::vec(proptest::sample::select(vec![0u8, 1, 2, 3, 4, 5, 11, 12, 17, 18, 21, 23, 24]), 0..24),
        body in proptest::collection::vec(proptest::sample::select(vec![0u8, 1, 2, 3, 0xff, 0x80]), 0..300),
    ) {
        let mut data = definition;
        data.extend(body);
        checks::opcua_structure(&data);
    }

    /// Names built from the characters that matter to the path rules.
    #[test]
    fn local_path_rules_hold_for_generated_names(
        parts in proptest::collection::vec(
            proptest::sample::select(vec!["a.txt", "d", "..", ".", "", "out", ".hidden", "own.ini", "x", "C:", "\0"]),
            0..6,
        ),
        seps in proptest::collection::vec(proptest::sample::select(vec!["/", "\\", "//"]), 6),
        lead in proptest::sample::select(vec!["", ".", "./", "//", "/"]),
    ) {
        let mut name = lead.to_string();
        for (part, sep) in parts.iter().zip(&seps) {
            name.push_str(part);
            name.push_str(sep);
        }
        checks::local_path(name.as_bytes());
        checks::local_path(name.trim_end_matches(['/', '\\']).as_bytes());
    }
}

proptest::proptest! {
    /// MQTT_URL lists of URLs, near-URLs and separators.
    #[test]
    fn broker_url_lists_hold(
        parts in proptest::collection::vec(
            proptest::sample::select(vec![
                "mqtt://a", "mqtt://a:1883", "mqtts://b:8883", "mqtt://[::1]:1", "tcp://c",
                "mqtt://", "mqtt://d:0", "http://e", "f", "mqtt://u@g", ",", " ", "\t", "",
            ]),
            0..20,
        ),
        seps in proptest::collection::vec(proptest::sample::select(vec![",", " ", ", ", ",,", ""]), 20),
    ) {
        let mut text = String::new();
        for (part, sep) in parts.iter().zip(&seps) {
            text.push_str(part);
            text.push_str(sep);
        }
        checks::mqtt_text(text.as_bytes());
    }
}

/// A protobuf varint.
fn varint(mut n: u64, out: &mut Vec<u8>) {
    while n >= 0x80 {
        out.push(n as u8 | 0x80);
        n >>= 7;
    }
    out.push(n as u8);
}

proptest::proptest! {
    /// OPC UA node ids and users files from the characters that matter to
    /// their grammars, through the fuzz targets' checks.
    #[test]
    fn opcua_parsers_hold_for_generated_text(
        parts in proptest::collection::vec(
            proptest::sample::select(vec![
                "Hala", "Hala.2", ".", "#", "TEMP", "EURange", "plccoms", "\n", " ", "write",
                "read", "pbkdf2-sha256:", "1000:", "0011223344556677:", "zz", "\u{17d}",
            ]),
            0..12,
        ),
        number in proptest::num::u64::ANY,
    ) {
        let text = parts.concat();
        checks::opcua_node_id(text.as_bytes());
        checks::opcua_users(text.as_bytes());
        let mut write = number.to_le_bytes().to_vec();
        write.extend_from_slice(text.as_bytes());
        checks::opcua_write(&write);
    }
}

proptest::proptest! {
    /// ADS packets with arbitrary data, framed right or cut anywhere, and
    /// arbitrary bytes: the ADS decoders never panic and round-trip.
    #[test]
    fn ads_decoders_hold_on_any_stream(
        data in proptest::collection::vec(proptest::num::u8::ANY, 0..200),
        command in 0u16..12,
        cut in 0usize..300,
    ) {
        let mut stream = vec![0u8, 0];
        stream.extend_from_slice(&(32 + data.len() as u32).to_le_bytes());
        stream.extend_from_slice(&[5, 1, 2, 3, 1, 1, 0x53, 3, 10, 0, 0, 1, 1, 1, 0x89, 0x80]);
        stream.extend_from_slice(&command.to_le_bytes());
        stream.extend_from_slice(&[5, 0]);
        stream.extend_from_slice(&(data.len() as u32).to_le_bytes());
        stream.extend_from_slice(&[0; 8]);
        stream.extend_from_slice(&data);
        checks::ads_stream(&stream);
        checks::ads_stream(&stream[..cut.min(stream.len())]);
        checks::ads_stream(&data);
    }

    /// Tag file lines built from the pieces that matter to its parser.
    #[test]
    fn ads_tag_files_hold(
        lines in proptest::collection::vec(
            proptest::collection::vec(
                proptest::sample::select(vec!["name", "MAIN.x", "0x4020:4", "1:x", "INT", "STRING(80)", "\"a,b\"", "", "#", "\u{e9}", "STRING[3]", ":"]),
                0..7,
            ),
            0..8,
        ),
    ) {
        let text: String = lines.iter().map(|l| l.join(",") + "\n").collect();
        checks::ads_stream(text.as_bytes());
    }
}
