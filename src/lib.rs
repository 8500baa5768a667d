//! plccoms: an open drop-in replacement for PLCComS.

pub mod backend;
pub mod plc;
pub mod sim;
