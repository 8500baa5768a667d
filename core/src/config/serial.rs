//! `[*] SERIAL_DEVICE_CFG`: the RTS GPIO pin of each serial device, parsed
//! once when the configuration is loaded; and the character format of a
//! line (`SERIAL_PARITY`, `SERIAL_DATA_BITS`, `SERIAL_STOP_BITS`).

/// `SERIAL_PARITY`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Parity {
    None,
    Even,
    Odd,
}

/// The key's choices.
pub const PARITIES: [&str; 3] = ["NONE", "EVEN", "ODD"];

impl Parity {
    /// One of [`PARITIES`], any case.
    pub fn parse(text: &str) -> Option<Parity> {
        Some(match text.to_ascii_uppercase().as_str() {
            "NONE" => Parity::None,
            "EVEN" => Parity::Even,
            "ODD" => Parity::Odd,
            _ => return None,
        })
    }

    /// The letter of `8E1`.
    pub fn letter(self) -> char {
        match self {
            Parity::None => 'N',
            Parity::Even => 'E',
            Parity::Odd => 'O',
        }
    }
}

/// One entry of SERIAL_DEVICE_CFG: a serial device and its RTS pin.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DevicePin {
    pub device: String,
    /// `None` for `-1`: no GPIO pin.
    pub pin: Option<u32>,
}

/// `"/dev/ttyS0 -1, /dev/ttyS1 17"`: each device's RTS GPIO pin (-1: none).
/// `Err` names the entry that is not `DEVICE PIN`.
pub fn parse_device_cfg(text: &str) -> Result<Vec<DevicePin>, String> {
    text.split(',')
        .map(str::trim)
        .filter(|entry| !entry.is_empty())
        .map(|entry| {
            let bad =
                || format!("SERIAL_DEVICE_CFG: '{entry}' is not DEVICE PIN (e.g. /dev/ttyS0 -1)");
            let (device, pin) = entry.rsplit_once(char::is_whitespace).ok_or_else(bad)?;
            let pin = match pin {
                "-1" => None,
                digits if !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit()) => {
                    Some(digits.parse::<u32>().map_err(|_| bad())?)
                }
                _ => return Err(bad()),
            };
            Ok(DevicePin {
                device: device.trim().to_string(),
                pin,
            })
        })
        .collect()
}

/// The RTS pin SERIAL_DEVICE_CFG gives `device`, if any.
pub fn pin_of(cfg: &[DevicePin], device: &str) -> Option<u32> {
    cfg.iter().find(|d| d.device == device).and_then(|d| d.pin)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_cfg_as_the_vendor_writes_it() {
        let pin = |device: &str, pin| DevicePin {
            device: device.into(),
            pin,
        };
        let cfg = parse_device_cfg("/dev/ttyS0 -1, /dev/ttyS1 17").unwrap();
        assert_eq!(cfg, [pin("/dev/ttyS0", None), pin("/dev/ttyS1", Some(17))]);
        assert_eq!(pin_of(&cfg, "/dev/ttyS1"), Some(17));
        assert_eq!(pin_of(&cfg, "/dev/ttyS0"), None);
        assert_eq!(
            parse_device_cfg("/dev/ttyS0").unwrap_err(),
            "SERIAL_DEVICE_CFG: '/dev/ttyS0' is not DEVICE PIN (e.g. /dev/ttyS0 -1)"
        );
        assert!(parse_device_cfg("/dev/ttyS0 -2").is_err());
        assert!(parse_device_cfg("/dev/ttyS0 99999999999").is_err());
    }
}
