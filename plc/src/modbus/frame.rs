//! Modbus frames as plain data: the requests this project sends or serves,
//! and the answers to them. Bytes are the codec's business.

/// A request (the PDU's function and its fields).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Request {
    /// FC 1.
    ReadCoils { address: u16, count: u16 },
    /// FC 2.
    ReadDiscreteInputs { address: u16, count: u16 },
    /// FC 3.
    ReadHoldingRegisters { address: u16, count: u16 },
    /// FC 4.
    ReadInputRegisters { address: u16, count: u16 },
    /// FC 5.
    WriteSingleCoil { address: u16, value: bool },
    /// FC 6.
    WriteSingleRegister { address: u16, value: u16 },
    /// FC 15.
    WriteMultipleCoils { address: u16, values: Vec<bool> },
    /// FC 16.
    WriteMultipleRegisters { address: u16, values: Vec<u16> },
    /// FC 22: register := (register AND and_mask) OR (or_mask AND NOT and_mask).
    MaskWriteRegister {
        address: u16,
        and_mask: u16,
        or_mask: u16,
    },
}

pub const READ_COILS: u8 = 0x01;
pub const READ_DISCRETE_INPUTS: u8 = 0x02;
pub const READ_HOLDING_REGISTERS: u8 = 0x03;
pub const READ_INPUT_REGISTERS: u8 = 0x04;
pub const WRITE_SINGLE_COIL: u8 = 0x05;
pub const WRITE_SINGLE_REGISTER: u8 = 0x06;
pub const WRITE_MULTIPLE_COILS: u8 = 0x0F;
pub const WRITE_MULTIPLE_REGISTERS: u8 = 0x10;
pub const MASK_WRITE_REGISTER: u8 = 0x16;

impl Request {
    pub fn function(&self) -> u8 {
        match self {
            Request::ReadCoils { .. } => READ_COILS,
            Request::ReadDiscreteInputs { .. } => READ_DISCRETE_INPUTS,
            Request::ReadHoldingRegisters { .. } => READ_HOLDING_REGISTERS,
            Request::ReadInputRegisters { .. } => READ_INPUT_REGISTERS,
            Request::WriteSingleCoil { .. } => WRITE_SINGLE_COIL,
            Request::WriteSingleRegister { .. } => WRITE_SINGLE_REGISTER,
            Request::WriteMultipleCoils { .. } => WRITE_MULTIPLE_COILS,
            Request::WriteMultipleRegisters { .. } => WRITE_MULTIPLE_REGISTERS,
            Request::MaskWriteRegister { .. } => MASK_WRITE_REGISTER,
        }
    }

    /// Whether it changes the device.
    pub fn is_write(&self) -> bool {
        self.function() >= WRITE_SINGLE_COIL
    }
}

/// A successful answer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Response {
    /// FC 1, 2: exactly the bits asked for.
    Bits(Vec<bool>),
    /// FC 3, 4: exactly the registers asked for.
    Registers(Vec<u16>),
    /// A write, its echo checked against the request.
    Written,
}
