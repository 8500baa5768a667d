//! Siemens S7 (S7comm over ISO-on-TCP, RFC 1006), as the server's S7
//! backend speaks it: the frames ([`frame`]: TPKT, COTP, S7comm jobs and
//! answers), bytes <-> frames ([`codec`]), how a cycle's blocks become as
//! few requests as the negotiated PDU allows ([`pack`]), the tag file and
//! the TIA Portal / Node-RED address notation ([`tags`]), and how S7's
//! big-endian types become a client's value ([`value`]).
//!
//! Own code rather than a crate: the Rust S7 crates on crates.io are either
//! bindings to the Snap7 C library (a C++ build and a shared library to
//! ship) or synchronous clients without multi-variable reads; the framing is
//! three small headers, and the simulated PLC and the fuzzers need the same
//! frames from the other end.
//!
//! # Layout
//!
//! An S7 section's variables live in the `(area, byte offset)` space every
//! section has, laid out by [`MAP`]:
//!
//! | S7 area | area | byte offset |
//! | --- | --- | --- |
//! | inputs `I`/`E` (0x81) | X | byte |
//! | outputs `Q`/`A` (0x82) | Y | byte |
//! | merkers `M` (0x83) | R | byte (below 65,536) |
//! | data block `DBn` (0x84) | R | `n x 65536 + byte` |
//! | system, answered by the backend | S | `__PLC_RUN` S2.2, `__PF_CRC` S70 |
//!
//! A block is at most 65,536 bytes (a non-optimised DB's limit), so a read
//! never needs to cross from one DB into the next; the backend splits one
//! that does.

pub mod codec;
pub mod frame;
pub mod pack;
pub mod tags;
pub mod value;

use std::fmt;

use plccoms_protocol::Area;

use crate::memory::MemoryMap;

/// ISO-on-TCP's port.
pub const DEFAULT_PORT: u16 = 102;

/// Bytes of one DB (or the merkers) in R.
pub const BLOCK: u32 = 65_536;

/// Highest DB number a tag may name: DB 65535 would end past R's u32 size
/// (no CPU has it: an S7-1500 numbers DBs up to 59999).
pub const MAX_DB: u16 = 65_534;

/// The areas of an S7 section: 64 KiB of inputs and outputs, the system
/// registers, the merkers and DB 1-65534 at 64 KiB each.
pub const MAP: MemoryMap = MemoryMap {
    sizes: [BLOCK, BLOCK, 4096, u32::MAX],
};

/// An S7 memory area as a request names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Region {
    Inputs,
    Outputs,
    Merkers,
    Db(u16),
}

impl Region {
    /// The area code of a read or write item.
    pub fn code(self) -> u8 {
        match self {
            Region::Inputs => 0x81,
            Region::Outputs => 0x82,
            Region::Merkers => 0x83,
            Region::Db(_) => 0x84,
        }
    }

    /// The DB number of an item (0 for the other areas).
    pub fn db(self) -> u16 {
        match self {
            Region::Db(n) => n,
            _ => 0,
        }
    }

    /// Where byte `byte` of this region lies.
    pub fn place(self, byte: u32) -> (Area, u32) {
        match self {
            Region::Inputs => (Area::X, byte),
            Region::Outputs => (Area::Y, byte),
            Region::Merkers => (Area::R, byte),
            Region::Db(n) => (Area::R, u32::from(n) * BLOCK + byte),
        }
    }

    /// The region and its byte at `offset` of `area`; `None` for S.
    pub fn locate(area: Area, offset: u32) -> Option<(Region, u32)> {
        Some(match area {
            Area::X => (Region::Inputs, offset),
            Area::Y => (Region::Outputs, offset),
            Area::R if offset < BLOCK => (Region::Merkers, offset),
            Area::R => (Region::Db((offset / BLOCK) as u16), offset % BLOCK),
            Area::S => return None,
        })
    }
}

impl fmt::Display for Region {
    /// As TIA Portal names it: `I`, `Q`, `M`, `DB5`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Region::Inputs => f.write_str("I"),
            Region::Outputs => f.write_str("Q"),
            Region::Merkers => f.write_str("M"),
            Region::Db(n) => write!(f, "DB{n}"),
        }
    }
}

