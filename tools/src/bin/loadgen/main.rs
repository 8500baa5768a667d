//! loadgen: a load generator for plccoms (or any PLCComS-compatible server).
//!
//! Scenarios: `get`, `set`, `fanout`, `poll`, `list`, `connect`, `memory`,
//! `startup`, `web`; `genpub` writes the generated projects. Every loop is bounded
//! in count and time and every address must be on 127.0.0.1. Results are
//! printed as `label.metric value` lines, and appended to `--out` for the
//! bench script (bench/run), which turns them into BENCHMARKS.md.

mod fanout;
mod proxy;
mod scenarios;
mod util;
mod web;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(
    name = "loadgen",
    version,
    about = "Load generator and benchmark probes for plccoms"
)]
struct Cli {
    /// Worker threads of the load generator's runtime (default: CPUs).
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    scenario: Scenario,
}

/// Options every scenario takes.
#[derive(Debug, Clone, Args)]
pub struct Common {
    /// The server's client port.
    #[arg(long, default_value = "127.0.0.1:5010")]
    pub addr: SocketAddr,
    /// The server's pid: report its CPU time and RSS (from /proc).
    #[arg(long)]
    pub server_pid: Option<u32>,
    /// Append `label.metric value` lines to this file.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Prefix of the result lines.
    #[arg(long)]
    pub label: Option<String>,
}

#[derive(Debug, Subcommand)]
enum Scenario {
    /// N clients send GET requests in batches of P (like redis-benchmark -P).
    Get(scenarios::GetArgs),
    /// SET -> DIFF round trips while another client keeps every variable polled.
    Set(scenarios::SetArgs),
    /// N clients with EN:* while the PLC animates variables: DIFF latency
    /// after the poll read completes, and every expected DIFF checked.
    Fanout(fanout::FanoutArgs),
    /// The poll cycle seen through the EPSNET relay: requests per cycle
    /// against the minimum, cycle start jitter.
    Poll(scenarios::PollArgs),
    /// LIST of the whole project: time to the terminator.
    List(scenarios::ListArgs),
    /// Connect storms: connect, one request, disconnect.
    Connect(scenarios::ConnectArgs),
    /// Server RSS with active clients, then per extra idle client.
    Memory(scenarios::MemoryArgs),
    /// Start-up: from spawning the server to its port accepting.
    Startup(scenarios::StartupArgs),
    /// Live-value streams on the web page (browsers) while telnet clients
    /// GET at a steady pace: server CPU and GET latency.
    Web(web::WebArgs),
    /// Writes a generated public file.
    Genpub(GenpubArgs),
}

#[derive(Debug, Args)]
struct GenpubArgs {
    /// Variables in the file.
    #[arg(long, default_value_t = 10_000)]
    vars: usize,
    /// Leading UDINT variables ANIM_nnnnn (for plcsim --animate 'ANIM_*').
    #[arg(long, default_value_t = 0)]
    animated: usize,
    /// DINT variables SETV_nnn (SET targets).
    #[arg(long, default_value_t = 0)]
    setvars: usize,
    #[arg(long)]
    out: PathBuf,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let mut builder = tokio::runtime::Builder::new_multi_thread();
    builder.enable_all();
    if let Some(threads) = cli.threads {
        builder.worker_threads(threads.max(1));
    }
    let runtime = match builder.build() {
        Ok(runtime) => runtime,
        Err(e) => {
            eprintln!("loadgen: cannot start the runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    let result = runtime.block_on(async move {
        match cli.scenario {
            Scenario::Get(a) => scenarios::get(a).await,
            Scenario::Set(a) => scenarios::set(a).await,
            Scenario::Fanout(a) => fanout::run(a).await,
            Scenario::Poll(a) => scenarios::poll(a).await,
            Scenario::List(a) => scenarios::list(a).await,
            Scenario::Connect(a) => scenarios::connect(a).await,
            Scenario::Memory(a) => scenarios::memory(a).await,
            Scenario::Startup(a) => scenarios::startup(a).await,
            Scenario::Web(a) => web::run(a).await,
            Scenario::Genpub(a) => {
                let bytes = plcsim::genpub::generate(&plcsim::genpub::Layout {
                    vars: a.vars,
                    animated: a.animated,
                    setvars: a.setvars,
                });
                std::fs::write(&a.out, bytes).map_err(|e| format!("{}: {e}", a.out.display()))
            }
        }
    });
    // Client tasks may still be parked on sockets: do not wait for them.
    runtime.shutdown_background();
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("loadgen: {message}");
            ExitCode::FAILURE
        }
    }
}

/// Refuses anything but loopback targets.
pub fn check_loopback(addr: SocketAddr) -> Result<(), String> {
    if addr.ip().is_loopback() {
        Ok(())
    } else {
        Err(format!("{addr}: only 127.0.0.1 targets are allowed"))
    }
}
