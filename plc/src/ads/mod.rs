//! Beckhoff ADS over TCP (AMS/TCP, port 48898), as the server's ADS backend
//! speaks it: frame types and the tokio-util codec ([`frame`]), the typed
//! commands and answers ([`command`]), the symbol table and data types a
//! TwinCAT PLC uploads ([`symbols`]), and the tag file for devices without
//! a symbol table ([`tags`]).
//!
//! Why our own codec: the ADS crates on crates.io are either blocking
//! (`ads`: one thread per connection, no tokio) or bindings to Beckhoff's
//! C++ router; neither fits a tokio link task that must time out each
//! request and be fuzzed without I/O. AMS/TCP is a fixed 38-byte header and
//! little-endian bodies, small enough to own.
//!
//! # Layout
//!
//! Symbols have no place in the X/Y/S/R memory the rest of the server
//! addresses; the backend lays them out one after another in R ([`MAP`]),
//! each at its own byte offset, and writes the public file that names them
//! ([`symbols::public_file`]). S holds `__PLC_RUN` (S2.2, from the ADS
//! state) and `__PF_CRC` (S70, the CRC of that public file), as the standard
//! fixed file places them.

pub mod command;
pub mod frame;
pub mod symbols;
pub mod tags;

use std::fmt;

use crate::memory::MemoryMap;

/// AMS/TCP port of every ADS device.
pub const TCP_PORT: u16 = 48898;
/// ADS port of the first PLC runtime: TwinCAT 3, TwinCAT 2.
pub const PORT_TC3: u16 = 851;
pub const PORT_TC2: u16 = 801;

/// Where a section's symbols live: R is large enough for 100,000 symbols of
/// a STRING(80) each, S holds the system variables.
pub const MAP: MemoryMap = MemoryMap {
    sizes: [0, 0, 4096, 16 * 1024 * 1024],
};

/// Index groups of the symbol services (ADS specification, "ADS Index
/// Groups" of TwinCAT's PLC runtime).
pub mod group {
    /// A handle for the name in the write data (ReadWrite).
    pub const SYM_HNDBYNAME: u32 = 0xF003;
    /// The value of a handle (offset: the handle).
    pub const SYM_VALBYHND: u32 = 0xF005;
    /// Release a handle (Write of the handle).
    pub const SYM_RELEASEHND: u32 = 0xF006;
    /// Symbol version: one byte, changed by every new PLC program.
    pub const SYM_VERSION: u32 = 0xF008;
    /// The symbol table, all entries (Read).
    pub const SYM_UPLOAD: u32 = 0xF00B;
    /// The data types, all entries (Read).
    pub const SYM_DT_UPLOAD: u32 = 0xF00E;
    /// Symbol count, symbol table length, data type count and length.
    pub const SYM_UPLOADINFO2: u32 = 0xF00F;
    /// Sum commands: offset = number of sub-requests.
    pub const SUMUP_READ: u32 = 0xF080;
    pub const SUMUP_WRITE: u32 = 0xF081;
    pub const SUMUP_READWRITE: u32 = 0xF082;
}

/// Most sub-requests one sum command may carry (Beckhoff's documented
/// limit).
pub const MAX_SUM: usize = 500;

/// An AMS Net ID: six bytes, written `5.12.34.56.1.1`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct NetId(pub [u8; 6]);

impl NetId {
    /// `a.b.c.d.e.f`, each 0-255.
    pub fn parse(text: &str) -> Result<NetId, String> {
        let mut id = [0u8; 6];
        let mut parts = text.trim().split('.');
        for (i, byte) in id.iter_mut().enumerate() {
            let part = parts.next().ok_or_else(|| {
                format!("AMS Net ID '{text}' has {i} parts; expected six (e.g. 5.12.34.56.1.1)")
            })?;
            *byte = part
                .parse()
                .map_err(|_| format!("AMS Net ID '{text}': '{part}' is not 0-255"))?;
        }
        if parts.next().is_some() {
            return Err(format!(
                "AMS Net ID '{text}' has more than six parts (e.g. 5.12.34.56.1.1)"
            ));
        }
        Ok(NetId(id))
    }
}

impl fmt::Display for NetId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [a, b, c, d, e, g] = self.0;
        write!(f, "{a}.{b}.{c}.{d}.{e}.{g}")
    }
}

/// One end of an ADS exchange: a Net ID and an ADS port.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct AmsAddr {
    pub net_id: NetId,
    pub port: u16,
}

/// An ADS error code (ADS return codes, Beckhoff InfoSys), as the device
/// answers it in a header or a body.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct AdsError(pub u32);

impl AdsError {
    pub const TARGET_PORT_NOT_FOUND: AdsError = AdsError(0x6);
    pub const TARGET_MACHINE_NOT_FOUND: AdsError = AdsError(0x7);
    pub const SERVICE_NOT_SUPPORTED: AdsError = AdsError(0x701);
    pub const INVALID_GROUP: AdsError = AdsError(0x702);
    pub const INVALID_OFFSET: AdsError = AdsError(0x703);
    pub const INVALID_ACCESS: AdsError = AdsError(0x704);
    pub const INVALID_SIZE: AdsError = AdsError(0x705);
    pub const INVALID_DATA: AdsError = AdsError(0x706);
    pub const NOT_READY: AdsError = AdsError(0x707);
    pub const SYMBOL_NOT_FOUND: AdsError = AdsError(0x710);
    pub const SYMBOL_VERSION_INVALID: AdsError = AdsError(0x711);
    pub const INVALID_NOTIFICATION_HANDLE: AdsError = AdsError(0x714);

