//! The `plcsim` command line (`plcsim --help`); the binary parses it, and
//! the man page and shell completions are generated from it
//! (`cargo run -p plccoms-tools --bin gen-docs`).

use std::net::SocketAddr;
use std::path::PathBuf;

use clap::Parser;

use crate::program::ProgramKind;

/// A simulated Tecomat PLC that speaks EPSNET over UDP or a serial line, for testing plccoms
/// (or the vendor's server) without hardware.
///
/// It serves a memory image laid out by a public file, runs a PLC program on
/// it every cycle (the user manual's demo program by default), serves a
/// directory as the PLC's file system, and can drop or delay packets and go
/// HALT on request. Service codes other than SETTID are this project's own,
/// unverified against a real PLC. With --modbus it is a Modbus TCP device
/// instead, its registers named by a tag file (--tags); with --s7 a Siemens
/// S7 CPU (DB1 and the merkers), its variables named by an S7 tag file.
#[derive(Debug, Parser)]
#[command(name = "plcsim", version, after_help = CONTROL_HELP)]
#[command(group = clap::ArgGroup::new("tcp_device").args(["modbus", "s7"]).multiple(false))]
pub struct Args {
    /// UDP address to listen on.
    #[arg(long, default_value = "127.0.0.1:61682", value_name = "ADDR:PORT")]
    pub bind: SocketAddr,

    /// User public file (variables, their addresses and types; its CRC
    /// becomes __PF_CRC). Default: the built-in demo file (conf/demo.pub).
    /// With --files, the PLC's file system serves it, read-only, at its
    /// root under its own name (as a PLC keeps it with its program).
    #[arg(long = "pub", value_name = "FILE")]
    pub pubfile: Option<PathBuf>,

    /// Fixed public file; checked to place __PLC_RUN at S2.2 and __PF_CRC at S70.
    #[arg(long, value_name = "FILE")]
    pub fixed: Option<PathBuf>,

    /// Directory served as the PLC's file system (paths confined to it).
    /// Without it, file services answer "service not activated".
    #[arg(long, value_name = "DIR")]
    pub files: Option<PathBuf>,

    /// PLC program: `demo` (manual chapter 6.1: dat, tim, c, sinus, cosinus,
    /// positive, text) or `idle` (none).
    #[arg(long, default_value = "demo", value_name = "demo|idle")]
    pub program: ProgramKind,

    /// Make every variable matching MASK change every cycle (`*` wildcard,
    /// case-insensitive; repeatable): integers ramp, reals follow a sine,
    /// BOOLs toggle, STRINGs count, times advance.
    #[arg(long, value_name = "MASK")]
    pub animate: Vec<String>,

    /// Change only this fraction of the animated variables per second, in
    /// turn (0.1 with 100,000 animated: 10,000 changes a second), each to a
    /// value it did not hold before; `status` on the control port counts
    /// them. Without it every animated variable changes every cycle.
    #[arg(long, value_name = "FRACTION", value_parser = parse_fraction, requires = "animate")]
    pub change_rate: Option<f64>,

    /// Serve this many devices from one process, each with its own memory
    /// and program, on consecutive ports from the --bind, --modbus, --s7 or
    /// --ads port (Modbus: the first port also serves device k as unit id
    /// k). The control port's commands apply to all, or with `device <i>`
    /// to one.
    #[arg(long, default_value_t = 1, value_name = "N", value_parser = clap::value_parser!(u16).range(1..), conflicts_with = "serial")]
    pub devices: u16,

    /// Fraction of incoming packets to drop (0.0 - 1.0).
    #[arg(long, default_value_t = 0.0, value_name = "FRACTION", value_parser = parse_fraction)]
    pub loss: f64,

    /// Delay every answer by this many milliseconds.
    #[arg(long, default_value_t = 0, value_name = "MS")]
    pub latency: u64,

    /// Loopback TCP address for run-time control (see below).
    #[arg(long, value_name = "ADDR:PORT")]
    pub control: Option<SocketAddr>,

    /// PLC cycle in milliseconds.
    #[arg(long, default_value_t = 10, value_name = "MS", value_parser = clap::value_parser!(u64).range(1..=60000))]
    pub cycle: u64,

    /// Identification string the PLC reports.
    #[arg(long, value_name = "TEXT")]
    pub ident: Option<String>,

    /// Serve Modbus TCP on this address instead of EPSNET (coils, discrete
    /// inputs, holding and input registers; any unit id).
    #[arg(long, value_name = "ADDR:PORT")]
    pub modbus: Option<SocketAddr>,

    /// Serve S7comm over ISO-on-TCP on this address instead of EPSNET: an
    /// S7 CPU with DB1-DB16 and the merkers (any rack and slot; PDU up to
    /// 960).
    #[arg(long, value_name = "ADDR:PORT", conflicts_with = "modbus")]
    pub s7: Option<SocketAddr>,

    /// Modbus or S7 tag file (CSV) naming the variables the program and
    /// --animate drive. Default: the built-in conf/demo-modbus.csv
    /// (conf/demo-s7.csv with --s7).
    #[arg(
        long,
        value_name = "FILE.csv",
        requires = "tcp_device",
        conflicts_with = "pubfile"
    )]
    pub tags: Option<PathBuf>,

    /// Serve Beckhoff ADS (AMS/TCP, e.g. 127.0.0.1:48898) on this address
    /// instead of EPSNET: the public file's variables as ADS symbols (by
    /// handle, sum commands, device notifications), ADS state RUN/STOP from
    /// HALT/RUN, a new symbol version with each `pub`.
    #[arg(long, value_name = "ADDR:PORT", conflicts_with_all = ["modbus", "serial"])]
    pub ads: Option<SocketAddr>,

    /// Serve EPSNET on this serial device (a port, or one end of a pty pair:
    /// `socat -d -d pty,raw,echo=0,link=/tmp/plc pty,raw,echo=0,link=/tmp/srv`)
    /// instead of UDP. `--loss` then damages that fraction of the exchanges
    /// (answer lost, cut short, corrupted, or after noise).
    #[arg(long, value_name = "DEVICE", conflicts_with_all = ["modbus", "s7"])]
    pub serial: Option<String>,

    /// Serial line speed, baud (8N1, no flow control).
    #[arg(
        long,
        default_value_t = 115_200,
        value_name = "BAUD",
        requires = "serial"
    )]
    pub speed: u32,

    /// Hold each answer back for the time the request and the answer take on
    /// a real line at --speed (a pty passes bytes at memory speed).
    #[arg(long, requires = "serial")]
    pub emulate_line: bool,
}

pub const CONTROL_HELP: &str = "\
Control port commands (one a line, answered OK or ERR <why>):
  loss <fraction>     drop this fraction of incoming packets
  latency <ms>        delay answers
  halt | run          switch the PLC to HALT or RUN (__PLC_RUN)
  pub <file>          load another public file (new program, new __PF_CRC),
                      served under its own name (with --modbus, --s7: a tag file)
  program demo|idle   switch the PLC program
  animate <mask>...   animate these variables (none: stop)
  status              show state (and, over all devices, the changes made)
  device <i> <cmd>    a command for device i (from 0) alone; without it a
                      command applies to every device of --devices";

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
