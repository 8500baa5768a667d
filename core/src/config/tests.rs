use super::*;

const FILE: &str = "PLCComS.ini";

fn ok(text: &str) -> Loaded {
    match parse(Path::new(FILE), text) {
        Ok(loaded) => loaded,
        Err(e) => panic!("{e}"),
    }
}

fn messages(loaded: &Loaded) -> Vec<String> {
    loaded.diagnostics.iter().map(ToString::to_string).collect()
}

fn all_are(loaded: &Loaded, severity: Severity) -> bool {
    loaded.diagnostics.iter().all(|d| d.severity == severity)
}

fn section_names(loaded: &Loaded) -> Vec<&str> {
    loaded
        .config
        .sections
        .iter()
        .map(|s| s.name.as_str())
        .collect()
}

/// A file whose `[*]` is `global` (line 2 onwards) and with one PLC section.
fn with_global(global: &str) -> Result<Loaded, ConfigError> {
    parse(
        Path::new(FILE),
        &format!("[*]\n{global}\n[PLC]\nSERVER_PORT = 5010\n"),
    )
}

/// The error messages of a file that cannot be used.
fn invalid(text: &str) -> Vec<String> {
    match parse(Path::new(FILE), text) {
        Err(ConfigError::Invalid { diagnostics, .. }) => diagnostics
            .iter()
            .filter(|d| d.severity == Severity::Error)
            .map(ToString::to_string)
            .collect(),
        Err(e) => panic!("{text}: {e}"),
        Ok(_) => panic!("{text}: loaded"),
    }
}

/// The message of the one error that a `[*]` line 2 of `global` causes.
fn global_error(global: &str) -> String {
    let errors = invalid(&format!("[*]\n{global}\n[PLC]\nSERVER_PORT = 5010\n"));
    assert_eq!(errors.len(), 1, "{global}: {errors:?}");
    errors[0].clone()
}

fn global(global: &str) -> Global {
    let loaded = with_global(global).unwrap_or_else(|e| panic!("{global}: {e}"));
    assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
    loaded.config.global
}

/// A file with `[*]` and one PLC section `[PLC]` whose body starts at
/// line 3.
fn with_section(body: &str) -> Result<Loaded, ConfigError> {
    parse(Path::new(FILE), &format!("[*]\n[PLC]\n{body}\n"))
}

fn section(body: &str) -> Section {
    let loaded = with_section(body).unwrap_or_else(|e| panic!("{body}: {e}"));
    assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
    loaded.config.sections.into_iter().next().unwrap()
}

/// The first error of a section body that makes the only section fail.
fn section_error(body: &str) -> String {
    let text = format!("[*]\n[PLC]\n{body}\n[OTHER]\nSERVER_PORT = 6000\n");
    let loaded = parse(Path::new(FILE), &text).unwrap_or_else(|e| panic!("{body}: {e}"));
    assert_eq!(loaded.config.sections.len(), 1, "{body}: not skipped");
    assert_eq!(loaded.config.sections[0].name, "OTHER");
    let errors: Vec<_> = loaded
        .diagnostics
        .iter()
        .filter(|d| d.severity == Severity::Error)
        .map(ToString::to_string)
        .collect();
    assert_eq!(
        errors[0], "PLCComS.ini:2: section [PLC] skipped (1 error)",
        "{body}"
    );
    assert_eq!(errors.len(), 2, "{body}: {errors:?}");
    errors[1].clone()
}

/// A section with only a SERVER_PORT: the defaults the manual gives, the
/// other keys unset.
fn plain_section(name: &str, server_port: u16) -> Section {
    Section {
        epstout: Duration::from_millis(1000),
        epstout_step: Duration::from_millis(500),
        epsport: 61682,
        server_port,
        pubfile_crc: false,
        pubfile_write: false,
        protocol: Protocol::Epsnet,
        read_only: false,
        ..section_defaults(name)
    }
}

#[test]
fn vendor_file_loads_unchanged() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/data/vendor/PLCComS.ini");
    let loaded = load(&path).unwrap();
    assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
    let config = loaded.config;
    assert_eq!(config.path, path);
    assert_eq!(
        config.global,
        Global {
            comm_sched_pri: 10,
            ffile_maxrecs: 0,
            sync_var_enabled: false,
            serial_device_cfg: serial::parse_device_cfg("/dev/ttyS0 -1, /dev/ttyS1 -1").ok(),
            ..Global::default()
        }
    );
    // Every section inherits [*] SERIAL_DEVICE_CFG (the RTS pins of lines).
    let mut sections = config.sections.clone();
    for section in &mut sections {
        assert_eq!(section.serial_device_cfg, config.global.serial_device_cfg);
        section.serial_device_cfg = None;
        // The path keys are noted as written, for Config::own_paths.
        let noted: Vec<_> = section.paths.drain(..).map(|p| (p.key, p.text)).collect();
        assert_eq!(
            noted,
            [
                ("PUBFILE", "//VARLIST.PUB".to_string()),
                ("PUBFILE_FIXED", "FIXED_Foxtrot.pub".to_string())
            ]
        );
    }
    assert_eq!(
        sections,
        vec![Section {
            ipaddr: Some(Ipv4Addr::new(192, 168, 89, 1)),
            pubfile_crc: true,
            pubfile: Some("//VARLIST.PUB".into()),
            pubfile_fixed: Some("FIXED_Foxtrot.pub".into()),
            ..plain_section("Foxtrot", 5011)
        }]
    );
}

#[test]
fn vendor_file_with_every_sample_section_uncommented() {
    let vendor = include_str!("../../../tests/data/vendor/PLCComS.ini");
    // Uncomment the sample sections and their keys, not the key catalogue
    // under [Alias for PLC] (its values are prose).
    let mut text = String::new();
    let mut in_samples = false;
    for line in vendor.lines() {
        if line.starts_with("#[") {
            in_samples = line != "#[Alias for PLC]";
        } else if line.starts_with('[') {
            in_samples = false;
        }
        if in_samples && line.starts_with('#') {
            text.push_str(&line[1..]);
        } else {
            text.push_str(line);
        }
        text.push_str("\r\n");
    }
    // And the commented IPADDR_LOCAL in [Foxtrot], with its trailing comment.
    let text = text.replace(
        "\n#IPADDR_LOCAL  = 192.168.1.100 #IP",
        "\nIPADDR_LOCAL  = 192.168.1.100 #IP",
    );
    let loaded = ok(&text);
    assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
    let names = section_names(&loaded);
    assert_eq!(
        names,
        ["iFoxtrot", "Foxtrot", "TC700", "TC700 RS232", "SoftPLC"]
    );
    let foxtrot = &loaded.config.sections[1];
    assert_eq!(foxtrot.ipaddr_local, Some(Ipv4Addr::new(192, 168, 1, 100)));
    assert_eq!(foxtrot.pubfile.as_deref(), Some("//VARLIST.PUB"));
    let ifoxtrot = &loaded.config.sections[0];
    assert_eq!(ifoxtrot.ipaddr, Some(Ipv4Addr::new(192, 168, 134, 176)));
    assert_eq!(ifoxtrot.pubfile.as_deref(), Some("//iFoxtrot.pub"));
    let rs232 = &loaded.config.sections[3];
    assert_eq!(rs232.serial_device.as_deref(), Some("/dev/ttyS0"));
    assert_eq!(rs232.serial_speed, Some(115200));
    assert_eq!(rs232.ipaddr, None);
    let soft = &loaded.config.sections[4];
    assert_eq!(soft.shm_name.as_deref(), Some("ShmSrv.dll"));
    assert_eq!((soft.shm_socket, soft.shm_port), (Some(0), Some(5)));
}

