//! A device's refusal of one request, whatever protocol the device speaks.
//! Each protocol keeps its own code type ([`Exception`] for EPSNET's error
//! byte, [`ExceptionCode`] for Modbus); this is the one type a backend's
//! refusal travels in, so that neither protocol's type stands for the other.

use std::fmt;

use crate::ads::AdsError;
use crate::epsnet::Exception;
use crate::modbus::ExceptionCode;

/// What a device answered instead of data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Refusal {
    /// An EPSNET error byte: a Tecomat PLC's answer, a plugin's (the plugin
    /// ABI uses the same bytes), and the server's own refusals (the
    /// constants below), which clients know in these terms.
    Epsnet(Exception),
    /// A Modbus device's exception code.
    Modbus(ExceptionCode),
    /// An S7 server's return code for an item, or its error for a job.
    S7(crate::s7::ReturnCode),
    /// An ADS device's error code.
    Ads(AdsError),
    /// An OPC UA server's StatusCode (Bad or Uncertain) for one node.
    Opcua(u32),
}

impl Refusal {
    /// Wrong parameters: past an area's end, a file that is not there.
    pub const BAD_PARAMETERS: Refusal = Refusal::Epsnet(Exception::BadParameters);
    /// A service this device or backend does not offer (files, most often).
    pub const NOT_ACTIVATED: Refusal = Refusal::Epsnet(Exception::NotActivated);
    pub const UNKNOWN_SERVICE: Refusal = Refusal::Epsnet(Exception::UnknownService);
}

impl From<Exception> for Refusal {
    fn from(e: Exception) -> Self {
        Refusal::Epsnet(e)
    }
}

impl From<ExceptionCode> for Refusal {
    fn from(code: ExceptionCode) -> Self {
        Refusal::Modbus(code)
    }
}

impl fmt::Display for Refusal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Refusal::Epsnet(e) => e.fmt(f),
            Refusal::Modbus(code) => code.fmt(f),
            Refusal::S7(code) => code.fmt(f),
            Refusal::Ads(code) => code.fmt(f),
            Refusal::Opcua(code) => match crate::opcua::status::name(*code) {
                Some(name) => write!(f, "OPC UA {name} (0x{code:08X})"),
                None => write!(f, "OPC UA status 0x{code:08X}"),
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texts_are_each_protocols_own() {
        assert_eq!(
            Refusal::BAD_PARAMETERS.to_string(),
            "wrong service parameters (0x0C)"
        );
        assert_eq!(
            Refusal::from(Exception::Other(0x42)).to_string(),
            "error byte 0x42"
        );
        assert_eq!(
            Refusal::from(ExceptionCode(2)).to_string(),
            "Modbus exception 2 (illegal data address)"
        );
        assert_eq!(
            Refusal::Opcua(0x803B_0000).to_string(),
            "OPC UA BadNotWritable (0x803B0000)"
        );
    }
}
