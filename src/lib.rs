//! plccoms: an open drop-in replacement for PLCComS, the communication server
//! of Tecomat PLCs, and a gateway around PLCs.
//!
//! This crate is the binary's: command line (`cli`), running detached
//! (`daemon`), the log file (`logfile`), the pid file (`pidfile`), watching the configuration
//! (`watch`), the built-in demo (`demo`) and start-up (`startup`), which
//! wires the south drivers ([`DRIVERS`]) and the north apps to the core. It
//! is the only crate that names concrete drivers and apps; the layers below
//! are crates of their own (see ARCHITECTURE.md):
//! `plccoms-protocol`, `plccoms-plc`, `plccoms-core`, `drivers/*`, `apps/*`.

pub mod cli;
pub mod daemon;
pub mod demo;
pub mod logfile;
pub mod pidfile;
pub mod startup;
pub mod watch;

use plccoms_core::driver::Drivers;

/// The crates whose reports `-v` and `-vv` raise; the libraries under them
/// (tokio's `mio::poll`, hyper, rustls) stay at `info`, so a trace shows
/// the server's work, not the I/O loop's. `tests/layers.rs` checks that
/// every crate of the workspace that runs in the server is listed.
pub const OUR_CRATES: &[&str] = &[
    "plccoms",
    "plccoms_protocol",
    "plccoms_plc",
    "plccoms_core",
    "plccoms_driver_epsnet",
    "plccoms_driver_modbus",
    "plccoms_driver_s7",
    "plccoms_driver_plugin",
    "plccoms_driver_ads",
    "plccoms_driver_opcua",
    "plccoms_telnet",
    "plccoms_historian",
    "plccoms_mqtt",
    "plccoms_web",
    "plccoms_opcua",
    "plcsim",
];

/// Libraries that report what our own crates report once, in our terms:
/// async-opcua's client logs every failed connection attempt (several
/// lines a second while a server is away) and each refused request; the
/// OPC UA driver says what matters once per outage. Shown with `-vv`.
pub const QUIET_CRATES: &[&str] = &["opcua_client", "opcua_core::comms::secure_channel"];

/// The log filter for `level` (`info`, `debug`, `trace`): our crates at
/// that level, every other at `info` ([`QUIET_CRATES`] off but at `trace`);
/// the frame trace always passes (each section decides whether it writes
/// one: `TRACE`, `SETCONF:trace`, `-vv`).
pub fn log_filter(level: &str) -> String {
    let mut filter = String::from("info");
    for name in OUR_CRATES {
        filter.push_str(&format!(",{name}={level}"));
    }
    for name in QUIET_CRATES {
        let quiet = if level == "trace" { "debug" } else { "off" };
        filter.push_str(&format!(",{name}={quiet}"));
    }
    filter.push_str(&format!(",{}=trace", plccoms_core::trace::TARGET));
    filter
}

/// The south drivers of this build: adding a driver is its crate and one
/// line here (and its cargo feature in Cargo.toml).
pub const DRIVERS: Drivers = Drivers(&[
    plccoms_driver_epsnet::DRIVER,
    #[cfg(feature = "modbus")]
    plccoms_driver_modbus::DRIVER,
    #[cfg(feature = "s7")]
    plccoms_driver_s7::DRIVER,
    #[cfg(feature = "plugin")]
    plccoms_driver_plugin::DRIVER,
    #[cfg(feature = "ads")]
    plccoms_driver_ads::DRIVER,
    #[cfg(feature = "opcua-client")]
    plccoms_driver_opcua::DRIVER,
]);
