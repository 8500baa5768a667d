//! Modbus TCP, as the server's Modbus backend and the simulated PLC speak it:
//! frame types ([`frame`]), bytes <-> frames ([`codec`], both ends), the tag
//! file that names a device's registers ([`tags`]), and the memory layout
//! that puts the four Modbus tables into the areas the rest of the server
//! knows.
//!
//! # Layout
//!
//! A Modbus section's variables live in the same `(area, byte offset)` space
//! as a Tecomat PLC's, laid out by [`MAP`]:
//!
//! | table | area | byte offset | per byte |
//! | --- | --- | --- | --- |
//! | coil (FC 1, 5, 15) | Y | `address` | one coil, bit 0 |
//! | discrete input (FC 2) | X | `address` | one input, bit 0 |
//! | holding register (FC 3, 6, 16, 22) | R | `2 x address` | high byte first |
//! | input register (FC 4) | R | [`INPUT_BASE`]` + 2 x address` | high byte first |
//! | system (answered by the backend) | S | `__PLC_RUN` S2.2, `__PF_CRC` S70 | |
//!
//! One byte per coil rather than eight: the poll planner works in bytes, and
//! with eight coils a byte a read of one coil would ask for up to seven
//! neighbours the device may not have (answered with exception 2). A BOOL
//! bit `b` of a register is bit `b % 8` of its high byte (`b >= 8`) or its
//! low byte. A read crossing the holding/input boundary or a table's end is
//! split by the backend.

pub mod codec;
pub mod frame;
pub mod rtu;
pub mod tags;

use std::fmt;

use plccoms_protocol::Area;

use crate::memory::MemoryMap;

/// Where the input registers start in R.
pub const INPUT_BASE: u32 = 131_072;

/// The areas of a Modbus section: 65,536 coils and discrete inputs, the
/// system registers, and both register tables.
pub const MAP: MemoryMap = MemoryMap {
    sizes: [65_536, 65_536, 4096, 2 * INPUT_BASE],
};

/// Standard TCP port.
pub const DEFAULT_PORT: u16 = 502;

/// Most registers one read may ask for (FC 3, 4).
pub const MAX_READ_REGISTERS: u16 = 125;
/// Most bits one read may ask for (FC 1, 2).
pub const MAX_READ_BITS: u16 = 2000;
/// Most registers one write may carry (FC 16).
pub const MAX_WRITE_REGISTERS: u16 = 123;
/// Most coils one write may carry (FC 15).
pub const MAX_WRITE_BITS: u16 = 1968;

/// The four data tables of a Modbus device.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Table {
    Coil,
    Discrete,
    Input,
    Holding,
}

impl Table {
    pub fn parse(text: &str) -> Option<Table> {
        Some(match text.to_ascii_lowercase().as_str() {
            "coil" | "coils" => Table::Coil,
            "discrete" | "discrete_input" | "discrete_inputs" => Table::Discrete,
            "input" | "input_register" | "input_registers" => Table::Input,
            "holding" | "holding_register" | "holding_registers" => Table::Holding,
            _ => return None,
        })
    }

    /// Coils and discrete inputs hold bits; the others 16-bit registers.
    pub fn is_bits(self) -> bool {
        matches!(self, Table::Coil | Table::Discrete)
    }

    /// Whether a client may write it (coils and holding registers).
    pub fn writable(self) -> bool {
        matches!(self, Table::Coil | Table::Holding)
    }

    /// Where `address` of this table starts: area and byte offset.
    pub fn place(self, address: u16) -> (Area, u32) {
        let address = u32::from(address);
        match self {
            Table::Coil => (Area::Y, address),
            Table::Discrete => (Area::X, address),
            Table::Holding => (Area::R, 2 * address),
            Table::Input => (Area::R, INPUT_BASE + 2 * address),
        }
    }

    /// The table and address at byte `offset` of `area` (a register's
    /// either byte), `None` for S and past the tables.
    pub fn locate(area: Area, offset: u32) -> Option<(Table, u16)> {
        let (table, index) = match area {
            Area::Y => (Table::Coil, offset),
            Area::X => (Table::Discrete, offset),
            Area::R if offset < INPUT_BASE => (Table::Holding, offset / 2),
            Area::R => (Table::Input, (offset - INPUT_BASE) / 2),
            Area::S => return None,
        };
        u16::try_from(index).ok().map(|address| (table, address))
    }
}

impl fmt::Display for Table {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Table::Coil => "coil",
            Table::Discrete => "discrete",
            Table::Input => "input",
            Table::Holding => "holding",
        })
    }
}

/// A 1-based reference as device manuals give it (`40001`), which is not
/// the 0-based address on the wire (holding 0): the usual mistake in a tag
/// file, answered by the device with "illegal data address".
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Reference {
    /// As written (`40001`, `00017`, `400001`).
    pub text: String,
    /// What it names.
    pub table: Table,
    pub address: u16,
}

