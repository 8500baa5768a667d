//! The PLC itself, as this project models it: a memory image with the areas the
//! public files address, shared by the in-process backend and the simulated
//! EPSNET PLC.

pub mod device;
pub mod image;

pub use device::Device;
pub use image::{MemoryImage, MemoryMap};
