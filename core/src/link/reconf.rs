//! SETCONF of a section-wide key: what it changes in the section's settings,
//! and whether the link must be made anew. The link applies the result
//! (reconnect, reload the public file, tell every client).

use crate::config::{Protocol, Section};

/// A section setting changed at run time (SETCONF).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ConfChange {
    IpAddr(std::net::Ipv4Addr),
    EpsAddr(u8),
    EpsPort(u16),
    SerialDevice(String),
    SerialSpeed(u32),
    PubFile(String),
}

impl ConfChange {
    /// As the client's SETCONF names it, for the log; on a section whose
    /// variables come from a tag file `pubfile` names that file, and the log
    /// says so rather than speak of a public file.
    pub fn describe(&self, tag_file: bool) -> String {
        match self {
            ConfChange::IpAddr(ip) => format!("ipaddr,{ip}"),
            ConfChange::EpsAddr(addr) => format!("epsaddr,{addr}"),
            ConfChange::EpsPort(port) => format!("epsport,{port}"),
            ConfChange::SerialDevice(device) => format!("serial_device,{device}"),
            ConfChange::SerialSpeed(speed) => format!("serial_speed,{speed}"),
            ConfChange::PubFile(name) if tag_file => format!("pubfile,{name} (the tag file)"),
            ConfChange::PubFile(name) => format!("pubfile,{name}"),
        }
    }
}

/// `config` with `change` applied, and whether the link changes.
pub fn apply(config: &Section, change: &ConfChange) -> (Section, bool) {
    let mut config = config.clone();
    let relink = match change {
        ConfChange::IpAddr(ip) => {
            config.ipaddr = Some(*ip);
            // A real address replaces the simulated PLC or the serial line.
            config.simulator = None;
            config.serial_device = None;
            true
        }
        ConfChange::EpsAddr(addr) => {
            config.epsaddr = Some(*addr);
            true
        }
        ConfChange::EpsPort(port) => {
            config.epsport = *port;
            true
        }
        ConfChange::SerialDevice(device) => {
            // The section's PLC is now on this line (see the epsnet driver's `open`).
            config.serial_device = Some(device.clone());
            config.simulator = None;
            true
        }
        ConfChange::SerialSpeed(speed) => {
            config.serial_speed = Some(*speed);
            // Kept for a later SETCONF:serial_device on a UDP section.
            config.serial_device.is_some()
        }
        // On a Modbus section it names the tag file, which the backend
        // watches (its CRC is `__PF_CRC`): a new link.
        ConfChange::PubFile(name) if config.protocol.is_modbus() => {
            config.modbus.tags = Some(name.clone());
            true
        }
        ConfChange::PubFile(name) if config.protocol == Protocol::S7 => {
            config.s7.tags = Some(name.clone());
            true
        }
        ConfChange::PubFile(name) => {
            config.pubfile = Some(name.clone());
            false
        }
    };
    (config, relink)
}