#[test]
fn defaults() {
    assert_eq!(global(""), Global::default());
    let d = Global::default();
    assert_eq!(d.comm_loop_delay, Duration::from_millis(100));
    assert_eq!(d.comm_sched_pri, 0);
    assert_eq!(d.net_connect_max, 128);
    assert_eq!(d.mem_blksize, 4096);
    assert!(d.mem_use_threads);
    assert_eq!(d.ffile_blksize, 4096);
    assert_eq!(d.ffile_timeout, Duration::from_secs(300));
    assert_eq!(d.ffile_timeout_wr, Duration::from_secs(5));
    assert_eq!(d.ffile_maxrecs, 256);
    assert!(d.end_line_crlf);
    assert!(d.pf_var_disabled);
    assert!(d.diff_var_enabled);
    assert!(d.sync_var_enabled);
    assert!(!d.date_time_decimal);
    assert!(!d.lim_of_decimals);
    assert_eq!(d.num_of_decimals, 10);
    assert!(!d.scient_notation);
    assert_eq!(d.serial_device_cfg, None);

    assert_eq!(section("SERVER_PORT = 5010"), plain_section("PLC", 5010));
}

#[test]
fn an_empty_value_means_the_default() {
    assert_eq!(
        global("COMM_LOOP_DELAY =\nEND_LINE_CRLF =  "),
        Global::default()
    );
}

/// (key, min, max, unit in messages, how to read the value back)
type GlobalRange = (&'static str, u64, u64, &'static str, fn(&Global) -> u64);

/// The messages of a number key's values out of its range `(min, max,
/// unit)`, or not numbers at all; `error` is the message of `KEY = value`
/// at `line`.
fn range_errors(
    key: &str,
    (min, max, unit): (u64, u64, &str),
    line: usize,
    error: impl Fn(&str) -> String,
) {
    let allowed = format!("(allowed {min}-{max}{unit})");
    let mut out_of_range = vec![(max + 1).to_string(), "99999999999999999999999".into()];
    if min > 0 {
        out_of_range.push((min - 1).to_string());
    }
    for value in out_of_range {
        assert_eq!(
            error(&format!("{key} = {value}")),
            format!("PLCComS.ini:{line}: {key} = {value} is out of range {allowed}")
        );
    }
    for value in ["-1", "x"] {
        assert_eq!(
            error(&format!("{key} = {value}")),
            format!("PLCComS.ini:{line}: {key} = {value} is not a number {allowed}")
        );
    }
}

#[test]
fn global_ranges() {
    let ranges: [GlobalRange; 11] = [
        ("COMM_LOOP_DELAY", 1, 1000, " ms", |g| {
            g.comm_loop_delay.as_millis() as u64
        }),
        ("COMM_SCHED_PRI", 0, 99, "", |g| u64::from(g.comm_sched_pri)),
        ("NET_CONNECT_MAX", 1, 1024, "", |g| g.net_connect_max as u64),
        ("MEM_BLKSIZE", 1, 65536, " bytes", |g| g.mem_blksize as u64),
        ("FFILE_BLKSIZE", 1, 65536, " bytes", |g| {
            g.ffile_blksize as u64
        }),
        ("FFILE_TIMEOUT", 0, 3600, " s", |g| {
            g.ffile_timeout.as_secs()
        }),
        ("FFILE_TIMEOUT_WR", 1, 60, " s", |g| {
            g.ffile_timeout_wr.as_secs()
        }),
        ("FFILE_MAXRECS", 0, 1024, "", |g| g.ffile_maxrecs as u64),
        ("NUM_OF_DECIMALS", 0, 15, "", |g| {
            u64::from(g.num_of_decimals)
        }),
        ("OUTPUT_HARD_LIMIT", 4096, 1 << 30, " bytes", |g| {
            g.output_hard_limit as u64
        }),
        ("OUTPUT_SOFT_TIMEOUT", 1, 3600, " s", |g| {
            g.output_soft_timeout.as_secs()
        }),
    ];
    for (key, min, max, unit, read) in ranges {
        assert_eq!(read(&global(&format!("{key} = {min}"))), min, "{key}");
        assert_eq!(read(&global(&format!("{key} = {max}"))), max, "{key}");
        range_errors(key, (min, max, unit), 2, global_error);
    }
    assert_eq!(
        global_error("COMM_LOOP_DELAY = 5000"),
        "PLCComS.ini:2: COMM_LOOP_DELAY = 5000 is out of range (allowed 1-1000 ms)"
    );
    assert_eq!(
        global_error("COMM_LOOP_DELAY = 10ms"),
        "PLCComS.ini:2: COMM_LOOP_DELAY = 10ms is not a number (allowed 1-1000 ms)"
    );
    assert_eq!(
        global("COMM_LOOP_DELAY = 0050").comm_loop_delay,
        Duration::from_millis(50)
    );
}

#[test]
fn output_limits() {
    let d = Global::default();
    assert_eq!(d.output_hard_limit, 16 << 20);
    assert_eq!(d.output_soft_limit, 1 << 20);
    assert_eq!(d.output_soft_timeout, Duration::from_secs(30));
    let g = global("OUTPUT_SOFT_LIMIT = 1024\nOUTPUT_HARD_LIMIT = 4096");
    assert_eq!((g.output_soft_limit, g.output_hard_limit), (1024, 4096));
    // Without its own value the soft limit follows a lower hard limit.
    assert_eq!(global("OUTPUT_HARD_LIMIT = 65536").output_soft_limit, 65536);
    assert_eq!(
        global("OUTPUT_SOFT_LIMIT = 16777216").output_soft_limit,
        16 << 20
    );
    assert_eq!(
        global_error("OUTPUT_SOFT_LIMIT = 1023"),
        "PLCComS.ini:2: OUTPUT_SOFT_LIMIT = 1023 is out of range (allowed 1024-1073741824 bytes)"
    );
    assert_eq!(
        global_error("OUTPUT_SOFT_LIMIT = 16777217"),
        "PLCComS.ini:2: OUTPUT_SOFT_LIMIT = 16777217 is above OUTPUT_HARD_LIMIT (16777216 bytes)"
    );
    assert_eq!(
        global_error("OUTPUT_HARD_LIMIT = 8192\nOUTPUT_SOFT_LIMIT = 8193"),
        "PLCComS.ini:3: OUTPUT_SOFT_LIMIT = 8193 is above OUTPUT_HARD_LIMIT (8192 bytes)"
    );
}

type SectionRange = (&'static str, u64, u64, &'static str, fn(&Section) -> u64);

#[test]
fn section_ranges() {
    let ranges: [SectionRange; 5] = [
        ("EPSADDR", 1, 126, "", |s| u64::from(s.epsaddr.unwrap())),
        ("EPSTOUT", 1, 15000, " ms", |s| s.epstout.as_millis() as u64),
        ("EPSTOUT_STEP", 0, 5000, " ms", |s| {
            s.epstout_step.as_millis() as u64
        }),
        ("EPSPORT", 1, 65535, "", |s| u64::from(s.epsport)),
        ("SERVER_PORT", 1, 65535, "", |s| u64::from(s.server_port)),
    ];
    for (key, min, max, unit, read) in ranges {
        let port = if key == "SERVER_PORT" {
            ""
        } else {
            "SERVER_PORT = 5010\n"
        };
        for value in [min, max] {
            let s = section(&format!("{port}{key} = {value}"));
            assert_eq!(read(&s), value, "{key}");
        }
        let line = if port.is_empty() { 3 } else { 4 };
        range_errors(key, (min, max, unit), line, |text| {
            section_error(&format!("{port}{text}"))
        });
    }
    let s = section(
        "SERVER_PORT = 1\nSERIAL_SPEED = 115200\nSERIAL_RTS = 17\nSHM_SOCKET = 0\nSHM_PORT = 5",
    );
    assert_eq!(
        (s.serial_speed, s.serial_rts, s.shm_socket, s.shm_port),
        (Some(115200), Some(17), Some(0), Some(5))
    );
    assert_eq!(
        section_error("SERVER_PORT = 1\nSERIAL_SPEED = 0"),
        "PLCComS.ini:4: SERIAL_SPEED = 0 is out of range (allowed 1-4294967295 baud)"
    );
    assert_eq!(
        section_error("SERVER_PORT = 1\nSHM_PORT = 4294967296"),
        "PLCComS.ini:4: SHM_PORT = 4294967296 is out of range (allowed 0-4294967295)"
    );
}

