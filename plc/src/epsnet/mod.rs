//! EPSNET, the protocol Tecomat PLCs speak: frame types ([`frame`]), bytes
//! <-> frames ([`codec`] for UDP datagrams, [`stream`] for serial lines), and
//! requests and answers ([`service`] and [`frame`], the places where choices
//! unverified against a real PLC are made).

pub mod codec;
pub mod frame;
pub mod service;
pub mod stream;

use std::fmt;

/// EPSNET address of the PLC itself (DA of every request).
pub const PLC_EPS_ADDR: u8 = 0;

/// An error byte the PLC answered with (EPSNET's public error codes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Exception {
    UnknownService,
    NotActivated,
    PasswordBlocked,
    NotReady,
    /// Wrong service parameters; also reading past the end of an area.
    BadParameters,
    Other(u8),
}

impl Exception {
    pub fn from_byte(byte: u8) -> Exception {
        match byte {
            0x02 => Exception::UnknownService,
            0x03 => Exception::NotActivated,
            0x04 => Exception::PasswordBlocked,
            0x09 => Exception::NotReady,
            0x0C => Exception::BadParameters,
            other => Exception::Other(other),
        }
    }

    pub fn to_byte(self) -> u8 {
        match self {
            Exception::UnknownService => 0x02,
            Exception::NotActivated => 0x03,
            Exception::PasswordBlocked => 0x04,
            Exception::NotReady => 0x09,
            Exception::BadParameters => 0x0C,
            Exception::Other(byte) => byte,
        }
    }
}

impl fmt::Display for Exception {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Exception::UnknownService => f.write_str("unknown service (0x02)"),
            Exception::NotActivated => f.write_str("service not activated (0x03)"),
            Exception::PasswordBlocked => f.write_str("service blocked by password (0x04)"),
            Exception::NotReady => f.write_str("data not ready (0x09)"),
            Exception::BadParameters => f.write_str("wrong service parameters (0x0C)"),
            Exception::Other(byte) => write!(f, "error byte 0x{byte:02X}"),
        }
    }
}
