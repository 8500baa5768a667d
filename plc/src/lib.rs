//! The PLC side of plccoms, without I/O: what a Tecomat PLC looks like from
//! outside. Memory areas and their image ([`memory`]), public files
//! ([`pubfile`]), file attributes and times ([`files`], [`time`]), and the
//! EPSNET wire format ([`epsnet`]: frames, codec, the one table of service
//! codes). Shared by the server's backends and the simulated PLC (`plcsim`),
//! which reuse the same frames and codec from opposite ends.

pub mod epsnet;
pub mod files;
pub mod memory;
pub mod pubfile;
pub mod time;

pub use epsnet::Exception;
pub use files::{DirEntry, FileInfo};
pub use memory::{MemoryImage, MemoryMap, WriteData};