#[test]
fn server_port_is_required() {
    assert_eq!(
        section_error("IPADDR = 10.0.0.1"),
        "PLCComS.ini:2: section [PLC] has no SERVER_PORT (required, allowed 1-65535)"
    );
}

#[test]
fn ip_addresses() {
    let s = section("SERVER_PORT = 1\nIPADDR = 192.168.001.010\nIPADDR_LOCAL = 010.0.0.1");
    assert_eq!(s.ipaddr, Some(Ipv4Addr::new(192, 168, 1, 10)));
    assert_eq!(s.ipaddr_local, Some(Ipv4Addr::new(10, 0, 0, 1)));
    assert_eq!(
        section("SERVER_PORT = 1\nIPADDR = 0.0.0.0").ipaddr,
        Some(Ipv4Addr::UNSPECIFIED)
    );
    for bad in [
        "192.168.1",
        "192.168.1.256",
        "1.2.3.4.5",
        "1..2.3",
        "a.b.c.d",
        "0001.2.3.4",
        "1.2.3.4 5",
    ] {
        assert_eq!(
            section_error(&format!("SERVER_PORT = 1\nIPADDR = {bad}")),
            format!("PLCComS.ini:4: IPADDR = {bad} is not an IPv4 address (allowed a.b.c.d, each part 0-255)")
        );
    }
}

#[test]
fn booleans() {
    for (text, value) in [
        ("Yes", true),
        ("YES", true),
        ("yes", true),
        ("yEs", true),
        ("true", true),
        ("TRUE", true),
        ("1", true),
        ("On", true),
        ("No", false),
        ("NO", false),
        ("no", false),
        ("False", false),
        ("0", false),
        ("off", false),
    ] {
        let g = global(&format!("SCIENT_NOTATION = {text}\nEND_LINE_CRLF = {text}"));
        assert_eq!(
            (g.scient_notation, g.end_line_crlf),
            (value, value),
            "{text}"
        );
        let s = section(&format!(
            "SERVER_PORT = 1\nPUBFILE_CRC = {text}\nPUBFILE_WRITE = {text}"
        ));
        assert_eq!((s.pubfile_crc, s.pubfile_write), (value, value), "{text}");
    }
    assert_eq!(
        global_error("MEM_USE_THREADS = maybe"),
        "PLCComS.ini:2: MEM_USE_THREADS = maybe is not Yes or No (allowed Yes/No, True/False, On/Off, 1/0)"
    );
    assert_eq!(
        section_error("SERVER_PORT = 1\nPUBFILE_CRC = 2"),
        "PLCComS.ini:4: PUBFILE_CRC = 2 is not Yes or No (allowed Yes/No, True/False, On/Off, 1/0)"
    );
}

#[test]
fn comments_and_quotes() {
    let g = global(concat!(
        "SERIAL_DEVICE_CFG   = \"/dev/ttyS0 -1, /dev/ttyS1 -1\"  # (Device_name RTS_gpio_pin_number)\n",
        "COMM_LOOP_DELAY = 20 ; semicolon comment\n",
    ));
    assert_eq!(
        g.serial_device_cfg,
        serial::parse_device_cfg("/dev/ttyS0 -1, /dev/ttyS1 -1").ok()
    );
    assert_eq!(g.comm_loop_delay, Duration::from_millis(20));

    let s = section(concat!(
        "SERVER_PORT = 1 # the port\n",
        "PUBFILE = \"//dir with spaces/a#b;c.pub\" ; comment\n",
        "PUBFILE_FIXED = 'FIXED # Foxtrot.pub'\n",
        "SHM_NAME = C:\\PLC\\ShmSrv.dll\n",
        "SERIAL_DEVICE = C:\\dev\\\n",
    ));
    assert_eq!(s.pubfile.as_deref(), Some("//dir with spaces/a#b;c.pub"));
    assert_eq!(s.pubfile_fixed.as_deref(), Some("FIXED # Foxtrot.pub"));
    assert_eq!(s.shm_name.as_deref(), Some("C:\\PLC\\ShmSrv.dll"));
    assert_eq!(s.serial_device.as_deref(), Some("C:\\dev\\"));
    assert_eq!(
        section_error("SERVER_PORT = 1\nIPADDR = 10.0.0.1#x"),
        "PLCComS.ini:4: IPADDR = 10.0.0.1#x is not an IPv4 address (allowed a.b.c.d, each part 0-255)"
    );
}

#[test]
fn unterminated_quote() {
    assert_eq!(
        global_error("SERIAL_DEVICE_CFG = \"/dev/ttyS0 -1"),
        "PLCComS.ini:2: SERIAL_DEVICE_CFG: unterminated \" quote in value"
    );
    assert_eq!(
        global_error("SERIAL_DEVICE_CFG = /dev/ttyS0 -1, /dev/ttyS1"),
        "PLCComS.ini:2: SERIAL_DEVICE_CFG: '/dev/ttyS1' is not DEVICE PIN (e.g. /dev/ttyS0 -1)"
    );
}

#[test]
fn sections_with_spaces_and_case_insensitive_keys() {
    let loaded = ok("[*]\ncomm_loop_delay = 7\n[TC700 RS232]\nserver_port = 5013\nSerial_Device = /dev/ttyS0\n  [ Indented ]  # comment\n\tServer_Port\t=\t5014\t\n");
    assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
    assert_eq!(
        loaded.config.global.comm_loop_delay,
        Duration::from_millis(7)
    );
    let s = &loaded.config.sections;
    assert_eq!(
        (s[0].name.as_str(), s[0].server_port),
        ("TC700 RS232", 5013)
    );
    assert_eq!(s[0].serial_device.as_deref(), Some("/dev/ttyS0"));
    assert_eq!((s[1].name.as_str(), s[1].server_port), ("Indented", 5014));
}

#[test]
fn unknown_and_misplaced_keys_are_warnings() {
    let loaded = ok(
        "[*]\nFOO = 1\nSERVER_PORT = 1\n[PLC]\nSERVER_PORT = 5010\nBAR = x\nNUM_OF_DECIMALS = 3\n",
    );
    assert_eq!(
        messages(&loaded),
        [
            "PLCComS.ini:2: FOO = 1 is an unknown key in section [*]; ignored",
            "PLCComS.ini:3: SERVER_PORT does not belong in section [*]; ignored",
            "PLCComS.ini:6: BAR = x is an unknown key in section [PLC]; ignored",
            "PLCComS.ini:7: NUM_OF_DECIMALS does not belong in section [PLC]; ignored",
        ]
    );
    assert!(all_are(&loaded, Severity::Warning));
    assert_eq!(loaded.config.sections.len(), 1);
}

#[test]
fn duplicate_keys_keep_the_later_value() {
    let loaded = ok("[*]\nCOMM_LOOP_DELAY = 5\ncomm_loop_delay = 6\n[PLC]\nSERVER_PORT = 5010\n");
    assert_eq!(
        loaded.config.global.comm_loop_delay,
        Duration::from_millis(6)
    );
    assert_eq!(
        messages(&loaded),
        ["PLCComS.ini:3: COMM_LOOP_DELAY is given twice (first on line 2); this value counts"]
    );
}

#[test]
fn a_bad_plc_section_is_skipped_and_the_others_load() {
    let text = "[*]\n[A]\nSERVER_PORT = 5010\n[B]\nSERVER_PORT = 5011\nEPSTOUT = 0\n[C]\nSERVER_PORT = 5012\n";
    let loaded = ok(text);
    let names = section_names(&loaded);
    assert_eq!(names, ["A", "C"]);
    assert_eq!(
        messages(&loaded),
        [
            "PLCComS.ini:4: section [B] skipped (1 error)",
            "PLCComS.ini:6: EPSTOUT = 0 is out of range (allowed 1-15000 ms)",
        ]
    );
    assert!(all_are(&loaded, Severity::Error));
}

