//! The live state of a section: its settings as SETCONF left them and its
//! link's status. One copy, on a `watch` channel written only by the section's
//! link; GETINFO, ALLOW, READ_ONLY, the listener and the web page read it.

use super::LinkState;
use crate::config;

#[derive(Debug, Clone)]
pub struct SectionState {
    pub config: config::Section,
    pub link: LinkStatus,
    /// The user public file is to be read from the PLC at its first
    /// connection: until that attempt is over, new sessions wait, so that
    /// a client connecting at start-up sees the whole table at once.
    pub table_pending: bool,
}

impl SectionState {
    /// Whether a new session may start serving.
    pub fn ready(&self) -> bool {
        !(self.table_pending && self.link.state == LinkState::Connecting)
    }
}

/// What is known about the link to the PLC.
#[derive(Debug, Clone)]
pub struct LinkStatus {
    pub state: LinkState,
    /// Where the PLC is, for logs and GETINFO (e.g. `127.0.0.1:61682`).
    pub describe: String,
    /// The PLC's identification, once connected.
    pub ident: Option<String>,
    /// The link's own address on the PLC's network (EPSNET source address).
    pub source_address: Option<u8>,
    /// UTC milliseconds of the last change of `state`.
    pub since_ms: i64,
}
