//! plccoms: an open drop-in replacement for PLCComS, the communication server
//! of Tecomat PLCs.
//!
//! Layout: `config` and `pubfile` read the files; `vars` is a section's
//! variable table; `backend` is the one interface to a PLC (and `plc` the
//! device model the in-process backend uses); `poller` reads the PLC and
//! serves direct requests; `fanout` publishes what it read; `session` serves a
//! client and `cmd` holds one module per protocol command; `server` listens.

pub mod backend;
pub mod cli;
pub mod cmd;
pub mod config;
pub mod daemon;
pub mod fanout;
pub mod localfs;
pub mod poller;
pub mod section;
pub mod server;
pub mod session;
pub mod startup;
pub mod vars;
pub mod watch;
