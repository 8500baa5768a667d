//! Public files over a PLC's life and SETCONF of section keys, through the
//! real start-up path, EPSNET and the simulated PLC on loopback.

mod common;

use std::time::Duration;

use common::Client;
use plcsim::{SimConfig, SimHandle};

struct Setup {
    server: plccoms::startup::Server,
    sim: SimHandle,
    files: tempfile::TempDir,
    _conf: tempfile::TempDir,
    port: u16,
}

async fn setup() -> Setup {
    let files = tempfile::tempdir().unwrap();
    std::fs::write(files.path().join("demo.pub"), plcsim::DEMO_PUB).unwrap();
    let sim = plcsim::spawn(SimConfig {
        bind: "127.0.0.1:0".parse().unwrap(),
        files: Some(files.path().to_path_buf()),
        program: "idle".parse().unwrap(),
        ..SimConfig::default()
    })
    .await
    .unwrap();
    let epsport = sim.local_addr().port();
    let (server, port, conf) = common::start_on_free_port(|port| {
        format!(
            "[*]\nCOMM_LOOP_DELAY = 20\n[PLC]\nIPADDR = 127.0.0.1\nEPSPORT = {epsport}\nEPSTOUT = 50\nEPSTOUT_STEP = 0\nIPADDR_LOCAL = 127.0.0.1\nSERVER_PORT = {port}\nPUBFILE_CRC = No\nPUBFILE = //demo.pub\n"
        )
    })
    .await;
    Setup {
        server,
        sim,
        files,
        _conf: conf,
        port,
    }
}

impl Setup {
    async fn client(&self) -> Client {
        Client::connect(([127, 0, 0, 1], self.port).into()).await
    }
}

/// Reads lines until one equals `want`, returning those before it.
async fn until(c: &mut Client, want: &str) -> Vec<String> {
    let mut before = Vec::new();
    for _ in 0..1000 {
        let line = String::from_utf8_lossy(&c.line().await).into_owned();
        if line == want {
            return before;
        }
        before.push(line);
    }
    panic!("never got {want:?}; got {before:?}");
}

#[tokio::test(flavor = "multi_thread")]
async fn a_program_change_reloads_the_public_file_and_keeps_client_settings() {
    let s = setup().await;
    let mut c = s.client().await;
    c.ask(
        "EN:counter\n",
        "WARNING:252 Changed active variables in public file: '[3/29]'\r\n",
    )
    .await;
    c.expect(b"DIFF:COUNTER,0\r\n").await;
    c.ask(
        "HIDE:note\n",
        "WARNING:253 Changed hidden variables in public file: '[1]'\r\n",
    )
    .await;
    c.ask(
        "EN:setpoint 5\n",
        "WARNING:252 Changed active variables in public file: '[4/29]'\r\n",
    )
    .await;
    c.expect(b"DIFF:SETPOINT,0.000000\r\n").await;

    // The PLC gets a new program: v_byte is gone, `extra` is new.
    let mut new_pub: Vec<u8> = plcsim::DEMO_PUB
        .split(|&b| b == b'\n')
        .filter(|line| !line.starts_with(b" v_byte ") && !line.starts_with(b";*"))
        .flat_map(|line| line.iter().copied().chain(std::iter::once(b'\n')))
        .collect();
    new_pub.truncate(new_pub.len() - 1);
    new_pub.extend_from_slice(b" extra R B 300 INT PUB_INOUT\r\n");
    let crc = plccoms_plc::pubfile::crc_of(&new_pub);
    new_pub.extend_from_slice(format!(";* Crc=\"{crc:08X}\"\r\n").as_bytes());
    std::fs::write(s.files.path().join("demo.pub"), &new_pub).unwrap();
    s.sim.load_pub(&new_pub);

    until(&mut c, "WARNING:250 Changed public file: 'demo.pub'\r\n").await;
    // Settings carried over by name; every enabled variable is sent again.
    c.send(b"LIST:\n").await;
    let list = until(&mut c, "LIST:\r\n").await;
    assert!(
        list.contains(&"LIST:COUNTER,INT\r\n".to_string()),
        "{list:?}"
    );
    assert!(
        list.contains(&"LIST:NOTE,STRING[40]*~\r\n".to_string()),
        "{list:?}"
    );
    assert!(
        list.contains(&"LIST:EXTRA,INT*\r\n".to_string()),
        "{list:?}"
    );
    assert!(
        !list.iter().any(|l| l.starts_with("LIST:V_BYTE")),
        "{list:?}"
    );
    c.ask("SET:extra,7\n", "DIFF:EXTRA,7\r\n").await;
    c.ask(
        "GET:v_byte\n",
        "ERROR:33 Unknown variable name in request: 'GET:v_byte'\r\n",
    )
    .await;
    // The enabled variables are polled through the new table.
    let sim = s.sim.device();
    {
        let mut device = sim.lock().unwrap();
        let id = new_pub.windows(7).position(|w| w == b"counter").unwrap();
        let _ = id;
        let counter = plccoms_plc::pubfile::parse(&new_pub)
            .vars
            .into_iter()
            .map(|def| def.var)
            .find(|v| &*v.name == b"counter")
            .unwrap();
        device
            .write(
                counter.area,
                counter.offset,
                &plccoms_core::driver::WriteData::Bytes(vec![9, 0]),
            )
            .unwrap();
    }
    let lines = until(&mut c, "DIFF:COUNTER,9\r\n").await;
    assert!(lines.iter().all(|l| l.starts_with("DIFF:")), "{lines:?}");
    drop(s.server);
}