#[test]
fn malformed_lines() {
    assert_eq!(
        global_error("COMM_LOOP_DELAY 100"),
        "PLCComS.ini:2: 'COMM_LOOP_DELAY 100' is neither a [SECTION] header nor KEY = VALUE"
    );
    assert_eq!(
        global_error("= 100"),
        "PLCComS.ini:2: '= 100' has no key before '='"
    );
    assert_eq!(
        global_error("A:B = 1"),
        "PLCComS.ini:2: invalid character ':' in key 'A:B'"
    );
    assert_eq!(
        section_error("SERVER_PORT = 1\nSERIAL_SPEED"),
        "PLCComS.ini:4: 'SERIAL_SPEED' is neither a [SECTION] header nor KEY = VALUE"
    );
    // A broken header keeps its keys: they do not leak into the section above.
    let loaded = ok("[*]\n[A]\nSERVER_PORT = 5010\n[B\nSERVER_PORT = 5011\nEPSTOUT = 9\n");
    assert_eq!(loaded.config.sections.len(), 1);
    assert_eq!(
        loaded.config.sections[0].epstout,
        Duration::from_millis(1000)
    );
    assert_eq!(
        messages(&loaded),
        [
            "PLCComS.ini:4: section [B] skipped (1 error)",
            "PLCComS.ini:4: section header [B has no closing ']'",
        ]
    );
    let loaded = ok("[*]\n[A] junk\nSERVER_PORT = 5010\n[C]\nSERVER_PORT = 5011\n");
    assert_eq!(loaded.config.sections[0].name, "C");
    assert_eq!(
        messages(&loaded)[1],
        "PLCComS.ini:2: unexpected 'junk' after section header [A]"
    );
}

#[test]
fn duplicate_server_port_and_section_name() {
    let loaded =
        ok("[*]\n[A]\nSERVER_PORT = 5010\n[B]\nSERVER_PORT = 5010\n[a]\nSERVER_PORT = 5011\n");
    let names = section_names(&loaded);
    assert_eq!(names, ["A"]);
    assert_eq!(
        messages(&loaded),
        [
            "PLCComS.ini:4: section [B] skipped (1 error)",
            "PLCComS.ini:5: SERVER_PORT = 5010 is already used by section [A] (line 2)",
            "PLCComS.ini:6: section [a] skipped (1 error)",
            "PLCComS.ini:6: duplicate section [a] (the first is on line 2)",
        ]
    );
}

#[test]
fn the_global_section_is_mandatory_and_unique() {
    assert_eq!(
        invalid("[PLC]\nSERVER_PORT = 5010\n"),
        ["PLCComS.ini:1: the mandatory [*] section is missing"]
    );
    assert_eq!(
        invalid("[*]\n[PLC]\nSERVER_PORT = 5010\n[*]\n"),
        ["PLCComS.ini:4: second [*] section (the first is on line 1)"]
    );
    // Junk before any section stops start-up too.
    assert_eq!(
        invalid("junk\n[*]\n[PLC]\nSERVER_PORT = 5010\n"),
        ["PLCComS.ini:1: 'junk' is neither a [SECTION] header nor KEY = VALUE"]
    );
    let loaded = ok("KEY = 1\n[*]\n[PLC]\nSERVER_PORT = 5010\n");
    assert_eq!(
        messages(&loaded),
        ["PLCComS.ini:1: KEY is outside any section; ignored"]
    );
}

#[test]
fn no_plc_section() {
    for text in ["[*]\n", "[*]\n[PLC]\nSERVER_PORT = 0\n"] {
        match parse(Path::new(FILE), text) {
            Err(e @ ConfigError::NoSections { .. }) => assert_eq!(
                e.to_string(),
                "PLCComS.ini: no usable PLC section (at least one section besides [*], with a SERVER_PORT, is needed)"
            ),
            other => panic!("{text}: {other:?}"),
        }
    }
}

#[test]
fn io_error_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("missing.ini");
    let err = load(&path).unwrap_err();
    assert!(matches!(err, ConfigError::Io { .. }));
    assert!(err
        .to_string()
        .starts_with(&format!("cannot read {}: ", path.display())));
}

#[test]
fn allow_and_read_only() {
    let s = section("SERVER_PORT = 5000");
    assert_eq!((s.allow, s.read_only), (None, false));
    let s = section(
        "SERVER_PORT = 5000\nALLOW = 127.0.0.1, 192.168.1.0/24 ,::1,fd00::/8, 10.1.2.3/8\nREAD_ONLY = Yes",
    );
    assert!(s.read_only);
    let allow = s.allow.unwrap();
    let shown: Vec<String> = allow.iter().map(ToString::to_string).collect();
    assert_eq!(
        shown,
        [
            "127.0.0.1/32",
            "192.168.1.0/24",
            "::1/128",
            "fd00::/8",
            "10.0.0.0/8"
        ]
    );
    let ok = |ip: &str| allowed(Some(&allow), ip.parse().unwrap());
    assert!(ok("127.0.0.1"));
    assert!(!ok("127.0.0.2"));
    assert!(ok("192.168.1.200"));
    assert!(!ok("192.168.2.1"));
    assert!(ok("10.255.0.1"));
    assert!(ok("::1"));
    assert!(ok("fd12::5"));
    assert!(!ok("fe80::1"));
    // An IPv4 client on an IPv6 socket.
    assert!(ok("::ffff:192.168.1.7"));
    assert!(!ok("::ffff:8.8.8.8"));
    assert!(allowed(None, "8.8.8.8".parse().unwrap()));
    let any = [Network::parse("0.0.0.0/0").unwrap()];
    assert!(allowed(Some(&any), "8.8.8.8".parse().unwrap()));
    assert!(!allowed(Some(&any), "::2".parse().unwrap()));
    for bad in [
        "10.0.0.0/33",
        "10.0.0/8",
        "host.example",
        "::1/129",
        "1.2.3.4/",
        "1.2.3.4/-1",
        "",
    ] {
        assert_eq!(
            section_error(&format!("SERVER_PORT = 5000\nALLOW = 127.0.0.1,{bad}")),
            format!("PLCComS.ini:4: ALLOW = 127.0.0.1,{bad} has '{bad}', which is not an IPv4 or IPv6 address or network (allowed a.b.c.d, a.b.c.d/n, x:y::z, x:y::/n)"),
        );
    }
    assert_eq!(
        section_error("SERVER_PORT = 5000\nREAD_ONLY = maybe"),
        "PLCComS.ini:4: READ_ONLY = maybe is not Yes or No (allowed Yes/No, True/False, On/Off, 1/0)"
    );
}

#[test]
fn simulator() {
    let s = section("SERVER_PORT = 1\nSIMULATOR = Yes");
    assert_eq!(
        s.simulator,
        Some(Simulator {
            program: "demo".into(),
            pubfile: None
        })
    );
    let s = section(
        "SERVER_PORT = 1\nSIMULATOR = yes\nSIMULATOR_PROGRAM = Idle\nSIMULATOR_PUB = sim/demo.pub",
    );
    assert_eq!(
        s.simulator,
        Some(Simulator {
            program: "idle".into(),
            pubfile: Some("sim/demo.pub".into())
        })
    );
    assert_eq!(
        section_error("SERVER_PORT = 1\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = fast"),
        "PLCComS.ini:5: SIMULATOR_PROGRAM = fast is not a simulator program (allowed demo, idle)"
    );
    let loaded =
        with_section("SERVER_PORT = 1\nIPADDR = 10.0.0.1\nSIMULATOR_PROGRAM = idle").unwrap();
    assert_eq!(loaded.config.sections[0].simulator, None);
    assert_eq!(
        messages(&loaded),
        ["PLCComS.ini:5: SIMULATOR_PROGRAM has no effect without SIMULATOR = Yes"]
    );
}

