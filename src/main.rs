//! `plccoms [-dtvh] [-c <config>] [-l <log>]`

use std::path::Path;
use std::process::ExitCode;

use clap::Parser;
use plccoms::cli::Cli;
use plccoms::config::{self, Diagnostic, Severity};
use plccoms::daemon::{self, Notifier};
use plccoms::watch;
use tracing::{error, info, warn};

/// The configuration used when no file is named and `PLCComS.ini` is absent:
/// one section with a simulated PLC, so the server is useful at once.
const EMBEDDED_CONFIG: &str = include_str!("../PLCComS.ini.example");
const DEFAULT_CONFIG: &str = "PLCComS.ini";

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Detach before any thread exists; the parent exits with the outcome of
    // the child's start-up.
    let mut notifier = if cli.daemon {
        match daemon::detach() {
            Ok(notifier) => notifier,
            Err(message) => {
                eprintln!("plccoms: cannot detach: {message}");
                return ExitCode::FAILURE;
            }
        }
    } else {
        Notifier::none()
    };
    if let Err(message) = init_logging(&cli) {
        eprintln!("plccoms: {message}");
        notifier.fail(&message);
        return ExitCode::FAILURE;
    }
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(runtime) => runtime,
        Err(err) => {
            let message = format!("cannot start the runtime: {err}");
            error!("{message}");
            notifier.fail(&message);
            return ExitCode::FAILURE;
        }
    };
    runtime.block_on(run(cli, notifier))
}

fn init_logging(cli: &Cli) -> Result<(), String> {
    let level = match cli.verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    use tracing_subscriber::layer::SubscriberExt;
    use tracing_subscriber::util::SubscriberInitExt;
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    // The log, and the last warnings and errors kept for the web page.
    let registry = tracing_subscriber::registry()
        .with(filter)
        .with(plccoms::logring::layer());
    let fmt = tracing_subscriber::fmt::layer().with_target(cli.verbose >= 2);
    match cli.log_path() {
        Some(path) => {
            // Clients never write it (WRITEFILE:./PLCComS.log).
            plccoms::localfs::protect(&path, false);
            // Appended, never truncated.
            let file = std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(&path)
                .map_err(|e| format!("cannot open log file {}: {e}", path.display()))?;
            // A plugin that crashes the process says so in the log too.
            plccoms::backend::plugin::crash::set_log_fd(std::os::fd::AsRawFd::as_raw_fd(&file));
            registry
                .with(
                    fmt.with_ansi(false)
                        .with_writer(std::sync::Mutex::new(file)),
                )
                .init();
        }
        None => registry.with(fmt.with_writer(std::io::stderr)).init(),
    }
    Ok(())
}

fn log_diagnostic(diagnostic: &Diagnostic) {
    match diagnostic.severity {
        Severity::Warning => warn!("{diagnostic}"),
        Severity::Error => error!("{diagnostic}"),
    }
}

async fn run(cli: Cli, mut notifier: Notifier) -> ExitCode {
    let embedded = cli.config == Path::new(DEFAULT_CONFIG) && !cli.config.exists();
    let loaded = if embedded {
        info!("no {DEFAULT_CONFIG} here: using the built-in configuration (a simulated PLC on port 5010)");
        config::parse(Path::new("PLCComS.ini.example (built in)"), EMBEDDED_CONFIG)
    } else {
        config::load(&cli.config)
    };
    let loaded = match loaded {
        Ok(loaded) => loaded,
        Err(err) => {
            // Every problem found, one line each, then why start-up stops;
            // the parent of -d prints the same.
            let mut report = String::new();
            for diagnostic in err.diagnostics() {
                log_diagnostic(diagnostic);
                report.push_str(&format!("{diagnostic}\n"));
            }
            error!("{err}");
            report.push_str(&err.to_string());
            notifier.fail(&report);
            return ExitCode::FAILURE;
        }
    };
    for diagnostic in &loaded.diagnostics {
        log_diagnostic(diagnostic);
    }
    // -t: exit when the configuration file changes (watching starts before
    // the sections, so no edit is missed).
    let mut config_changes = None;
    if cli.terminate {
        if embedded {
            warn!("-t: there is no configuration file to watch (built-in configuration)");
        } else {
            match watch::watch_file(&cli.config) {
                Ok(watch) => config_changes = Some(watch),
                Err(err) => {
                    let message = format!("-t: cannot watch {}: {err}", cli.config.display());
                    error!("{message}");
                    notifier.fail(&message);
                    return ExitCode::FAILURE;
                }
            }
        }
    }
    let server = match plccoms::startup::start(&loaded.config).await {
        Ok(server) => server,
        Err(message) => {
            error!("{message}");
            notifier.fail(&message);
            return ExitCode::FAILURE;
        }
    };
    let mut terminate =
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(signal) => signal,
            Err(err) => {
                let message = format!("cannot handle SIGTERM: {err}");
                error!("{message}");
                notifier.fail(&message);
                return ExitCode::FAILURE;
            }
        };
    info!(
        "plccoms {} running, {} section(s)",
        env!("CARGO_PKG_VERSION"),
        server.sections.len()
    );
    notifier.ready();
    let config_changed = async {
        match config_changes.as_mut() {
            Some((_, changes)) => changes.recv().await,
            None => std::future::pending().await,
        }
    };
    tokio::select! {
        _ = tokio::signal::ctrl_c() => info!("SIGINT: shutting down"),
        _ = terminate.recv() => info!("SIGTERM: shutting down"),
        _ = config_changed => info!("configuration file {} changed: exiting (-t)", cli.config.display()),
    }
    server.shutdown().await;
    info!("stopped");
    ExitCode::SUCCESS
}