#[tokio::test(flavor = "multi_thread")]
async fn setconf_pubfile_and_link_keys() {
    let s = setup().await;
    let mut c = s.client().await;
    let mut other = s.client().await;
    other.ask("GET:counter\n", "GET:COUNTER,0\r\n").await;
    c.ask(
        "SETCONF:pubfile,//demo.pub\n",
        "WARNING:251 Public file not changed: 'demo.pub'\r\n",
    )
    .await;
    other
        .expect(b"WARNING:251 Public file not changed: 'demo.pub'\r\n")
        .await;
    c.ask(
        "SETCONF:pubfile,\n",
        "ERROR:35 Wrong parameter value in request: 'SETCONF:pubfile,'\r\n",
    )
    .await;
    c.ask(
        "SETCONF:epsaddr,127\n",
        "ERROR:35 Wrong parameter value in request: 'SETCONF:epsaddr,127'\r\n",
    )
    .await;
    c.ask(
        "SETCONF:ipaddr,300.1.1.1\n",
        "ERROR:35 Wrong parameter value in request: 'SETCONF:ipaddr,300.1.1.1'\r\n",
    )
    .await;
    c.ask(
        "SETCONF:nothing,1\n",
        "ERROR:50 Unknown name in request: 'SETCONF:nothing,1'\r\n",
    )
    .await;
    // Nothing answers on this loopback address: refused, nothing changed.
    c.ask(
        "SETCONF:ipaddr,127.0.0.2\n",
        "ERROR:10 Unable to connect to PLC.\r\n",
    )
    .await;
    c.ask("GETINFO:ipaddr\n", "GETINFO:IPADDR,127.0.0.1\r\n")
        .await;
    c.ask("GET:counter\n", "GET:COUNTER,0\r\n").await;
    c.ask(
        "SETCONF:ipaddr,127.000.000.001\n",
        "WARNING:251 Public file not changed: 'demo.pub'\r\n",
    )
    .await;
    c.ask("GETINFO:ipaddr\n", "GETINFO:IPADDR,127.0.0.1\r\n")
        .await;
    c.ask(
        "SETCONF:epsaddr,99\n",
        "WARNING:251 Public file not changed: 'demo.pub'\r\n",
    )
    .await;
    c.ask("GETINFO:epsaddr\n", "GETINFO:EPSADDR,99\r\n").await;
    let port = s.sim.local_addr().port();
    c.ask(
        &format!("SETCONF:epsport,{port}\n"),
        "WARNING:251 Public file not changed: 'demo.pub'\r\n",
    )
    .await;
    c.ask("GET:counter\n", "GET:COUNTER,0\r\n").await;
    // The other client heard of each reload, between its answers.
    let mut heard = 0;
    other.send(b"GET:counter\n").await;
    loop {
        let line = other.line().await;
        if line == b"GET:COUNTER,0\r\n" {
            break;
        }
        assert_eq!(line, b"WARNING:251 Public file not changed: 'demo.pub'\r\n");
        heard += 1;
    }
    assert_eq!(heard, 3);
    tokio::time::sleep(Duration::from_millis(10)).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn requests_pipelined_after_setconf_use_the_public_file_it_loads() {
    let s = setup().await;
    let other_pub = common::demo_pub_with_extra();
    std::fs::write(s.files.path().join("other.pub"), &other_pub).unwrap();
    let mut c = s.client().await;
    // One write: the GETs are read while the SETCONF is still under way.
    c.send(b"GET:extra\nSETCONF:pubfile,//other.pub\nGET:extra\nSETCONF:pubfile,//demo.pub\nGET:extra\n")
        .await;
    c.expect(b"ERROR:33 Unknown variable name in request: 'GET:extra'\r\n")
        .await;
    c.expect(b"WARNING:250 Changed public file: 'other.pub'\r\n")
        .await;
    c.expect(b"GET:EXTRA,0\r\n").await;
    c.expect(b"WARNING:250 Changed public file: 'demo.pub'\r\n")
        .await;
    c.expect(b"ERROR:33 Unknown variable name in request: 'GET:extra'\r\n")
        .await;
    c.silent(200).await;
}
