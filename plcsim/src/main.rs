//! plcsim: a simulated Tecomat PLC speaking EPSNET over UDP or a serial line.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::Parser;
use plcsim::{program::ProgramKind, PubSource, SimConfig};

/// A simulated Tecomat PLC that speaks EPSNET over UDP or a serial line, for
/// testing plccoms (or the vendor's server) without hardware.
///
/// It serves a memory image laid out by a public file, runs a PLC program on
/// it every cycle (the user manual's demo program by default), serves a
/// directory as the PLC's file system, and can drop or delay packets and go
/// HALT on request. Service codes other than SETTID are this project's own,
/// unverified against a real PLC.
#[derive(Debug, Parser)]
#[command(name = "plcsim", version, after_help = CONTROL_HELP)]
struct Args {
    /// UDP address to listen on.
    #[arg(long, default_value = "127.0.0.1:61682", value_name = "ADDR:PORT")]
    bind: SocketAddr,

    /// User public file (variables, their addresses and types; its CRC
    /// becomes __PF_CRC). Default: the built-in demo file (conf/demo.pub).
    #[arg(long = "pub", value_name = "FILE")]
    pubfile: Option<PathBuf>,

    /// Fixed public file; checked to place __PLC_RUN at S2.2 and __PF_CRC at S70.
    #[arg(long, value_name = "FILE")]
    fixed: Option<PathBuf>,

    /// Directory served as the PLC's file system (paths confined to it).
    /// Without it, file services answer "service not activated".
    #[arg(long, value_name = "DIR")]
    files: Option<PathBuf>,

    /// PLC program: `demo` (manual chapter 6.1: dat, tim, c, sinus, cosinus,
    /// positive, text) or `idle` (none).
    #[arg(long, default_value = "demo", value_name = "demo|idle")]
    program: ProgramKind,

    /// Make every variable matching MASK change every cycle (`*` wildcard,
    /// case-insensitive; repeatable): integers ramp, reals follow a sine,
    /// BOOLs toggle, STRINGs count, times advance.
    #[arg(long, value_name = "MASK")]
    animate: Vec<String>,

    /// Fraction of incoming packets to drop (0.0 - 1.0).
    #[arg(long, default_value_t = 0.0, value_name = "FRACTION", value_parser = parse_fraction)]
    loss: f64,

    /// Delay every answer by this many milliseconds.
    #[arg(long, default_value_t = 0, value_name = "MS")]
    latency: u64,

    /// Loopback TCP address for run-time control (see below).
    #[arg(long, value_name = "ADDR:PORT")]
    control: Option<SocketAddr>,

    /// PLC cycle in milliseconds.
    #[arg(long, default_value_t = 10, value_name = "MS", value_parser = clap::value_parser!(u64).range(1..=60000))]
    cycle: u64,

    /// Identification string the PLC reports.
    #[arg(long, value_name = "TEXT")]
    ident: Option<String>,

    /// Serve EPSNET on this serial device (a port, or one end of a pty pair:
    /// `socat -d -d pty,raw,echo=0,link=/tmp/plc pty,raw,echo=0,link=/tmp/srv`)
    /// instead of UDP. `--loss` then damages that fraction of the exchanges
    /// (answer lost, cut short, corrupted, or after noise).
    #[arg(long, value_name = "DEVICE")]
    serial: Option<String>,

    /// Serial line speed, baud (8N1, no flow control).
    #[arg(
        long,
        default_value_t = 115_200,
        value_name = "BAUD",
        requires = "serial"
    )]
    speed: u32,

    /// Hold each answer back for the time the request and the answer take on
    /// a real line at --speed (a pty passes bytes at memory speed).
    #[arg(long, requires = "serial")]
    emulate_line: bool,
}

const CONTROL_HELP: &str = "\
Control port commands (one a line, answered OK or ERR <why>):
  loss <fraction>     drop this fraction of incoming packets
  latency <ms>        delay answers
  halt | run          switch the PLC to HALT or RUN (__PLC_RUN)
  pub <file>          load another public file (new program, new __PF_CRC)
  program demo|idle   switch the PLC program
  animate <mask>...   animate these variables (none: stop)
  status              show state";

fn parse_fraction(text: &str) -> Result<f64, String> {
    let value: f64 = text
        .parse()
        .map_err(|_| format!("'{text}' is not a number"))?;
    if (0.0..=1.0).contains(&value) {
        Ok(value)
    } else {
        Err("must be within 0.0 and 1.0".into())
    }
}

#[tokio::main]
async fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
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
        serial: args.serial.map(|device| plcsim::serial::SerialLine {
            device,
            speed: args.speed,
            emulate: args.emulate_line,
        }),
        ..SimConfig::default()
    };
    let on = match &config.serial {
        Some(line) => format!("serial {} {} 8N1", line.device, line.speed),
        None => format!("udp://{}", config.bind),
    };
    if let Some(path) = args.pubfile {
        config.pubfile = PubSource::Path(path);
    }
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
    let on = if on.starts_with("udp") {
        format!("udp://{}", handle.local_addr())
    } else {
        on
    };
    tracing::info!(
        "plcsim: EPSNET on {on} (__PF_CRC {:08X}){}",
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