    /// Beckhoff's name of the code, where it is one of the common ones.
    pub fn name(self) -> Option<&'static str> {
        Some(match self.0 {
            0x1 => "internal error",
            0x6 => "target port not found",
            0x7 => "target machine not found",
            0x8 => "unknown command ID",
            0xE => "no access (not logged on or not routed)",
            0x12 => "port disabled",
            0x13 => "port already connected",
            0x18 => "invalid AMS fragment",
            0x19 => "timeout",
            0x700 => "general device error",
            0x701 => "service not supported",
            0x702 => "invalid index group",
            0x703 => "invalid index offset",
            0x704 => "reading or writing not permitted",
            0x705 => "parameter size not correct",
            0x706 => "invalid data values",
            0x707 => "device not ready",
            0x708 => "device busy",
            0x709 => "invalid OS context",
            0x70A => "insufficient memory",
            0x70B => "invalid parameter value",
            0x70C => "not found",
            0x70D => "syntax error",
            0x710 => "symbol not found",
            0x711 => "symbol version invalid",
            0x712 => "device in an invalid state",
            0x713 => "transmission mode not supported",
            0x714 => "notification handle invalid",
            0x715 => "notification client not registered",
            0x716 => "no further notification handle",
            0x717 => "notification size too large",
            0x719 => "device has timed out",
            0x71A => "device interrupt error",
            0x745 => "timeout",
            0x1861 => "timeout elapsed (router)",
            _ => return None,
        })
    }

    /// What to check, for the codes a user can do something about.
    pub fn hint(self) -> Option<&'static str> {
        Some(match self.0 {
            0x6 => "is ADS_PORT the PLC runtime's (851 TwinCAT 3, 801 TwinCAT 2) and is that runtime started?",
            0x7 | 0xE => "is ADS_NET_ID the PLC's AMS Net ID, and does the PLC have a route to ADS_SOURCE_NET_ID at this machine's address?",
            0x701..=0x703 => "does the device serve this index group/offset (a symbol of the PLC program)?",
            0x704 => "is the variable writable in the PLC program (not a constant, not read-only)?",
            0x705 => "the variable's size in the PLC differs from its type here: check the type in ADS_TAGS, or the PLC program changed",
            0x707 | 0x712 => "is the PLC in RUN (or CONFIG mode with the runtime stopped)?",
            0x710 => "does the PLC program still have this symbol (name as MAIN.x or GVL.x)?",
            0x711 => "the PLC program changed: its symbols are loaded again",
            0x716 => "the PLC has no notification handles left: fewer variables in ADS_NOTIFY",
            _ => return None,
        })
    }
}

impl fmt::Display for AdsError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.name() {
            Some(name) => write!(f, "ADS error 0x{:X} ({name})", self.0),
            None => write!(f, "ADS error 0x{:X}", self.0),
        }
    }
}

/// An ADS state (ReadState's first word).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AdsState(pub u16);

impl AdsState {
    pub const RUN: AdsState = AdsState(5);
    pub const STOP: AdsState = AdsState(6);
    pub const CONFIG: AdsState = AdsState(15);

    pub fn is_run(self) -> bool {
        self == AdsState::RUN
    }
}

/// A Windows FILETIME (100 ns ticks since 1601-01-01 UTC) as seconds since
/// the Unix epoch: the time stamp of a device notification.
pub fn filetime_to_unix(filetime: u64) -> f64 {
    const EPOCH_DIFF: u64 = 116_444_736_000_000_000;
    (filetime as f64 - EPOCH_DIFF as f64) / 1e7
}

/// A FILETIME as UTC milliseconds since the Unix epoch (truncated).
pub fn filetime_to_unix_ms(filetime: u64) -> i64 {
    const EPOCH_DIFF: i128 = 116_444_736_000_000_000;
    ((i128::from(filetime) - EPOCH_DIFF).div_euclid(10_000)) as i64
}

/// Seconds since the Unix epoch as a FILETIME (0 before 1601).
pub fn unix_to_filetime(unix: f64) -> u64 {
    let ticks = unix * 1e7 + 116_444_736_000_000_000.0;
    if ticks <= 0.0 {
        0
    } else {
        ticks as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn net_ids_parse_and_print() {
        let id = NetId::parse("5.12.34.56.1.1").unwrap();
        assert_eq!(id.0, [5, 12, 34, 56, 1, 1]);
        assert_eq!(id.to_string(), "5.12.34.56.1.1");
        assert!(NetId::parse("5.12.34.56.1")
            .unwrap_err()
            .contains("has 5 parts"));
        assert!(NetId::parse("5.12.34.56.1.1.1")
            .unwrap_err()
            .contains("more than six"));
        assert!(NetId::parse("5.12.34.256.1.1")
            .unwrap_err()
            .contains("'256' is not 0-255"));
    }

    #[test]
    fn errors_are_named_with_what_to_check() {
        assert_eq!(
            AdsError::SYMBOL_NOT_FOUND.to_string(),
            "ADS error 0x710 (symbol not found)"
        );
        assert!(AdsError(0x6).hint().unwrap().contains("ADS_PORT"));
        assert!(AdsError(0x705).hint().unwrap().contains("size"));
        assert_eq!(AdsError(0x9999).to_string(), "ADS error 0x9999");
    }

    #[test]
    fn filetimes_round_trip() {
        // 2024-03-15T13:45:30.5Z
        let unix = 1_710_510_330.5;
        let ft = unix_to_filetime(unix);
        assert_eq!(ft, 133_549_839_305_000_000);
        assert!((filetime_to_unix(ft) - unix).abs() < 1e-6);
        assert_eq!(unix_to_filetime(-2e10), 0);
        assert_eq!(filetime_to_unix_ms(ft), 1_710_510_330_500);
        assert_eq!(filetime_to_unix_ms(0), -11_644_473_600_000);
    }
}
