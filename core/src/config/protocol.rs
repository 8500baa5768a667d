//! `PROTOCOL`: which driver a section talks through.

use std::fmt;

/// A section's backend, as its `PROTOCOL` key names it. A new driver adds
/// one variant here (listed in [`Protocol::ALL`], named in
/// [`Protocol::name`]) and claims it in its `open` (see CONTRIBUTING.md);
/// the key table's choices follow, and the compiler points at every match.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Protocol {
    /// Teco's EPSNET, over UDP, serial line or shared memory (the default).
    #[default]
    Epsnet,
    /// Modbus TCP, variables from a tag file (`MODBUS_TAGS`).
    ModbusTcp,
    /// Modbus RTU on a serial line (`SERIAL_DEVICE`), the same tag files.
    ModbusRtu,
    /// Modbus RTU frames over TCP to a serial device server (`IPADDR`,
    /// `MODBUS_PORT`).
    ModbusRtuTcp,
    /// Siemens S7comm over ISO-on-TCP, variables from a tag file (`S7_TAGS`).
    S7,
    /// Beckhoff ADS over TCP, variables from the PLC's symbol table.
    Ads,
    /// A PLC's own OPC UA server (`OPCUA_URL`), variables browsed
    /// (`OPCUA_BROWSE`) or from a tag file (`OPCUA_TAGS`).
    Opcua,
}

/// The ini names, in [`Protocol::ALL`]'s order: the key table's choices.
pub const PROTOCOLS: &[&str] = &{
    let mut names = [""; Protocol::ALL.len()];
    let mut i = 0;
    while i < names.len() {
        names[i] = Protocol::ALL[i].name();
        i += 1;
    }
    names
};

impl Protocol {
    /// Every protocol, in the order the documentation lists them.
    pub const ALL: [Protocol; 7] = [
        Protocol::Epsnet,
        Protocol::ModbusTcp,
        Protocol::ModbusRtu,
        Protocol::ModbusRtuTcp,
        Protocol::S7,
        Protocol::Ads,
        Protocol::Opcua,
    ];

    /// The name in the ini file and in `GETINFO:PROTOCOL`.
    pub const fn name(self) -> &'static str {
        match self {
            Protocol::Epsnet => "EPSNET",
            Protocol::ModbusTcp => "MODBUS_TCP",
            Protocol::ModbusRtu => "MODBUS_RTU",
            Protocol::ModbusRtuTcp => "MODBUS_RTU_TCP",
            Protocol::S7 => "S7",
            Protocol::Ads => "ADS",
            Protocol::Opcua => "OPCUA",
        }
    }

    /// Whether the section's variables come from a Modbus tag file.
    pub const fn is_modbus(self) -> bool {
        matches!(
            self,
            Protocol::ModbusTcp | Protocol::ModbusRtu | Protocol::ModbusRtuTcp
        )
    }

    /// The protocol `text` names, ignoring case as the ini file does.
    pub fn parse(text: &str) -> Option<Protocol> {
        Protocol::ALL
            .into_iter()
            .find(|p| p.name().eq_ignore_ascii_case(text))
    }
}

impl fmt::Display for Protocol {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_back_in_any_case() {
        assert_eq!(
            PROTOCOLS,
            [
                "EPSNET",
                "MODBUS_TCP",
                "MODBUS_RTU",
                "MODBUS_RTU_TCP",
                "S7",
                "ADS",
                "OPCUA"
            ]
        );
        for protocol in Protocol::ALL {
            assert_eq!(Protocol::parse(protocol.name()), Some(protocol));
            let lower = protocol.to_string().to_ascii_lowercase();
            assert_eq!(Protocol::parse(&lower), Some(protocol));
        }
        assert_eq!(Protocol::parse("MODBUS"), None);
    }
}