#[test]
fn crlf_bom_and_non_utf8() {
    let loaded = ok("\u{feff}[*]\r\nCOMM_LOOP_DELAY = 9\r\n[PLC]\r\nSERVER_PORT = 5010\r\n");
    assert_eq!(
        loaded.config.global.comm_loop_delay,
        Duration::from_millis(9)
    );
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cp1250.ini");
    std::fs::write(
        &path,
        b"# koment\xe1\xf8\n[*]\n[Kuchyn\xec]\nSERVER_PORT = 5010\nPUBFILE = a\xec.pub\n",
    )
    .unwrap();
    let loaded = load(&path).unwrap();
    assert_eq!(loaded.config.sections.len(), 1);
    let warnings: Vec<_> = loaded
        .diagnostics
        .iter()
        .map(|d| (d.line, d.severity))
        .collect();
    assert_eq!(warnings, [(3, Severity::Warning), (5, Severity::Warning)]);
}

/// Every diagnostic of a file that loads no PLC section.
fn no_sections(text: &str) -> Vec<String> {
    match parse(Path::new(FILE), text) {
        Err(ConfigError::NoSections { diagnostics, .. }) => {
            diagnostics.iter().map(ToString::to_string).collect()
        }
        other => panic!("{text}: {other:?}"),
    }
}

#[test]
fn a_single_bad_section_reports_every_problem() {
    let text =
        "[*]\n[PLC]\nPUBFILE_CRC = Yse\nEPSADDR = 200\nIPADDR = 192.168.1.300\nSERVER_PRT = 5010\n";
    assert_eq!(
        no_sections(text),
        [
            "PLCComS.ini:2: section [PLC] skipped (4 errors)",
            "PLCComS.ini:2: section [PLC] has no SERVER_PORT (required, allowed 1-65535)",
            "PLCComS.ini:3: PUBFILE_CRC = Yse is not Yes or No (allowed Yes/No, True/False, On/Off, 1/0)",
            "PLCComS.ini:4: EPSADDR = 200 is out of range (allowed 1-126)",
            "PLCComS.ini:5: IPADDR = 192.168.1.300 is not an IPv4 address (allowed a.b.c.d, each part 0-255)",
            "PLCComS.ini:6: SERVER_PRT = 5010 is an unknown key in section [PLC] (did you mean SERVER_PORT?); ignored",
        ]
    );
    assert_eq!(
        no_sections("[*]\n[PLC]\nSERVER_PORT = 0\n"),
        [
            "PLCComS.ini:2: section [PLC] skipped (1 error)",
            "PLCComS.ini:3: SERVER_PORT = 0 is out of range (allowed 1-65535)",
        ]
    );
}

#[test]
fn every_global_error_is_reported() {
    let text = "[*]\nCOMM_LOOP_DELAY = 0\nMEM_USE_THREADS = maybe\nCOMM_LOP_DELAY = 5\nNUM_OF_DECIMALS = 16\n[PLC]\nSERVER_PORT = 5010\nEPSADDR = 0\n";
    let err = parse(Path::new(FILE), text).unwrap_err();
    assert_eq!(
        err.to_string(),
        "PLCComS.ini: the configuration cannot be used (an error in [*] or outside the PLC sections)"
    );
    let all: Vec<_> = err.diagnostics().iter().map(ToString::to_string).collect();
    assert_eq!(
        all,
        [
            "PLCComS.ini:2: COMM_LOOP_DELAY = 0 is out of range (allowed 1-1000 ms)",
            "PLCComS.ini:3: MEM_USE_THREADS = maybe is not Yes or No (allowed Yes/No, True/False, On/Off, 1/0)",
            "PLCComS.ini:4: COMM_LOP_DELAY = 5 is an unknown key in section [*] (did you mean COMM_LOOP_DELAY?); ignored",
            "PLCComS.ini:5: NUM_OF_DECIMALS = 16 is out of range (allowed 0-15)",
            // The PLC sections are read too, so that one run shows everything.
            "PLCComS.ini:6: section [PLC] skipped (1 error)",
            "PLCComS.ini:8: EPSADDR = 0 is out of range (allowed 1-126)",
        ]
    );
    // Malformed lines and a second [*] are reported with the rest.
    assert_eq!(
        invalid("junk\n[*]\nFFILE_TIMEOUT = x\n[PLC]\nSERVER_PORT = 5010\n[*]\n"),
        [
            "PLCComS.ini:1: 'junk' is neither a [SECTION] header nor KEY = VALUE",
            "PLCComS.ini:3: FFILE_TIMEOUT = x is not a number (allowed 0-3600 s)",
            "PLCComS.ini:6: second [*] section (the first is on line 2)",
        ]
    );
}

#[test]
fn unknown_keys_get_the_key_they_are_probably_a_typo_of() {
    let loaded = ok(concat!(
        "[*]\n",
        "COMM_LOP_DELAY = 5\n",
        "SCIENT_NOTATON = Yes\n",
        "END_LINE = Yes\n",
        "SERVER_PORT = 1\n",
        "EPSADR = 1\n",
        "[PLC]\n",
        "SERVER_PORT = 5010\n",
        "PUBFILE_CCR = Yes\n",
        "SIMULATOR_PROG = idle\n",
        "server_prot = 5011\n",
        "NUM_OF_DECIMALS = 3\n",
        "BAR = 1\n",
        "XPUBFILE = a.pub\n",
    ));
    assert_eq!(
        messages(&loaded),
        [
            "PLCComS.ini:2: COMM_LOP_DELAY = 5 is an unknown key in section [*] (did you mean COMM_LOOP_DELAY?); ignored",
            "PLCComS.ini:3: SCIENT_NOTATON = Yes is an unknown key in section [*] (did you mean SCIENT_NOTATION?); ignored",
            "PLCComS.ini:4: END_LINE = Yes is an unknown key in section [*] (did you mean END_LINE_CRLF?); ignored",
            "PLCComS.ini:5: SERVER_PORT does not belong in section [*]; ignored",
            "PLCComS.ini:6: EPSADR = 1 is an unknown key in section [*]; ignored",
            "PLCComS.ini:9: PUBFILE_CCR = Yes is an unknown key in section [PLC] (did you mean PUBFILE_CRC?); ignored",
            "PLCComS.ini:10: SIMULATOR_PROG = idle is an unknown key in section [PLC] (did you mean SIMULATOR_PROGRAM?); ignored",
            "PLCComS.ini:11: SERVER_PROT = 5011 is an unknown key in section [PLC] (did you mean SERVER_PORT?); ignored",
            "PLCComS.ini:12: NUM_OF_DECIMALS does not belong in section [PLC]; ignored",
            "PLCComS.ini:13: BAR = 1 is an unknown key in section [PLC]; ignored",
            "PLCComS.ini:14: XPUBFILE = a.pub is an unknown key in section [PLC] (did you mean PUBFILE?); ignored",
        ]
    );
}

#[test]
fn defaults_come_from_the_table() {
    assert_eq!(global(""), Global::default());
    for key in keys() {
        let Some(default) = key.default else {
            continue;
        };
        assert!(
            key.parse(default).is_ok(),
            "{}: default {default}",
            key.name
        );
        // Writing the default changes nothing.
        match key.scope() {
            Scope::Global => assert_eq!(
                global(&format!("{} = {default}", key.name)),
                Global::default(),
                "{}",
                key.name
            ),
            Scope::Section => assert_eq!(
                section(&format!("{}\n{} = {default}", base(key.name), key.name)),
                section(base(key.name)),
                "{}",
                key.name
            ),
        }
    }
    let mut expected = section_defaults("PLC");
    expected.server_port = 5010;
    assert_eq!(section("SERVER_PORT = 5010"), expected);
    assert_eq!(expected.protocol, Protocol::Epsnet);
}

