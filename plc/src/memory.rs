//! PLC memory: the areas' sizes, a byte image of them, and what a write
//! puts into it.

use plccoms_protocol::Area;

use crate::epsnet::Exception;

/// Byte and bit of `__PLC_RUN`, and byte of `__PF_CRC`, in the S area (as the
/// vendor's fixed public files place them): the simulated PLC keeps them, a
/// Modbus backend fills them in for its device.
pub const PLC_RUN_BYTE: u32 = 2;
pub const PLC_RUN_BIT: u8 = 2;
pub const PF_CRC_OFFSET: u32 = 70;

/// What a write puts into memory: whole bytes, or one bit of one byte (so two
/// BOOLs sharing a byte never overwrite each other).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum WriteData {
    Bytes(Vec<u8>),
    Bit { bit: u8, value: bool },
}

/// Size of each memory area in bytes. Not public for real PLCs; these are the
/// sizes of current Foxtrot CPUs as far as public files show them (R up to
/// 512 KiB), and the bounds the server checks public-file addresses against.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MemoryMap {
    pub sizes: [u32; 4],
}

impl MemoryMap {
    pub const FOXTROT: MemoryMap = MemoryMap {
        sizes: [16 * 1024, 16 * 1024, 4 * 1024, 512 * 1024],
    };

    pub fn size(&self, area: Area) -> u32 {
        self.sizes[area.index()]
    }

    /// Whether `len` bytes at `offset` lie inside `area`.
    pub fn contains(&self, area: Area, offset: u32, len: u32) -> bool {
        u64::from(offset) + u64::from(len) <= u64::from(self.size(area))
    }
}

impl Default for MemoryMap {
    fn default() -> Self {
        MemoryMap::FOXTROT
    }
}

/// PLC memory: every area zero-initialised at its map's size.
#[derive(Debug, Clone)]
pub struct MemoryImage {
    map: MemoryMap,
    areas: [Vec<u8>; 4],
}

impl MemoryImage {
    pub fn new(map: MemoryMap) -> Self {
        MemoryImage {
            map,
            areas: map.sizes.map(|size| vec![0; size as usize]),
        }
    }

    pub fn map(&self) -> MemoryMap {
        self.map
    }

    /// `len` bytes at `offset`; `BadParameters` past the end of the area, as a
    /// PLC answers.
    pub fn read(&self, area: Area, offset: u32, len: u32) -> Result<&[u8], Exception> {
        if !self.map.contains(area, offset, len) {
            return Err(Exception::BadParameters);
        }
        let start = offset as usize;
        Ok(&self.areas[area.index()][start..start + len as usize])
    }

    pub fn write(&mut self, area: Area, offset: u32, data: &WriteData) -> Result<(), Exception> {
        let len = match data {
            WriteData::Bytes(bytes) => bytes.len() as u32,
            WriteData::Bit { .. } => 1,
        };
        if !self.map.contains(area, offset, len) {
            return Err(Exception::BadParameters);
        }
        let start = offset as usize;
        let target = &mut self.areas[area.index()];
        match data {
            WriteData::Bytes(bytes) => target[start..start + bytes.len()].copy_from_slice(bytes),
            WriteData::Bit { bit, value } => {
                if *bit > 7 {
                    return Err(Exception::BadParameters);
                }
                let mask = 1u8 << bit;
                if *value {
                    target[start] |= mask;
                } else {
                    target[start] &= !mask;
                }
            }
        }
        Ok(())
    }

    /// Direct mutable access for the PLC program.
    pub fn area_mut(&mut self, area: Area) -> &mut [u8] {
        &mut self.areas[area.index()]
    }

    pub fn area(&self, area: Area) -> &[u8] {
        &self.areas[area.index()]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bit_writes_touch_only_their_bit() {
        let mut image = MemoryImage::new(MemoryMap::FOXTROT);
        image
            .write(
                Area::R,
                10,
                &WriteData::Bit {
                    bit: 0,
                    value: true,
                },
            )
            .unwrap();
        image
            .write(
                Area::R,
                10,
                &WriteData::Bit {
                    bit: 7,
                    value: true,
                },
            )
            .unwrap();
        assert_eq!(image.read(Area::R, 10, 1).unwrap(), &[0x81]);
        image
            .write(
                Area::R,
                10,
                &WriteData::Bit {
                    bit: 0,
                    value: false,
                },
            )
            .unwrap();
        assert_eq!(image.read(Area::R, 10, 1).unwrap(), &[0x80]);
    }

    #[test]
    fn out_of_range_is_bad_parameters() {
        let image = MemoryImage::new(MemoryMap::FOXTROT);
        let end = MemoryMap::FOXTROT.size(Area::R);
        assert!(image.read(Area::R, end - 4, 4).is_ok());
        assert_eq!(
            image.read(Area::R, end - 3, 4),
            Err(Exception::BadParameters)
        );
        assert_eq!(
            image.read(Area::R, u32::MAX, 4),
            Err(Exception::BadParameters)
        );
    }
}
