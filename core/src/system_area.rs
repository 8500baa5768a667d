//! The S area of a backend whose variables come from a tag file (Modbus,
//! S7): the device has no such area, so the backend answers it itself with
//! `__PLC_RUN` (S2.2) and `__PF_CRC` (S70: the tag file's CRC-32, taken
//! again whenever the file changes, so an edited tag file is loaded again
//! as a new program in a Tecomat PLC is).

use std::path::PathBuf;
use std::time::SystemTime;

use plccoms_plc::memory::{PF_CRC_OFFSET, PLC_RUN_BIT, PLC_RUN_BYTE};

/// Bytes of the S area answered.
pub const SIZE: u32 = 4096;

pub struct SystemArea {
    tags: Option<PathBuf>,
    /// Modification time and length of the tag file when its CRC was taken.
    seen: Option<(SystemTime, u64)>,
    crc: u32,
}

impl SystemArea {
    /// For the tag file at `tags` (none: `__PF_CRC` is 0).
    pub fn new(tags: Option<PathBuf>) -> SystemArea {
        SystemArea {
            tags,
            seen: None,
            crc: 0,
        }
    }

    /// Takes the tag file's CRC again when the file changed.
    fn refresh(&mut self) {
        let Some(path) = &self.tags else { return };
        let Ok(meta) = std::fs::metadata(path) else {
            return;
        };
        let stamp = (
            meta.modified().unwrap_or(SystemTime::UNIX_EPOCH),
            meta.len(),
        );
        if self.seen == Some(stamp) {
            return;
        }
        // A file being rewritten may be unreadable for a moment: keep the
        // last CRC and look again at the next poll.
        if let Ok(bytes) = std::fs::read(path) {
            self.crc = plccoms_plc::pubfile::crc_of(&bytes);
            self.seen = Some(stamp);
        }
    }

    /// `len` bytes from `offset`, with `__PLC_RUN` as `run`; `None` past
    /// the area's end.
    pub fn read(&mut self, run: bool, offset: u32, len: u32) -> Option<Vec<u8>> {
        self.refresh();
        let mut image = [0u8; SIZE as usize];
        if run {
            image[PLC_RUN_BYTE as usize] |= 1 << PLC_RUN_BIT;
        }
        let crc = PF_CRC_OFFSET as usize;
        image[crc..crc + 4].copy_from_slice(&self.crc.to_le_bytes());
        let end = offset.checked_add(len)? as usize;
        image.get(offset as usize..end).map(<[u8]>::to_vec)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn run_bit_and_the_tag_files_crc() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tags.csv");
        std::fs::write(&path, b"name,address\n").unwrap();
        let mut area = SystemArea::new(Some(path.clone()));
        assert_eq!(
            area.read(true, PLC_RUN_BYTE, 1),
            Some(vec![1 << PLC_RUN_BIT])
        );
        assert_eq!(area.read(false, PLC_RUN_BYTE, 1), Some(vec![0]));
        let crc = plccoms_plc::pubfile::crc_of(b"name,address\n");
        assert_eq!(
            area.read(true, PF_CRC_OFFSET, 4),
            Some(crc.to_le_bytes().to_vec())
        );
        assert_eq!(area.read(true, SIZE - 1, 2), None);
        assert_eq!(area.read(true, u32::MAX, 2), None);
    }
}
