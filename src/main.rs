//! `plccoms [-dtvh] [-c <config>] [-l <log>]`

use std::io::IsTerminal;
use std::path::Path;
use std::process::ExitCode;
use std::sync::Arc;

use clap::Parser;
use plccoms::cli::Cli;
use plccoms::daemon::{self, Notifier};
use plccoms::logfile::{self, LogFile};
use plccoms::watch;
use plccoms_core::config::{self, Diagnostic, Severity};
use tokio::signal::unix::{signal, Signal, SignalKind};
use tracing::{error, info, warn};

const DEFAULT_CONFIG: &str = "PLCComS.ini";

/// glibc's allocator, set for a long-running server (each setting only
/// where its environment variable, or GLIBC_TUNABLES, does not set it):
///
/// - threads that meet in malloc get arenas of their own, up to 8 per
///   core, and each arena keeps what was freed in it: the change stream,
///   the OPC UA stack and the pollers allocate on many threads, and at
///   100,000 variables the arenas held 10-15 % of the RSS. One arena per
///   core: `bench/opcua/run --soak 1 plccoms` 260-263 -> 250-255 MiB (2
///   cores), the same notifications and latency.
/// - a block of 1 MiB or more is mapped on its own and unmapped when freed.
///   By default glibc raises that threshold to the largest block freed so
///   far, so that a burst's big buffers (an OPC UA publish of 100,000
///   notifications, its decoded lists) are reused from the heap and their
///   pages stay resident between bursts. `bench-opcua --vars 100000
///   --window 20 --against ua --plccoms BIN`, the binary before and after
///   alternating, 3 runs each: client RSS peak 104.8-107.2 -> 95.1-95.9
///   MiB, CPU the same (0.24-0.27 core).
fn tune_malloc() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let tunables = std::env::var("GLIBC_TUNABLES").unwrap_or_default();
        let unset = |variable: &str, tunable: &str| {
            std::env::var_os(variable).is_none() && !tunables.contains(tunable)
        };
        if unset("MALLOC_ARENA_MAX", "glibc.malloc.arena_max") {
            let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
            let arenas = libc::c_int::try_from(cores).unwrap_or(libc::c_int::MAX);
            // SAFETY: mallopt only sets a parameter of the allocator; called
            // before any thread is started.
            unsafe {
                libc::mallopt(libc::M_ARENA_MAX, arenas);
            }
        }
        if unset("MALLOC_MMAP_THRESHOLD_", "glibc.malloc.mmap_threshold") {
            // SAFETY: as above.
            unsafe {
                libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 20);
            }
        }
    }
}

fn main() -> ExitCode {
    tune_malloc();
    let cli = Cli::parse();
    #[cfg(feature = "historian")]
    if let Some(plccoms::cli::Command::History(args)) = &cli.command {
        return plccoms_historian::command::run(&cli.config, args);
    }
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
    let log = match init_logging(&cli) {
        Ok(log) => log,
        Err(message) => {
            eprintln!("plccoms: {message}");
            notifier.fail(&message);
            return ExitCode::FAILURE;
        }
    };
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        // Clients woken by the I/O driver beyond a worker's local queue wait
        // in the global one; the self-tuned interval let busy local clients
        // starve them (1,000 clients: GET p99 50 ms against p50 3 ms). Every
        // 4th task from the global queue keeps them in turn at no cost in
        // throughput (BENCHMARKS.md).
        .global_queue_interval(4)
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
    runtime.block_on(run(cli, notifier, log))
}

/// The log file, if reports go to one (reopened on SIGHUP).
fn init_logging(cli: &Cli) -> Result<Option<Arc<LogFile>>, String> {
    let level = match cli.verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    // -vv: every section's frame trace.
    plccoms_core::trace::trace_all(cli.verbose >= 2);
    use tracing_subscriber::layer::SubscriberExt;
    use tracing_subscriber::util::SubscriberInitExt;
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(plccoms::log_filter(level)));
    // The log, and the last warnings and errors kept for the web page.
    let registry = tracing_subscriber::registry()
        .with(filter)
        .with(plccoms_core::logring::layer());
    let fmt = tracing_subscriber::fmt::layer().with_target(cli.verbose >= 2);
    match cli.log_path() {
        Some(path) => {
            // Clients never write it (WRITEFILE:./PLCComS.log).
            plccoms_core::localfs::protect(&path, false);
            let file = LogFile::open(&path)
                .map_err(|e| format!("cannot open log file {}: {e}", path.display()))?;
            // A plugin that crashes the process says so in the log too.
            #[cfg(feature = "plugin")]
            plccoms_driver_plugin::crash::set_log_fd(std::os::fd::AsRawFd::as_raw_fd(&*file));
            registry
                .with(fmt.with_ansi(false).with_writer(file.clone()))
                .init();
            Ok(Some(file))
        }
        None => {
            // Colour for a person at a terminal; journald, docker and
            // redirection get plain text.
            registry
                .with(
                    fmt.with_ansi(std::io::stderr().is_terminal())
                        .with_writer(std::io::stderr),
                )
                .init();
            Ok(None)
        }
    }
}

