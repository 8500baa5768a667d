//! plcsim: a simulated Tecomat PLC speaking EPSNET over UDP or a serial
//! line, a Modbus TCP device, a Siemens S7 CPU or a Beckhoff ADS device.

use std::time::Duration;

use clap::Parser;
use plcsim::cli::Args;
use plcsim::{PubSource, SimConfig};

#[tokio::main]
async fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        // Colour only for a person at a terminal.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    if let Some(control) = args.control {
        if !control.ip().is_loopback() {
            eprintln!("plcsim: --control must be a loopback address");
            return std::process::ExitCode::from(2);
        }
    }
    let mut config = SimConfig {
        bind: args.bind,
        fixed: args.fixed,
        files: args.files,
        program: args.program,
        animate: args.animate,
        loss: args.loss,
        latency: Duration::from_millis(args.latency),
        cycle: Duration::from_millis(args.cycle),
        control: args.control,
        devices: usize::from(args.devices),
        change_rate: args.change_rate,
        serial: args.serial.map(|device| plcsim::serial::SerialLine {
            device,
            speed: args.speed,
            emulate: args.emulate_line,
        }),
        ..SimConfig::default()
    };
    let line = config
        .serial
        .as_ref()
        .map(|line| format!("EPSNET on serial {} {} 8N1", line.device, line.speed));
    if let Some(path) = args.pubfile {
        config.pubfile = PubSource::Path(path);
    }
    if let Some(addr) = args.modbus {
        config.modbus = Some(addr);
        config.pubfile = match &args.tags {
            Some(path) => PubSource::Path(path.clone()),
            None => PubSource::Bytes(plcsim::DEMO_TAGS.to_vec()),
        };
    }
    if let Some(addr) = args.s7 {
        config.s7 = Some(addr);
        config.pubfile = match &args.tags {
            Some(path) => PubSource::Path(path.clone()),
            None => PubSource::Bytes(plcsim::DEMO_S7_TAGS.to_vec()),
        };
    }
    config.ads = args.ads;
    if let Some(ident) = args.ident {
        config.ident = ident;
    }
    let handle = match plcsim::spawn(config).await {
        Ok(handle) => handle,
        Err(e) => {
            eprintln!("plcsim: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    let addrs = handle.local_addrs();
    let more = match addrs.as_slice() {
        [_] => String::new(),
        [.., last] => format!(" and {} more to port {}", addrs.len() - 1, last.port()),
        [] => String::new(),
    };
    tracing::info!(
        "plcsim: {}{more} (__PF_CRC {:08X}){}",
        match line {
            Some(line) => line,
            None if args.modbus.is_some() => format!("Modbus TCP on tcp://{}", handle.local_addr()),
            None if args.s7.is_some() =>
                format!("S7 (ISO-on-TCP) on tcp://{}", handle.local_addr()),
            None if args.ads.is_some() => format!("ADS on tcp://{}", handle.local_addr()),
            None => format!("EPSNET on udp://{}", handle.local_addr()),
        },
        handle.pf_crc(),
        handle
            .control_addr()
            .map(|a| format!(", control on tcp://{a}"))
            .unwrap_or_default()
    );
    let _ = tokio::signal::ctrl_c().await;
    handle.stop().await;
    std::process::ExitCode::SUCCESS
}
