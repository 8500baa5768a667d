//! The PLC itself, as this project models it: a memory image with the areas the
//! public files address, shared by the in-process backend and the simulated
//! EPSNET PLC.

pub mod device;
pub mod files;
pub mod image;
pub mod time;

pub use device::Device;
pub use files::FileStore;
pub use image::{MemoryImage, MemoryMap};