impl Reference {
    /// `text` read as a reference: five digits (00001-09999 coil, with its
    /// leading 0; 10001-19999 discrete; 30001-39999 input; 40001-49999
    /// holding) or six (000001-065536, 100001-165536, 300001-365536,
    /// 400001-465536).
    pub fn parse(text: &str) -> Option<Reference> {
        if !matches!(text.len(), 5 | 6) || !text.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        let table = match text.as_bytes()[0] {
            b'0' => Table::Coil,
            b'1' => Table::Discrete,
            b'3' => Table::Input,
            b'4' => Table::Holding,
            _ => return None,
        };
        let index: u32 = text[1..].parse().ok()?;
        let address = u16::try_from(index.checked_sub(1)?).ok()?;
        Some(Reference {
            text: text.to_string(),
            table,
            address,
        })
    }

    /// The reference a 0-based `address` may have been meant as: one of
    /// 10000 or more that reads as one (a coil's 0xxxx has fewer digits).
    pub fn of_address(address: u16) -> Option<Reference> {
        (address >= 10_000)
            .then(|| Reference::parse(&address.to_string()))
            .flatten()
    }

    /// How `table address` (as a tag names it) maps if it was meant as this
    /// reference.
    pub fn hint(&self, table: Table, address: u16) -> String {
        format!(
            "{table} {address} looks like the 1-based reference {}, which is {} {} (addresses are 0-based)",
            self.text, self.table, self.address
        )
    }
}

/// An exception code a device answered with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ExceptionCode(pub u8);

impl ExceptionCode {
    pub const ILLEGAL_FUNCTION: ExceptionCode = ExceptionCode(1);
    pub const ILLEGAL_DATA_ADDRESS: ExceptionCode = ExceptionCode(2);
    pub const ILLEGAL_DATA_VALUE: ExceptionCode = ExceptionCode(3);
    pub const SERVER_DEVICE_FAILURE: ExceptionCode = ExceptionCode(4);
    pub const GATEWAY_PATH_UNAVAILABLE: ExceptionCode = ExceptionCode(10);
    pub const GATEWAY_TARGET_FAILED: ExceptionCode = ExceptionCode(11);

    /// The specification's name for the code.
    pub fn meaning(self) -> &'static str {
        match self.0 {
            1 => "illegal function",
            2 => "illegal data address",
            3 => "illegal data value",
            4 => "server device failure",
            5 => "acknowledge",
            6 => "server device busy",
            8 => "memory parity error",
            10 => "gateway path unavailable",
            11 => "gateway target device failed to respond",
            _ => "unknown exception",
        }
    }

    /// Codes 10 and 11: a gateway says the device behind it cannot be
    /// reached, which is the link's failure, not a refusal of the request.
    pub fn is_gateway(self) -> bool {
        matches!(self.0, 10 | 11)
    }
}

impl fmt::Display for ExceptionCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Modbus exception {} ({})", self.0, self.meaning())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_place_and_locate_back() {
        for table in [Table::Coil, Table::Discrete, Table::Input, Table::Holding] {
            for address in [0u16, 1, 1000, u16::MAX] {
                let (area, offset) = table.place(address);
                assert!(MAP.contains(area, offset, if table.is_bits() { 1 } else { 2 }));
                assert_eq!(Table::locate(area, offset), Some((table, address)));
                if !table.is_bits() {
                    assert_eq!(Table::locate(area, offset + 1), Some((table, address)));
                }
            }
        }
        assert_eq!(Table::locate(Area::S, 2), None);
    }

    #[test]
    fn references_map_to_zero_based_addresses() {
        let of = |text: &str| Reference::parse(text).map(|r| (r.table, r.address));
        assert_eq!(of("40001"), Some((Table::Holding, 0)));
        assert_eq!(of("49999"), Some((Table::Holding, 9998)));
        assert_eq!(of("30010"), Some((Table::Input, 9)));
        assert_eq!(of("10001"), Some((Table::Discrete, 0)));
        assert_eq!(of("00017"), Some((Table::Coil, 16)));
        assert_eq!(of("400001"), Some((Table::Holding, 0)));
        assert_eq!(of("465536"), Some((Table::Holding, 65535)));
        for not in [
            "40000", "465537", "20001", "50001", "4001", "4000a", "", "0040001",
        ] {
            assert_eq!(of(not), None, "{not}");
        }
        assert_eq!(Reference::of_address(17), None);
        assert_eq!(Reference::of_address(9999), None);
        assert_eq!(Reference::of_address(20001), None);
        let r = Reference::of_address(40001).unwrap();
        assert_eq!(
            r.hint(Table::Holding, 40001),
            "holding 40001 looks like the 1-based reference 40001, which is holding 0 (addresses are 0-based)"
        );
    }
}
