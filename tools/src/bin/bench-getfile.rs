//! GETFILE throughput and peak memory: a 100 MiB local file, and a 10 MiB
//! PLC file through the EPSNET simulator on loopback. Server, simulator and
//! client run in this process; the peak resident size (VmHWM) therefore
//! covers all three, which only makes it an upper bound for the server.
//!
//! `cargo run --release --bin bench-getfile [-- <local MiB> <plc MiB>]`

use std::io::Write;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use plccoms::startup::start_section;
use plccoms_core::config;
use plccoms_core::vars::VarTable;
use plccoms_driver_epsnet::{EpsnetBackend, EpsnetConfig};
use plccoms_plc::pubfile;
use plccoms_plc::MemoryMap;
use plcsim::{program::ProgramKind, SimConfig};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

const FIXED_PUB: &[u8] =
    b" __PLC_RUN S B 2 .2 BOOL PUB_INOUT\r\n __PF_CRC S B 70 DWORD PUB_INOUT\r\n";
const MIB: usize = 1024 * 1024;

fn vm_kib(key: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with(key))
                .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .unwrap_or(0)
}

/// Writes `mib` MiB of patterned bytes without holding them in memory.
fn make_file(path: &Path, mib: usize) {
    let mut file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let chunk: Vec<u8> = (0..MIB).map(|i| (i * 7 + i / 251) as u8).collect();
    for _ in 0..mib {
        file.write_all(&chunk).unwrap();
    }
    file.flush().unwrap();
}

/// Sends GETFILE and reads the answer to its terminator, checking the
/// framing; returns the data bytes received.
async fn getfile(addr: std::net::SocketAddr, name: &str) -> u64 {
    let mut stream = TcpStream::connect(addr).await.unwrap();
    stream
        .write_all(format!("GETFILE:{name}\n").as_bytes())
        .await
        .unwrap();
    let prefix = format!("GETFILE:{name}[");
    let mut buf = vec![0u8; 256 * 1024];
    let mut pending: Vec<u8> = Vec::new();
    let mut total = 0u64;
    loop {
        // Parse what is buffered: header, n bytes, CRLF.
        while let Some(eq) = pending.iter().position(|&b| b == b'=') {
            let head = &pending[..=eq];
            assert!(
                head.starts_with(prefix.as_bytes()),
                "unexpected answer: {:?}",
                String::from_utf8_lossy(&pending[..pending.len().min(80)])
            );
            let n: usize = std::str::from_utf8(&head[prefix.len()..head.len() - 2])
                .unwrap()
                .parse()
                .unwrap();
            if pending.len() < eq + 1 + n + 2 {
                break;
            }
            pending.drain(..eq + 1 + n + 2);
            if n == 0 {
                return total;
            }
            total += n as u64;
        }
        let got = stream.read(&mut buf).await.unwrap();
        assert!(got > 0, "connection closed");
        pending.extend_from_slice(&buf[..got]);
    }
}

#[tokio::main]
async fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let local_mib = args.first().copied().unwrap_or(100);
    let plc_mib = args.get(1).copied().unwrap_or(10);
    let work = std::env::temp_dir().join(format!("plccoms-bench-{}", std::process::id()));
    let root = work.join("root");
    let plc = work.join("plc");
    std::fs::create_dir_all(&root).unwrap();
    std::fs::create_dir_all(&plc).unwrap();
    make_file(&root.join("big.bin"), local_mib);
    make_file(&plc.join("big.bin"), plc_mib);

    let sim = plcsim::spawn(SimConfig {
        bind: "127.0.0.1:0".parse().unwrap(),
        program: ProgramKind::Idle,
        files: Some(plc.clone()),
        ..SimConfig::default()
    })
    .await
    .unwrap();
    let mut eps = EpsnetConfig::new(sim.local_addr());
    eps.local_ip = "127.0.0.1".parse().unwrap();
    let ini = "[*]\nFFILE_BLKSIZE = 16384\n[Bench]\nSERVER_PORT = 5010\n";
    let loaded = config::parse(Path::new("bench.ini"), ini).unwrap();
    let mut warnings = Vec::new();
    let table = VarTable::build(
        "FIXED.pub",
        &pubfile::parse(FIXED_PUB),
        None,
        &MemoryMap::FOXTROT,
        &mut warnings,
    )
    .unwrap();
    let section = start_section(
        Arc::new(loaded.config.global),
        loaded.config.sections.into_iter().next().unwrap(),
        table,
        Some(Box::new(EpsnetBackend::new(eps))),
        "127.0.0.1:0".parse().unwrap(),
        root.clone(),
        None,
    )
    .await
    .unwrap();
    let addr = section.local_addr;
    // Let the poller connect.
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    println!(
        "baseline: VmRSS {} KiB, VmHWM {} KiB",
        vm_kib("VmRSS:"),
        vm_kib("VmHWM:")
    );

    let start = Instant::now();
    let got = getfile(addr, "./big.bin").await;
    let secs = start.elapsed().as_secs_f64();
    assert_eq!(got, (local_mib * MIB) as u64);
    println!(
        "local {local_mib} MiB: {secs:.3} s, {:.1} MiB/s; VmHWM {} KiB",
        local_mib as f64 / secs,
        vm_kib("VmHWM:")
    );

    let start = Instant::now();
    let got = getfile(addr, "big.bin").await;
    let secs = start.elapsed().as_secs_f64();
    assert_eq!(got, (plc_mib * MIB) as u64);
    println!(
        "PLC (EPSNET simulator) {plc_mib} MiB: {secs:.3} s, {:.2} MiB/s; VmHWM {} KiB",
        plc_mib as f64 / secs,
        vm_kib("VmHWM:")
    );
    drop(section);
    let _ = std::fs::remove_dir_all(&work);
}
