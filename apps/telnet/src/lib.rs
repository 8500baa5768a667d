//! The PLCComS line protocol server: the vendor's telnet face, byte for
//! byte, one TCP port per section.
//!
//! - `server` listens, one port per section; `session` serves one client:
//!   framing, the ordered answer queue and every "wait behind" rule;
//! - `cmd` holds one module per protocol command, all of one shape
//!   (`run(&mut Cx, args, ..) -> Reply`); `client` is one client's view of
//!   the variable table (enabled, hidden, deltas, DIFFs owed).

pub mod client;
pub mod cmd;
pub mod server;
pub mod session;
