//! The PLC as a device: memory image, run state and identification. The
//! in-process backend calls it directly; the simulated EPSNET PLC serves it
//! over UDP.

use plccoms_protocol::Area;

use plccoms_plc::{Exception, MemoryImage, MemoryMap, WriteData};

use crate::store::FileStore;

pub use plccoms_plc::memory::{PF_CRC_OFFSET, PLC_RUN_BIT, PLC_RUN_BYTE};

pub const DEFAULT_IDENT: &str = "CP1000    SIM 1.0 1.0";

#[derive(Debug, Clone)]
pub struct Device {
    pub image: MemoryImage,
    pub ident: String,
    /// The PLC's file system; `None`: file services are not activated.
    pub files: Option<FileStore>,
}

impl Device {
    /// A PLC in RUN with an empty program.
    pub fn new(map: MemoryMap) -> Self {
        let mut device = Device {
            image: MemoryImage::new(map),
            ident: DEFAULT_IDENT.to_string(),
            files: None,
        };
        device.set_run(true);
        device
    }

    pub fn run(&self) -> bool {
        self.image.area(Area::S)[PLC_RUN_BYTE as usize] & (1 << PLC_RUN_BIT) != 0
    }

    pub fn set_run(&mut self, run: bool) {
        self.image
            .write(
                Area::S,
                PLC_RUN_BYTE,
                &WriteData::Bit {
                    bit: PLC_RUN_BIT,
                    value: run,
                },
            )
            .expect("S area holds __PLC_RUN");
    }

    pub fn pf_crc(&self) -> u32 {
        let bytes = self
            .image
            .read(Area::S, PF_CRC_OFFSET, 4)
            .expect("S area holds __PF_CRC");
        u32::from_le_bytes(bytes.try_into().expect("4 bytes"))
    }

    pub fn set_pf_crc(&mut self, crc: u32) {
        self.image
            .write(
                Area::S,
                PF_CRC_OFFSET,
                &WriteData::Bytes(crc.to_le_bytes().to_vec()),
            )
            .expect("S area holds __PF_CRC");
    }

    pub fn read(&self, area: Area, offset: u32, len: u32) -> Result<Vec<u8>, Exception> {
        self.image.read(area, offset, len).map(<[u8]>::to_vec)
    }

    pub fn write(&mut self, area: Area, offset: u32, data: &WriteData) -> Result<(), Exception> {
        self.image.write(area, offset, data)
    }
}