/// A PLC section body to try a key in: keys of the simulator need it on,
/// Modbus keys a Modbus section (with a tag file, or a simulated device).
fn base(key: &str) -> &'static str {
    if key.starts_with("SIMULATOR_") || key == "PROTOCOL" {
        "SERVER_PORT = 5010\nSIMULATOR = Yes"
    } else if key.starts_with("HISTORY_") {
        "SERVER_PORT = 5010\nHISTORY = *"
    } else if key == "MODBUS_TAGS" {
        "SERVER_PORT = 5010\nPROTOCOL = MODBUS_TCP\nSIMULATOR = Yes"
    } else if key.starts_with("MODBUS_") {
        "SERVER_PORT = 5010\nPROTOCOL = MODBUS_TCP\nMODBUS_TAGS = t.csv"
    } else if key == "S7_TAGS" {
        "SERVER_PORT = 5010\nPROTOCOL = S7\nSIMULATOR = Yes"
    } else if key.starts_with("S7_") {
        "SERVER_PORT = 5010\nPROTOCOL = S7\nS7_TAGS = t.csv"
    } else if key.starts_with("ADS_") {
        "SERVER_PORT = 5010\nPROTOCOL = ADS"
    } else if matches!(
        key,
        "SERIAL_PARITY" | "SERIAL_DATA_BITS" | "SERIAL_STOP_BITS"
    ) {
        "SERVER_PORT = 5010\nPROTOCOL = MODBUS_RTU\nMODBUS_TAGS = t.csv"
    } else if key == "OPCUA_URL" {
        "SERVER_PORT = 5010\nPROTOCOL = OPCUA"
    } else if key.starts_with("OPCUA_") {
        "SERVER_PORT = 5010\nPROTOCOL = OPCUA\nOPCUA_URL = opc.tcp://plc:4840"
    } else {
        "SERVER_PORT = 5010"
    }
}

/// A good value of the key's kind other than its default.
fn sample(key: &Key) -> Option<String> {
    let default = key.default_value();
    // Text keys whose values are checked beyond their kind.
    match key.name {
        "MQTT_URL" => return Some("mqtt://broker.lan".into()),
        "MQTT_DELTA" => return Some("0.5".into()),
        "S7_TSAP" => return Some("0100/0200".into()),
        "ADS_NET_ID" | "ADS_SOURCE_NET_ID" => return Some("5.1.2.3.1.1".into()),
        _ => {}
    }
    Some(match key.kind {
        Kind::Number { min, max, .. } if default == Some(Value::Number(min)) => max.to_string(),
        Kind::Number { min, .. } => min.to_string(),
        Kind::Bool if default == Some(Value::Bool(true)) => "No".into(),
        Kind::Bool => "Yes".into(),
        Kind::Ipv4 => "10.0.0.1".into(),
        Kind::IpAddr => "::1".into(),
        Kind::Text if key.name == "SERIAL_DEVICE_CFG" => "/dev/ttyS0 17".into(),
        Kind::Text | Kind::Path(_) => "x".into(),
        Kind::Networks => "10.0.0.0/8".into(),
        Kind::Choice { choices, .. } => choices
            .iter()
            .find(|c| default != Some(Value::Choice(c)))?
            .to_string(),
        Kind::Choices { choices, .. } => choices[..2].join(", "),
        Kind::Form(form) => form.example().into(),
    })
}

#[test]
fn every_key_sets_its_field() {
    for key in keys() {
        let name = key.name;
        let Some(value) = sample(key) else {
            assert_eq!(name, "PROTOCOL", "no other value to try");
            continue;
        };
        match key.scope() {
            Scope::Global => {
                assert_ne!(
                    global(&format!("{name} = {value}")),
                    Global::default(),
                    "{name}"
                )
            }
            Scope::Section if name == "SERIAL_DEVICE_CFG" => {
                // No effect in a PLC section.
                section(&format!("SERVER_PORT = 5010\n{name} = {value}"));
            }
            Scope::Section if name == "SERVER_PORT" => {
                assert_ne!(section(&format!("{name} = {value}")), section(base(name)))
            }
            Scope::Section => assert_ne!(
                section(&format!("{}\n{name} = {value}", base(name))),
                section(base(name)),
                "{name}"
            ),
        }
    }
    assert_eq!(global_keys().count() + section_keys().count(), keys().len());
}

#[test]
fn protocol() {
    assert_eq!(
        section("SERVER_PORT = 1\nPROTOCOL = epsnet").protocol,
        Protocol::Epsnet
    );
    assert_eq!(
        section("SERVER_PORT = 1\nPROTOCOL = modbus_tcp\nMODBUS_TAGS = t.csv").protocol,
        Protocol::ModbusTcp
    );
    assert_eq!(
        section_error("SERVER_PORT = 1\nPROTOCOL = modbus"),
        "PLCComS.ini:4: PROTOCOL = modbus is not a protocol (allowed EPSNET, MODBUS_TCP, MODBUS_RTU, MODBUS_RTU_TCP, S7, ADS, OPCUA)"
    );
}

#[test]
fn ads_sections_serve_the_symbols_and_check_their_net_ids() {
    let warnings = |body: &str| {
        let loaded = with_section(body).unwrap_or_else(|e| panic!("{body}: {e}"));
        assert_eq!(loaded.config.sections.len(), 1, "{body}");
        messages(&loaded)
    };
    let ads = section("SERVER_PORT = 1\nPROTOCOL = ADS\nADS_NET_ID = 5.1.2.3.1.1");
    assert_eq!(ads.protocol, Protocol::Ads);
    assert_eq!(ads.pubfile.as_deref(), Some(ADS_SYMBOLS));
    assert_eq!(ads.ads.port, 851);
    assert_eq!(ads.ads.tcp_port, 48898);
    assert_eq!(
        section_error("SERVER_PORT = 1\nPROTOCOL = ADS\nADS_NET_ID = 5.1.2.3"),
        "PLCComS.ini:5: ADS_NET_ID: AMS Net ID '5.1.2.3' has 4 parts; expected six (e.g. 5.12.34.56.1.1)"
    );
    assert_eq!(
        warnings("SERVER_PORT = 1\nADS_PORT = 801"),
        ["PLCComS.ini:4: ADS_PORT has no effect without PROTOCOL = ADS"]
    );
    assert_eq!(
        warnings("SERVER_PORT = 1\nPROTOCOL = ADS\nPUBFILE = x.pub"),
        ["PLCComS.ini:5: PUBFILE has no effect with PROTOCOL = ADS (its variables are the PLC's symbols)"]
    );
}

#[test]
fn opcua_client_sections() {
    let opcua = section(
        "SERVER_PORT = 1\nPROTOCOL = opcua\nOPCUA_URL = opc.tcp://plc:4840\nOPCUA_MODE = read",
    );
    assert_eq!(opcua.protocol, Protocol::Opcua);
    assert_eq!(
        opcua.opcua_client.url.as_deref(),
        Some("opc.tcp://plc:4840")
    );
    assert!(!opcua.opcua_client.subscribe);
}

#[test]
fn opcua_keys_where_they_do_nothing_are_warnings() {
    let warnings = |body: &str| {
        let loaded = with_section(body).unwrap_or_else(|e| panic!("{body}: {e}"));
        messages(&loaded)
    };
    assert_eq!(
        warnings("SERVER_PORT = 1\nOPCUA_URL = opc.tcp://plc:4840"),
        ["PLCComS.ini:4: OPCUA_URL has no effect without PROTOCOL = OPCUA"]
    );
    // The OPC UA server's section keys belong to any section.
    assert!(warnings("SERVER_PORT = 1\nOPCUA_WRITE = T*\nOPCUA_PUBLISH = *").is_empty());
    assert_eq!(
        warnings("SERVER_PORT = 1\nPROTOCOL = OPCUA\nPUBFILE = x.pub"),
        [
            "PLCComS.ini:5: PUBFILE has no effect with PROTOCOL = OPCUA (the server is OPCUA_URL, \
          its variables come from OPCUA_BROWSE or OPCUA_TAGS)"
        ]
    );
}

