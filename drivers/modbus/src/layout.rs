//! Reads of the section's memory layout (see `plccoms_plc::modbus`) as
//! Modbus requests, and their answers put back together: a read is cut at
//! the holding/input boundary and at the device's request limits, and
//! widened to whole registers; S is answered by the backend itself.

use plccoms_protocol::Area;

use plccoms_core::driver::{ReadRequest, Refusal};
use plccoms_plc::modbus::frame::{Request, Response};
use plccoms_plc::modbus::{ExceptionCode, Table, INPUT_BASE, MAP};

/// The device's request limits (MODBUS_MAX_REGS, MODBUS_MAX_BITS).
#[derive(Debug, Clone, Copy)]
pub struct DeviceLimits {
    pub max_regs: u16,
    pub max_bits: u16,
}

/// Where some bytes of a read come from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Source {
    /// Bytes `from..from + len` of the answer to Modbus request `request`
    /// (registers high byte first, bits one a byte).
    Device {
        request: usize,
        from: usize,
        len: usize,
    },
    /// The backend's own system registers.
    System { offset: u32, len: u32 },
    /// Outside the layout: refused without asking the device.
    Refused(Refusal),
}

/// The Modbus requests (appended to `requests`) and local parts that make
/// up `read`, in order.
pub fn plan_read(
    read: &ReadRequest,
    limits: DeviceLimits,
    requests: &mut Vec<Request>,
) -> Vec<Source> {
    let start = read.offset;
    let Some(end) = start
        .checked_add(read.len)
        .filter(|&end| MAP.contains(read.area, start, read.len) && end > start)
    else {
        return vec![Source::Refused(Refusal::Modbus(
            ExceptionCode::ILLEGAL_DATA_ADDRESS,
        ))];
    };
    match read.area {
        Area::S => vec![Source::System {
            offset: start,
            len: read.len,
        }],
        Area::X | Area::Y => {
            let table = if read.area == Area::Y {
                Table::Coil
            } else {
                Table::Discrete
            };
            let max = u32::from(limits.max_bits.max(1));
            let mut sources = Vec::new();
            let mut at = start;
            while at < end {
                let count = (end - at).min(max);
                sources.push(Source::Device {
                    request: requests.len(),
                    from: 0,
                    len: count as usize,
                });
                requests.push(read_request(table, at as u16, count as u16));
                at += count;
            }
            sources
        }
        Area::R => {
            let mut sources = Vec::new();
            for (table, base) in [(Table::Holding, 0), (Table::Input, INPUT_BASE)] {
                let (from, to) = (start.max(base), end.min(base + INPUT_BASE));
                if from >= to {
                    continue;
                }
                let max = u32::from(limits.max_regs.max(1));
                let mut register = (from - base) / 2;
                let last = (to - base).div_ceil(2);
                while register < last {
                    let count = (last - register).min(max);
                    let (bytes_from, bytes_to) =
                        (base + 2 * register, base + 2 * (register + count));
                    let (take_from, take_to) = (from.max(bytes_from), to.min(bytes_to));
                    sources.push(Source::Device {
                        request: requests.len(),
                        from: (take_from - bytes_from) as usize,
                        len: (take_to - take_from) as usize,
                    });
                    requests.push(read_request(table, register as u16, count as u16));
                    register += count;
                }
            }
            sources
        }
    }
}

fn read_request(table: Table, address: u16, count: u16) -> Request {
    match table {
        Table::Coil => Request::ReadCoils { address, count },
        Table::Discrete => Request::ReadDiscreteInputs { address, count },
        Table::Holding => Request::ReadHoldingRegisters { address, count },
        Table::Input => Request::ReadInputRegisters { address, count },
    }
}

/// The bytes of a read answer, as the layout holds them.
pub fn answer_bytes(response: &Response) -> Vec<u8> {
    match response {
        Response::Bits(bits) => bits.iter().map(|&b| u8::from(b)).collect(),
        Response::Registers(registers) => registers.iter().flat_map(|r| r.to_be_bytes()).collect(),
        Response::Written => Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: DeviceLimits = DeviceLimits {
        max_regs: 125,
        max_bits: 2000,
    };

    fn plan(area: Area, offset: u32, len: u32) -> (Vec<Source>, Vec<Request>) {
        let mut requests = Vec::new();
        let sources = plan_read(&ReadRequest { area, offset, len }, LIMITS, &mut requests);
        (sources, requests)
    }

    #[test]
    fn registers_are_whole_and_split_at_the_limit_and_the_boundary() {
        // One byte of register 3: the whole register, its second byte.
        let (sources, requests) = plan(Area::R, 7, 1);
        assert_eq!(
            requests,
            [Request::ReadHoldingRegisters {
                address: 3,
                count: 1
            }]
        );
        assert_eq!(
            sources,
            [Source::Device {
                request: 0,
                from: 1,
                len: 1
            }]
        );
        // 130 registers: 125 + 5.
        let (_, requests) = plan(Area::R, 0, 260);
        assert_eq!(requests.len(), 2);
        // Across the holding/input boundary.
        let (sources, requests) = plan(Area::R, INPUT_BASE - 2, 4);
        assert_eq!(
            requests,
            [
                Request::ReadHoldingRegisters {
                    address: 65535,
                    count: 1
                },
                Request::ReadInputRegisters {
                    address: 0,
                    count: 1
                }
            ]
        );
        assert_eq!(sources.len(), 2);
    }

    #[test]
    fn bits_one_a_byte_and_what_lies_outside() {
        let (_, requests) = plan(Area::Y, 10, 3000);
        assert_eq!(
            requests,
            [
                Request::ReadCoils {
                    address: 10,
                    count: 2000
                },
                Request::ReadCoils {
                    address: 2010,
                    count: 1000
                }
            ]
        );
        let (sources, requests) = plan(Area::X, 65535, 2);
        assert!(requests.is_empty());
        assert!(matches!(sources[0], Source::Refused(_)));
        let (sources, _) = plan(Area::S, 70, 4);
        assert_eq!(sources, [Source::System { offset: 70, len: 4 }]);
    }
}
