//! plccoms: an open drop-in replacement for PLCComS.

pub mod backend;
pub mod cli;
pub mod config;
pub mod plc;
pub mod pubfile;
pub mod sim;
