//! RS-485 direction control for the serial drivers (EPSNET and Modbus RTU):
//! a GPIO pin through sysfs, driven high while a frame is sent (SERIAL_RTS,
//! or the device's pin in `[*] SERIAL_DEVICE_CFG`), and the wait until the
//! UART has sent the frame's last bit.

use std::path::{Path, PathBuf};

/// Where the kernel's GPIO pins are.
pub const SYSFS_GPIO: &str = "/sys/class/gpio";

/// A GPIO pin through sysfs, driven as RTS.
#[derive(Debug)]
pub struct Gpio {
    value: PathBuf,
}

impl Gpio {
    /// Exports `pin` under `root` if needed, as an output, low.
    pub fn open(root: &Path, pin: u32) -> std::io::Result<Gpio> {
        let dir = root.join(format!("gpio{pin}"));
        if !dir.exists() {
            std::fs::write(root.join("export"), pin.to_string())?;
        }
        std::fs::write(dir.join("direction"), "out")?;
        let gpio = Gpio {
            value: dir.join("value"),
        };
        gpio.set(false)?;
        Ok(gpio)
    }

    pub fn set(&self, high: bool) -> std::io::Result<()> {
        std::fs::write(&self.value, if high { "1" } else { "0" })
    }
}

/// Waits until the UART behind `fd` has sent everything written to it.
pub fn drain(fd: std::os::fd::RawFd) {
    // SAFETY: tcdrain on a descriptor the caller holds open.
    unsafe {
        libc::tcdrain(fd);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gpio_is_exported_set_out_and_low() {
        let root = tempfile::tempdir().unwrap();
        std::fs::create_dir(root.path().join("gpio17")).unwrap();
        let gpio = Gpio::open(root.path(), 17).unwrap();
        assert_eq!(
            std::fs::read_to_string(root.path().join("gpio17/direction")).unwrap(),
            "out"
        );
        gpio.set(true).unwrap();
        assert_eq!(
            std::fs::read_to_string(root.path().join("gpio17/value")).unwrap(),
            "1"
        );
        // Not exported yet: asks the kernel to.
        assert!(Gpio::open(root.path(), 4).is_err());
        assert_eq!(
            std::fs::read_to_string(root.path().join("export")).unwrap(),
            "4"
        );
    }
}
