//! `plccoms [-dtvh] [-c <config>] [-l <log>]`

use std::path::Path;
use std::process::ExitCode;

use clap::Parser;
use plccoms::cli::Cli;
use plccoms::config::{self, Severity};
use tracing::{error, info, warn};

/// The configuration used when no file is named and `PLCComS.ini` is absent:
/// one section with a simulated PLC, so the server is useful at once.
const EMBEDDED_CONFIG: &str = include_str!("../PLCComS.ini.example");
const DEFAULT_CONFIG: &str = "PLCComS.ini";

fn main() -> ExitCode {
    let cli = Cli::parse();
    if let Err(message) = init_logging(&cli) {
        eprintln!("plccoms: {message}");
        return ExitCode::FAILURE;
    }
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(runtime) => runtime,
        Err(err) => {
            error!("cannot start the runtime: {err}");
            return ExitCode::FAILURE;
        }
    };
    runtime.block_on(run(cli))
}

fn init_logging(cli: &Cli) -> Result<(), String> {
    let level = match cli.verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_target(cli.verbose >= 2);
    match cli.log_path() {
        Some(path) => {
            let file = std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(&path)
                .map_err(|e| format!("cannot open log file {}: {e}", path.display()))?;
            builder
                .with_ansi(false)
                .with_writer(std::sync::Mutex::new(file))
                .init();
        }
        None => builder.with_writer(std::io::stderr).init(),
    }
    Ok(())
}

async fn run(cli: Cli) -> ExitCode {
    let loaded = if cli.config == Path::new(DEFAULT_CONFIG) && !cli.config.exists() {
        info!("no {DEFAULT_CONFIG} here: using the built-in configuration (a simulated PLC on port 5010)");
        config::parse(Path::new("PLCComS.ini.example (built in)"), EMBEDDED_CONFIG)
    } else {
        config::load(&cli.config)
    };
    let loaded = match loaded {
        Ok(loaded) => loaded,
        Err(err) => {
            error!("{err}");
            return ExitCode::FAILURE;
        }
    };
    for diagnostic in &loaded.diagnostics {
        match diagnostic.severity {
            Severity::Warning => warn!("{diagnostic}"),
            Severity::Error => error!("{diagnostic}"),
        }
    }
    let server = match plccoms::startup::start(&loaded.config).await {
        Ok(server) => server,
        Err(message) => {
            error!("{message}");
            return ExitCode::FAILURE;
        }
    };
    info!(
        "plccoms {} running, {} section(s)",
        env!("CARGO_PKG_VERSION"),
        server.sections.len()
    );
    shutdown_signal().await;
    info!("shutting down");
    drop(server);
    ExitCode::SUCCESS
}

async fn shutdown_signal() {
    let mut terminate = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .expect("SIGTERM handler");
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        _ = terminate.recv() => {}
    }
}
