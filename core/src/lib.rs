//! The gateway's core, between the PLC model below and the drivers and apps
//! above: what every driver and every app shares.
//!
//! - `config` reads the INI file into typed values (the key table, each
//!   value parsed once); `vars` is a section's variable table;
//! - `driver` is the one interface to a device (the trait every south
//!   driver implements, its request and answer types) and the list of
//!   drivers the binary registers;
//! - `link` is the task that owns a section's backend: health, poll cycle,
//!   client jobs, SETCONF, file transfers, public-file tables;
//! - `changes` is a section's change stream (snapshots, quality,
//!   subscriptions for in-process consumers);
//! - `section` is a running section: its state, its change stream and the
//!   one write path (`Section::write`) every app goes through;
//! - `history_source` is recorded history as the apps read it (the
//!   historian implements it, the web page reads it, the binary wires them);
//! - `localfs` and `files_quota` are the clients' local files; `metrics`,
//!   `ratelimit` and `logring` serve the apps' reports; `present` is a value
//!   in the user's terms (ISO 8601 times, numbers as numbers) for every face
//!   but the telnet port.

pub mod changes;
pub mod config;
pub mod driver;
pub mod files_quota;
pub mod history_source;
pub mod link;
pub mod localfs;
pub mod logring;
pub mod metrics;
pub mod present;
pub mod ratelimit;
pub mod rs485;
pub mod section;
pub mod sections;
pub mod system_area;
pub mod trace;
pub mod vars;