#[test]
fn modbus_keys_where_they_do_nothing_are_warnings() {
    let warnings = |body: &str| {
        let loaded = with_section(body).unwrap_or_else(|e| panic!("{body}: {e}"));
        assert_eq!(loaded.config.sections.len(), 1, "{body}");
        messages(&loaded)
    };
    assert_eq!(
        warnings("SERVER_PORT = 1\nMODBUS_PORT = 1502"),
        ["PLCComS.ini:4: MODBUS_PORT has no effect without PROTOCOL = MODBUS_TCP, MODBUS_RTU or MODBUS_RTU_TCP"]
    );
    assert_eq!(
        warnings("SERVER_PORT = 1\nPROTOCOL = MODBUS_TCP\nMODBUS_TAGS = t.csv\nPUBFILE = x.pub"),
        [
            "PLCComS.ini:6: PUBFILE has no effect with PROTOCOL = MODBUS_TCP \
          (its variables come from MODBUS_TAGS)"
        ]
    );
    assert_eq!(
        warnings("SERVER_PORT = 1\nPROTOCOL = MODBUS_TCP"),
        ["PLCComS.ini:2: section [PLC] has no MODBUS_TAGS: it serves __PLC_RUN and __PF_CRC only"]
    );
}

#[test]
fn modbus_rtu_keys_load_and_warn_elsewhere() {
    let loaded = with_section(
        "SERVER_PORT = 1\nPROTOCOL = modbus_rtu\nSERIAL_DEVICE = /dev/ttyUSB0\nSERIAL_SPEED = 9600\n\
         SERIAL_PARITY = none\nSERIAL_DATA_BITS = 8\nSERIAL_STOP_BITS = 2\nMODBUS_UNIT = 7\nMODBUS_TAGS = t.csv",
    )
    .unwrap();
    assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
    let s = &loaded.config.sections[0];
    assert_eq!(s.protocol, Protocol::ModbusRtu);
    assert_eq!(
        (
            s.serial_parity,
            s.serial_data_bits,
            s.serial_stop_bits,
            s.modbus.unit
        ),
        (Some(super::serial::Parity::None), Some(8), Some(2), 7)
    );
    let loaded = with_section("SERVER_PORT = 1\nSERIAL_PARITY = EVEN").unwrap();
    assert_eq!(
        messages(&loaded),
        ["PLCComS.ini:4: SERIAL_PARITY has no effect without PROTOCOL = MODBUS_RTU (EPSNET's line is 8N1)"]
    );
    assert!(
        with_section("SERVER_PORT = 1\nPROTOCOL = MODBUS_RTU\nSERIAL_PARITY = MARK").is_err()
            || !messages(
                &with_section("SERVER_PORT = 1\nPROTOCOL = MODBUS_RTU\nSERIAL_PARITY = MARK")
                    .unwrap()
            )
            .is_empty()
    );
}

#[test]
fn bool_grammar() {
    for (text, value) in [
        ("yes", true),
        ("YES", true),
        ("True", true),
        ("on", true),
        ("ON", true),
        ("1", true),
        ("no", false),
        ("No", false),
        ("FALSE", false),
        ("off", false),
        ("Off", false),
        ("0", false),
    ] {
        assert_eq!(parse_bool(text), Some(value), "{text}");
    }
    for bad in ["", "y", "n", "2", "yes ", "maybe", "enabled"] {
        assert_eq!(parse_bool(bad), None, "{bad}");
    }
}

#[test]
fn setconf_names() {
    for (name, key, scope) in [
        ("crlf", "END_LINE_CRLF", SetConfScope::Client),
        ("CRLF", "END_LINE_CRLF", SetConfScope::Client),
        ("diff", "DIFF_VAR_ENABLED", SetConfScope::Client),
        ("ipaddr", "IPADDR", SetConfScope::Section),
        ("EpsAddr", "EPSADDR", SetConfScope::Section),
        ("epsport", "EPSPORT", SetConfScope::Section),
        ("serial_device", "SERIAL_DEVICE", SetConfScope::Section),
        ("serial_speed", "SERIAL_SPEED", SetConfScope::Section),
        ("pubfile", "PUBFILE", SetConfScope::Section),
        ("trace", "TRACE", SetConfScope::Section),
    ] {
        let found = setconf_key(name).unwrap_or_else(|| panic!("{name}"));
        assert_eq!(
            (found.name, found.setconf_scope()),
            (key, Some(scope)),
            "{name}"
        );
    }
    for unknown in ["nothing", "END_LINE_CRLF", "pubfile_crc", "server_port", ""] {
        assert!(setconf_key(unknown).is_none(), "{unknown}");
    }
    assert_eq!(
        keys().iter().filter(|k| k.setconf_name().is_some()).count(),
        9
    );
}

#[test]
fn setconf_crlf_and_diff_take_every_boolean_spelling() {
    for name in ["crlf", "diff"] {
        let key = setconf_key(name).unwrap();
        for (yes, no) in [("Yes", "No"), ("True", "False"), ("On", "Off"), ("1", "0")] {
            for (text, value) in [(yes, true), (no, false)] {
                for spelling in [
                    text.to_string(),
                    text.to_ascii_lowercase(),
                    text.to_ascii_uppercase(),
                ] {
                    assert_eq!(parse_bool(&spelling), Some(value), "{name},{spelling}");
                    // The same words as the ini key.
                    assert_eq!(key.parse(&spelling), Ok(Value::Bool(value)));
                }
            }
        }
        // A client setting is not a section's.
        let mut section = plain_section("PLC", 5010);
        assert!(key.apply_setconf(&mut section, "yes").is_err());
        assert_eq!(section, plain_section("PLC", 5010));
    }
}

#[test]
fn setconf_section_keys_parse_as_the_ini_keys() {
    let base = plain_section("PLC", 5010);
    let good: [(&str, &str, Section); 12] = [
        (
            "ipaddr",
            "192.168.1.10",
            Section {
                ipaddr: Some(Ipv4Addr::new(192, 168, 1, 10)),
                ..base.clone()
            },
        ),
        (
            "ipaddr",
            "010.0.0.001",
            Section {
                ipaddr: Some(Ipv4Addr::new(10, 0, 0, 1)),
                ..base.clone()
            },
        ),
        (
            "ipaddr",
            "0.0.0.0",
            Section {
                ipaddr: Some(Ipv4Addr::UNSPECIFIED),
                ..base.clone()
            },
        ),
        (
            "epsaddr",
            "1",
            Section {
                epsaddr: Some(1),
                ..base.clone()
            },
        ),
        (
            "epsaddr",
            "126",
            Section {
                epsaddr: Some(126),
                ..base.clone()
            },
        ),
        (
            "epsport",
            "1",
            Section {
                epsport: 1,
                ..base.clone()
            },
        ),
        (
            "epsport",
            "65535",
            Section {
                epsport: 65535,
                ..base.clone()
            },
        ),
        (
            "serial_device",
            "/dev/ttyS0",
            Section {
                serial_device: Some("/dev/ttyS0".into()),
                ..base.clone()
            },
        ),
        (
            "serial_speed",
            "1",
            Section {
                serial_speed: Some(1),
                ..base.clone()
            },
        ),
        (
            "serial_speed",
            "4294967295",
            Section {
                serial_speed: Some(u32::MAX),
                ..base.clone()
            },
        ),
        (
            "pubfile",
            "//demo.pub",
            Section {
                pubfile: Some("//demo.pub".into()),
                ..base.clone()
            },
        ),
        (
            "pubfile",
            "a b.pub",
            Section {
                pubfile: Some("a b.pub".into()),
                ..base.clone()
            },
        ),
    ];
    for (name, value, expected) in good {
        let mut section = base.clone();
        let key = setconf_key(name).unwrap();
        assert_eq!(
            key.apply_setconf(&mut section, value),
            Ok(()),
            "{name},{value}"
        );
        assert_eq!(section, expected, "{name},{value}");
    }
    let bad = [
        (
            "ipaddr",
            "192.168.1.300",
            "is not an IPv4 address (allowed a.b.c.d, each part 0-255)",
        ),
        (
            "ipaddr",
            "1.2.3",
            "is not an IPv4 address (allowed a.b.c.d, each part 0-255)",
        ),
        (
            "ipaddr",
            "",
            "is not an IPv4 address (allowed a.b.c.d, each part 0-255)",
        ),
        ("epsaddr", "0", "is out of range (allowed 1-126)"),
        ("epsaddr", "127", "is out of range (allowed 1-126)"),
        ("epsaddr", "x", "is not a number (allowed 1-126)"),
        ("epsport", "0", "is out of range (allowed 1-65535)"),
        ("epsport", "65536", "is out of range (allowed 1-65535)"),
        ("epsport", "+5", "is not a number (allowed 1-65535)"),
        (
            "serial_device",
            "",
            "is empty (allowed a file or folder name)",
        ),
        (
            "serial_speed",
            "0",
            "is out of range (allowed 1-4294967295 baud)",
        ),
        (
            "serial_speed",
            "4294967296",
            "is out of range (allowed 1-4294967295 baud)",
        ),
        (
            "serial_speed",
            "fast",
            "is not a number (allowed 1-4294967295 baud)",
        ),
        ("pubfile", "", "is empty (allowed a file or folder name)"),
    ];
    for (name, value, problem) in bad {
        let mut section = base.clone();
        assert_eq!(
            setconf_key(name)
                .unwrap()
                .apply_setconf(&mut section, value),
            Err(format!("{name} = {value} {problem}")),
        );
        assert_eq!(section, base, "{name},{value}: changed");
    }
}

