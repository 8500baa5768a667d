//! The PLCComS line protocol, without I/O: request parsing, answer and value
//! formatting, wildcard masks and cp1250 text. Shared by the server, its tests,
//! tools and clients.

pub mod address;
pub mod answer;
pub mod cp1250;
pub mod decoder;
pub mod mask;
pub mod request;
pub mod types;
pub mod value;

pub use address::{parse_direct, DirectAddress};
pub use answer::{write_error, write_warning, ErrorCode, WarningCode};
pub use decoder::{Decoder, Frame};
pub use mask::Mask;
pub use request::{classify, ArgError, Command, Line};
pub use types::{Area, IecType};
pub use value::{Delta, FormatOptions, Value, ValueError};