/// `DB5.DBB10`, `MB3`, `I0.1`: a byte (or bit) as a user writes it.
pub fn address_text(region: Region, byte: u32, bit: Option<u8>) -> String {
    match (region, bit) {
        (Region::Db(n), Some(bit)) => format!("DB{n}.DBX{byte}.{bit}"),
        (Region::Db(n), None) => format!("DB{n}.DBB{byte}"),
        (region, Some(bit)) => format!("{region}{byte}.{bit}"),
        (region, None) => format!("{region}B{byte}"),
    }
}

/// What an S7 server answered for one item, or for a whole job (then its
/// header's error class and code, `0x8104`), instead of data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ReturnCode {
    /// An item's return code (0xFF is success and never one of these).
    Item(u8),
    /// The job's error class (high byte) and code (low byte).
    Job(u16),
}

impl ReturnCode {
    pub const HARDWARE_FAULT: ReturnCode = ReturnCode::Item(0x01);
    pub const ACCESS_DENIED: ReturnCode = ReturnCode::Item(0x03);
    pub const OUT_OF_RANGE: ReturnCode = ReturnCode::Item(0x05);
    pub const TYPE_NOT_SUPPORTED: ReturnCode = ReturnCode::Item(0x06);
    pub const TYPE_INCONSISTENT: ReturnCode = ReturnCode::Item(0x07);
    pub const NO_OBJECT: ReturnCode = ReturnCode::Item(0x0A);
    /// "Context not supported": an S7-1200/1500 without PUT/GET access.
    pub const FUNCTION_NOT_ALLOWED: ReturnCode = ReturnCode::Job(0x8104);

    /// The meaning, with what to do where the usual cause is known.
    pub fn meaning(self) -> &'static str {
        match self {
            ReturnCode::Item(0x01) => "hardware fault",
            ReturnCode::Item(0x03) => "access denied (S7-1200/1500: allow PUT/GET access in the CPU's protection settings and clear 'optimized block access' of the DB)",
            ReturnCode::Item(0x05) => "address out of range",
            ReturnCode::Item(0x06) => "data type not supported",
            ReturnCode::Item(0x07) => "data type inconsistent",
            ReturnCode::Item(0x0A) => "object does not exist",
            ReturnCode::Item(_) => "unknown return code",
            ReturnCode::Job(0x8104) => "function not allowed (S7-1200/1500: allow PUT/GET access in the CPU's protection settings)",
            ReturnCode::Job(0x8500) => "PDU too large",
            ReturnCode::Job(0xD602) => "access denied: the CPU is password protected",
            ReturnCode::Job(_) => "job refused",
        }
    }
}

impl fmt::Display for ReturnCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ReturnCode::Item(code) => write!(f, "S7 {} (0x{code:02X})", self.meaning()),
            ReturnCode::Job(code) => write!(f, "S7 {} (error 0x{code:04X})", self.meaning()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn regions_place_and_locate_back() {
        for region in [
            Region::Inputs,
            Region::Outputs,
            Region::Merkers,
            Region::Db(1),
            Region::Db(MAX_DB),
        ] {
            for byte in [0u32, 1, 65535] {
                let (area, offset) = region.place(byte);
                assert!(MAP.contains(area, offset, 1), "{region} {byte}");
                assert_eq!(Region::locate(area, offset), Some((region, byte)));
            }
        }
        assert_eq!(Region::locate(Area::S, 2), None);
        assert_eq!(address_text(Region::Db(3), 4, Some(5)), "DB3.DBX4.5");
        assert_eq!(address_text(Region::Merkers, 4, None), "MB4");
        assert_eq!(address_text(Region::Inputs, 0, Some(1)), "I0.1");
    }

    #[test]
    fn refusals_say_what_to_do() {
        assert!(ReturnCode::ACCESS_DENIED.to_string().contains("PUT/GET"));
        assert!(ReturnCode::FUNCTION_NOT_ALLOWED
            .to_string()
            .contains("PUT/GET"));
        assert_eq!(
            ReturnCode::NO_OBJECT.to_string(),
            "S7 object does not exist (0x0A)"
        );
    }
}