/// The keys `PLCComS.ini.example` writes or documents: `KEY =` at the start
/// of a line, possibly after `#`.
fn example_keys(text: &str) -> std::collections::BTreeSet<&str> {
    text.lines()
        .filter_map(|line| {
            let line = line.strip_prefix('#').unwrap_or(line);
            let end = line
                .find(|c: char| !(c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_'))
                .unwrap_or(line.len());
            let (key, rest) = line.split_at(end);
            (!key.is_empty() && rest.trim_start().starts_with('=')).then_some(key)
        })
        .collect()
}

#[test]
fn the_example_documents_every_key() {
    let text = include_str!("../../../PLCComS.ini.example");
    let documented = example_keys(text);
    let table: std::collections::BTreeSet<&str> = keys().iter().map(|k| k.name).collect();
    let missing: Vec<_> = table.difference(&documented).collect();
    assert!(
        missing.is_empty(),
        "not in PLCComS.ini.example: {missing:?}"
    );
    let unknown: Vec<_> = documented.difference(&table).collect();
    assert!(unknown.is_empty(), "not in the table of keys: {unknown:?}");
    // And it loads cleanly: it is the built-in configuration.
    let loaded = ok(text);
    assert!(loaded.diagnostics.is_empty(), "{:?}", messages(&loaded));
}

/// A key that names a file or folder must be a `Kind::Path` row, so that the
/// server guards the file from clients (`Config::own_paths`). Every text key
/// is either listed here as not a path, or fails this test until it is
/// classified.
#[test]
fn every_key_naming_a_file_is_a_path_key() {
    const NOT_PATHS: &[&str] = &[
        "SERIAL_DEVICE_CFG", // devices and pins, each device also SERIAL_DEVICE
        "HTTP_TOKEN",
        "HTTP_HOSTS",
        "MQTT_URL",
        "MQTT_USER",
        "MQTT_PASSWORD",
        "MQTT_CLIENT_ID",
        "MQTT_PREFIX",
        "HISTORY_TRIGGER",
        "MQTT_PUBLISH",
        "MQTT_WRITE",
        "MQTT_DELTA",
        "SPARKPLUG_NODE",
        "SPARKPLUG_GROUP",
        "SPARKPLUG_HOST",
        "OPCUA_HOST",
        "OPCUA_PUBLISH",
        "OPCUA_WRITE",
        "S7_TSAP",
        "ADS_NET_ID",
        "ADS_SOURCE_NET_ID",
        "ADS_NOTIFY",
        "OPCUA_URL",
        "OPCUA_SECURITY",
        "OPCUA_USER",
        "OPCUA_PASSWORD",
        "OPCUA_BROWSE",
    ];
    for key in keys() {
        if key.kind == Kind::Text {
            assert!(
                NOT_PATHS.contains(&key.name),
                "{} is a text key: make it Kind::Path if it names a file or folder, else list it here",
                key.name
            );
        }
    }
}

#[test]
fn own_paths_resolve_as_their_consumers_do() {
    let ini = "[*]\nHTTP_KEY = tls/key.pem\nMQTT_PASSWORD_FILE = /etc/secret/mqtt.pass\nFILES_ROOT = files\n\
               [P]\nSERVER_PORT = 5010\nPUBFILE = //user.pub\nPUBFILE_WRITE = Yes\nSHM_NAME = ./libplant.so\n";
    let config = parse(Path::new("/etc/plccoms/PLCComS.ini"), ini)
        .unwrap()
        .config;
    let own = config.own_paths();
    let find = |key: &str| {
        own.iter()
            .find(|o| o.key == key)
            .unwrap_or_else(|| panic!("{key} not among {own:?}"))
    };
    assert_eq!(find("HTTP_KEY").path, Path::new("/etc/plccoms/tls/key.pem"));
    assert_eq!(find("HTTP_KEY").used, PathUse::Secret);
    assert_eq!(
        find("MQTT_PASSWORD_FILE").path,
        Path::new("/etc/secret/mqtt.pass")
    );
    assert_eq!(find("PUBFILE").path, Path::new("/etc/plccoms/P/user.pub"));
    assert_eq!(find("PUBFILE").section.as_deref(), Some("P"));
    assert_eq!(
        find("SHM_NAME").path,
        Path::new("/etc/plccoms/./libplant.so")
    );
    // Defaults count: the queue folder and the history folder.
    assert_eq!(
        find("MQTT_SPOOL").path,
        Path::new("/etc/plccoms/mqtt-spool")
    );
    assert_eq!(find("MQTT_SPOOL").used, PathUse::State);
    assert_eq!(find("HISTORY_DIR").path, Path::new("/etc/plccoms/history"));
    // The clients' own folder is theirs.
    assert!(own.iter().all(|o| o.key != "FILES_ROOT"));
}

#[test]
fn mqtt_url_is_parsed_once_at_load() {
    assert_eq!(
        global("MQTT_URL = mqtts://b.lan:8884").mqtt.url,
        Some(vec![BrokerUrl {
            host: "b.lan".into(),
            port: 8884,
            tls: true
        }])
    );
    assert_eq!(
        global("MQTT_URL = mqtt://a, mqtt://b:1884")
            .mqtt
            .url
            .map(|list| list.len()),
        Some(2)
    );
    assert_eq!(
        global_error("MQTT_URL = mqtt://a, tcp//b"),
        "PLCComS.ini:2: MQTT_URL = mqtt://a, tcp//b (URL 2 of 2, tcp//b) is not a URL (mqtt://host:port or mqtts://host:port)"
    );
    assert_eq!(
        global_error("MQTT_URL = http://b"),
        "PLCComS.ini:2: MQTT_URL = http://b has scheme 'http' (allowed mqtt, mqtts)"
    );
}

#[test]
fn s7_keys() {
    let warnings = |body: &str| {
        let loaded = with_section(body).unwrap_or_else(|e| panic!("{body}: {e}"));
        messages(&loaded)
    };
    let s = section("SERVER_PORT = 1\nPROTOCOL = S7\nS7_TAGS = t.csv\nS7_TSAP = 01.00/02.00");
    assert_eq!(s.s7.tsap, Some((0x0100, 0x0200)));
    assert_eq!(
        (s.s7.port, s.s7.rack, s.s7.slot, s.s7.pdu),
        (102, 0, 1, 960)
    );
    let e = section_error("SERVER_PORT = 1\nPROTOCOL = S7\nS7_TAGS = t.csv\nS7_TSAP = 100/200");
    assert!(
        e.contains("S7_TSAP = 100/200 is not local/remote TSAP in hex (e.g. 0100/0200)"),
        "{e}"
    );
    assert_eq!(
        warnings("SERVER_PORT = 1\nS7_PDU = 480"),
        ["PLCComS.ini:4: S7_PDU has no effect without PROTOCOL = S7"]
    );
    assert_eq!(
        warnings("SERVER_PORT = 1\nPROTOCOL = S7"),
        ["PLCComS.ini:2: section [PLC] has no S7_TAGS: it serves __PLC_RUN and __PF_CRC only"]
    );
}
