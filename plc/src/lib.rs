//! The PLC side of plccoms, without I/O: what a Tecomat PLC looks like from
//! outside. Memory areas and their image ([`memory`]), public files
//! ([`pubfile`]), file attributes and times ([`files`], [`time`]), and the
//! EPSNET wire format ([`epsnet`]: frames, codec, the one table of service
//! codes), Modbus TCP ([`modbus`]: frames, codec, tag files), Siemens S7 ([`s7`]: frames,
//! codec, packing, tag files), OPC UA ([`opcua`]: node ids, tag files, StatusCode names),
//! a device's
//! refusal whatever its protocol ([`refusal`]), a variable ([`var`]) and how
//! its bytes become a client's value ([`value_codec`]). Shared by the
//! server's backends and the simulated PLC (`plcsim`), which reuse the same
//! frames and codecs from opposite ends.

pub mod ads;
pub mod epsnet;
pub mod files;
pub mod memory;
pub mod modbus;
pub mod opcua;
pub mod pubfile;
pub mod refusal;
pub mod s7;
pub mod tag_csv;
pub mod time;
pub mod value_codec;
pub mod var;

pub use epsnet::Exception;
pub use files::{DirEntry, FileInfo};
pub use memory::{MemoryImage, MemoryMap, WriteData};
pub use refusal::Refusal;
pub use var::{Var, VarInfo};
