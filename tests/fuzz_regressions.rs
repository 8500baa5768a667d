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
    ] {
        checks::user_value(text.as_bytes());
    }
    // IDENT request from 0x7D.
    checks::modbus_tags(include_bytes!("../conf/demo-modbus.csv"));
    checks::modbus_tags(
        b"name,type,table,address,bit,order,scale,offset\nx,INT,holding,65535,,,0.5,1\n",
    );
    checks::opcua_tags(
        b"name,node,type,access,unit\nspeed,\"ns=3;s=\"\"DB\"\".\"\"x\"\"\",REAL,rw,rpm\nb,i=1,BOOL\nu,ns=1;i=2\n",
    );
    checks::opcua_node_id(b"nsu=http://x/;g=09087e75-8e5e-499b-954f-f2a9603db28a");
    // FC 3 answer of two registers, then an exception, then half an ADU.
    checks::modbus_answer(&[
        0, 2, 0, 1, 0, 0, 0, 7, 1, 3, 4, 0xBE, 0xEF, 0, 1, 0, 2, 0, 0, 0, 3, 1, 0x83, 2, 0, 3, 0,
    ]);
    checks::epsnet_device(&[
        0x00, 0x01, 0x02, 0x00, 0x00, 0x0A, 0x68, 0x04, 0x04, 0x68, 0x00, 0x7D, 0x63, 0x01, 0xE1,
        0x16,
    ]);
}

proptest::proptest! {
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
            checks::opcua_node_id(node.as_bytes());
        }
        checks::opcua_tags(text.as_bytes());
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
