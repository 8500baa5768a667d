//! plccoms: an open drop-in replacement for PLCComS, the communication server
//! of Tecomat PLCs, and a gateway around PLCs.
//!
//! Layout, from the wire inwards:
//! - `server` listens, one port per section; `session` serves one client:
//!   framing, the ordered answer queue and every "wait behind" rule;
//! - `cmd` holds one module per protocol command, all of one shape
//!   (`run(&mut Cx, args, ..) -> Reply`); `client` is one client's view of
//!   the variable table (enabled, hidden, deltas, DIFFs owed);
//! - `section` is a running section (live state, clients); `changes` is its
//!   change stream (snapshots, quality, subscriptions for in-process
//!   consumers);
//! - `link` is the task that owns a section's backend: health, poll cycle,
//!   client jobs, SETCONF, file transfers, public-file tables;
//! - `backend` is the one interface to a PLC, chosen by `PROTOCOL`;
//! - `config` reads the INI file, `vars` is a section's variable table;
//! - `web` serves the status page, `/metrics` and the JSON API; `logring`
//!   keeps the last warnings and errors for it.
//! - `mqtt` publishes each section's changes to an MQTT broker and takes
//!   writes back.
//! - `history_source` is recorded history as the apps read it: the
//!   historian implements it, the web page reads it, start-up wires them.
//!
//! The line protocol (`plccoms-protocol`), the PLC model and EPSNET wire
//! format (`plccoms-plc`) and the simulated PLC (`plcsim`) are crates of
//! their own.

pub mod backend;
pub mod changes;
pub mod cli;
pub mod client;
pub mod cmd;
pub mod config;
pub mod daemon;
pub mod demo;
pub mod files_quota;
pub mod historian;
pub mod history_source;
pub mod link;
pub mod localfs;
pub mod logfile;
pub mod logring;
pub mod metrics;
pub mod mqtt;
pub mod ratelimit;
pub mod section;
pub mod server;
pub mod session;
pub mod startup;
pub mod vars;
pub mod watch;
pub mod web;