/// SIGHUP: re-reads the configuration and applies it section by section; a
/// file with errors is refused whole and the running configuration stays.
async fn reload(path: &Path, embedded: bool, server: &mut plccoms::startup::Server) {
    if embedded {
        info!("SIGHUP: the built-in configuration has no file to re-read");
        return;
    }
    info!("SIGHUP: re-reading {}", path.display());
    let loaded = match config::load(path) {
        Ok(loaded) if !loaded.has_errors() => loaded,
        Ok(loaded) => {
            for diagnostic in &loaded.diagnostics {
                log_diagnostic(diagnostic);
            }
            let errors = loaded
                .diagnostics
                .iter()
                .filter(|d| d.severity == Severity::Error)
                .count();
            error!(
                "SIGHUP: {} not applied: {errors} error(s) above; the running configuration stays",
                path.display()
            );
            return;
        }
        Err(err) => {
            for diagnostic in err.diagnostics() {
                log_diagnostic(diagnostic);
            }
            error!("SIGHUP: {err}; not applied, the running configuration stays");
            return;
        }
    };
    for diagnostic in &loaded.diagnostics {
        log_diagnostic(diagnostic);
    }
    let report = server.reload(loaded).await;
    if !report.global_keys.is_empty() {
        warn!(
            "SIGHUP: [*] {} changed: [*] keys take effect at the next restart; the running values stay",
            report.global_keys.join(", ")
        );
    }
    info!("SIGHUP: configuration reloaded: {report}");
}

fn log_diagnostic(diagnostic: &Diagnostic) {
    match diagnostic.severity {
        Severity::Warning => warn!("{diagnostic}"),
        Severity::Error => error!("{diagnostic}"),
    }
}

/// The streams of SIGTERM and SIGINT, the signals that stop the server.
fn stop_signals() -> Result<(Signal, Signal), String> {
    let listen = |kind, name| signal(kind).map_err(|err| format!("cannot handle {name}: {err}"));
    Ok((
        listen(SignalKind::terminate(), "SIGTERM")?,
        listen(SignalKind::interrupt(), "SIGINT")?,
    ))
}

async fn run(cli: Cli, mut notifier: Notifier, log: Option<Arc<LogFile>>) -> ExitCode {
    // Held (locked) until the server ends; written after -d forked, so it
    // names the server, not the parent that waits for its start.
    let _pid_file = match cli
        .pid_path()
        .map(|path| plccoms::pidfile::PidFile::create(&path))
    {
        Some(Ok(pid_file)) => {
            // Clients never write it (WRITEFILE:./PLCComS.pid).
            plccoms_core::localfs::protect(pid_file.path(), false);
            Some(pid_file)
        }
        Some(Err(message)) => {
            error!("{message}");
            notifier.fail(&message);
            return ExitCode::FAILURE;
        }
        None => None,
    };
    // SIGHUP reopens the log (logrotate) and re-reads the configuration,
    // instead of ending the server.
    let mut hangups = match logfile::reopen_on_hangup(log) {
        Ok(hangups) => hangups,
        Err(err) => {
            let message = format!("cannot handle SIGHUP: {err}");
            error!("{message}");
            notifier.fail(&message);
            return ExitCode::FAILURE;
        }
    };
    let embedded = cli.config == Path::new(DEFAULT_CONFIG) && !cli.config.exists();
    let loaded = if embedded {
        // The built-in demo (plccoms::demo): a simulated PLC, said loudly.
        config::parse(Path::new(plccoms::demo::NAME), plccoms::demo::CONFIG)
            .inspect(|loaded| warn!("{}", plccoms::demo::banner(&loaded.config)))
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
    // Before the sections start: once their ports accept, a SIGTERM or
    // SIGINT must stop the server gracefully, not kill it with the
    // signal's default action.
    let (mut terminate, mut interrupt) = match stop_signals() {
        Ok(signals) => signals,
        Err(message) => {
            error!("{message}");
            notifier.fail(&message);
            return ExitCode::FAILURE;
        }
    };
    let mut server = match plccoms::startup::start(&loaded.config).await {
        Ok(server) => server,
        Err(message) => {
            error!("{message}");
            notifier.fail(&message);
            return ExitCode::FAILURE;
        }
    };
    info!(
        "plccoms {} running, {} section(s), pid {}",
        env!("CARGO_PKG_VERSION"),
        server.sections.len(),
        std::process::id()
    );
    server.written = loaded.written;
    notifier.ready();
    loop {
        let config_changed = async {
            match config_changes.as_mut() {
                Some((_, changes)) => changes.recv().await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            _ = interrupt.recv() => info!("SIGINT: shutting down"),
            _ = terminate.recv() => info!("SIGTERM: shutting down"),
            _ = config_changed => info!("configuration file {} changed: exiting (-t)", cli.config.display()),
            Some(()) = hangups.recv() => {
                reload(&cli.config, embedded, &mut server).await;
                continue;
            }
        }
        break;
    }
    server.shutdown().await;
    info!("stopped");
    ExitCode::SUCCESS
}
