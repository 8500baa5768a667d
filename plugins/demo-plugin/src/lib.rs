//! The example backend plugin: a section with `SHM_NAME` pointing at this
//! library behaves like the simulated PLC. Each handle is a `plcsim`
//! [`Device`] laid out by `conf/demo.pub` (its CRC in `__PF_CRC`), running
//! the manual's demo program, with a file system holding `demo.pub` (so
//! `PUBFILE = //demo.pub` is fetched through the plugin).
//!
//! The program runs when the server calls, at most once per PLC cycle of
//! 10 ms: values change as they are read, as on a PLC.
//!
//! Keys: `SHM_SOCKET` = 1 starts the PLC in HALT (any other value: RUN);
//! `SHM_PORT` is shown in the identification.

use std::time::{Duration, Instant};

use plccoms_plc::{time, Exception, MemoryMap, WriteData};
use plccoms_plugin_abi::{export_plugin, Failure, FileInfo, Plugin};
use plccoms_protocol::Area;
use plcsim::program::{Program, ProgramKind};
use plcsim::{Device, FileStore};

const CYCLE: Duration = Duration::from_millis(10);

pub struct Demo {
    device: Device,
    program: Program,
    last_cycle: Option<Instant>,
    _files: tempfile::TempDir,
}

fn area(letter: u8) -> Result<Area, Failure> {
    Area::from_letter(letter).ok_or_else(|| refused(Exception::BadParameters))
}

fn refused(e: Exception) -> Failure {
    Failure::new(i32::from(e.to_byte()), e.to_string())
}

fn info(i: plccoms_plc::files::FileInfo) -> FileInfo {
    FileInfo {
        size: i.size,
        attributes: i.attributes,
        reserved: 0,
        created: i.created,
        modified: i.modified,
    }
}

impl Demo {
    /// Runs the program if a cycle is due.
    fn cycle(&mut self) {
        let due = self.last_cycle.is_none_or(|at| at.elapsed() >= CYCLE);
        if due && self.device.run() {
            self.program.step(&mut self.device.image, time::unix_now());
        }
        if due {
            self.last_cycle = Some(Instant::now());
        }
    }

    fn files(&mut self) -> &mut FileStore {
        self.device.files.as_mut().expect("opened with files")
    }
}

impl Plugin for Demo {
    const FILES: bool = true;

    fn open(keys: &[(String, String)]) -> Result<Self, Failure> {
        let key = |name: &str| {
            keys.iter()
                .find(|(k, _)| k == name)
                .map(|(_, v)| v.as_str())
        };
        let files = tempfile::tempdir()
            .map_err(|e| Failure::new(plccoms_plugin_abi::ERR_IO, e.to_string()))?;
        std::fs::write(files.path().join("demo.pub"), plcsim::DEMO_PUB)
            .map_err(|e| Failure::new(plccoms_plugin_abi::ERR_IO, e.to_string()))?;
        let mut device = Device::new(MemoryMap::FOXTROT);
        device.files = Some(
            FileStore::open(files.path())
                .map_err(|e| Failure::new(plccoms_plugin_abi::ERR_IO, e.to_string()))?,
        );
        let (vars, crc) = plcsim::load_pub_bytes(plcsim::DEMO_PUB);
        device.set_pf_crc(crc);
        device.set_run(key("SHM_SOCKET") != Some("1"));
        device.ident = format!(
            "CP1000    PLUGIN 1.0 port {}",
            key("SHM_PORT").unwrap_or("-")
        );
        let program = Program::new(ProgramKind::Demo, vars, &[], CYCLE.as_millis() as u64);
        let mut demo = Demo {
            device,
            program,
            last_cycle: None,
            _files: files,
        };
        demo.cycle();
        Ok(demo)
    }

    fn identify(&mut self) -> Result<Vec<u8>, Failure> {
        Ok(self.device.ident.as_bytes().to_vec())
    }

    fn status(&mut self) -> Result<bool, Failure> {
        Ok(self.device.run())
    }

    fn read(&mut self, letter: u8, offset: u32, buf: &mut [u8]) -> Result<u32, Failure> {
        self.cycle();
        let bytes = self
            .device
            .read(area(letter)?, offset, buf.len() as u32)
            .map_err(refused)?;
        buf.copy_from_slice(&bytes);
        Ok(bytes.len() as u32)
    }

    fn write(&mut self, letter: u8, offset: u32, data: &[u8]) -> Result<(), Failure> {
        self.device
            .write(area(letter)?, offset, &WriteData::Bytes(data.to_vec()))
            .map_err(refused)
    }

    fn write_bits(&mut self, letter: u8, offset: u32, mask: u8, value: u8) -> Result<(), Failure> {
        let area = area(letter)?;
        let old = self.device.read(area, offset, 1).map_err(refused)?[0];
        let new = (old & !mask) | (value & mask);
        self.device
            .write(area, offset, &WriteData::Bytes(vec![new]))
            .map_err(refused)
    }

    fn file_info(&mut self, path: &[u8]) -> Result<FileInfo, Failure> {
        self.files().info(path).map(info).map_err(refused)
    }

    fn file_read(&mut self, path: &[u8], offset: u64, buf: &mut [u8]) -> Result<u32, Failure> {
        let data = self
            .files()
            .read(path, offset, buf.len() as u32)
            .map_err(refused)?;
        buf[..data.len()].copy_from_slice(&data);
        Ok(data.len() as u32)
    }

    fn file_write(
        &mut self,
        path: &[u8],
        offset: u64,
        data: &[u8],
        last: bool,
    ) -> Result<(), Failure> {
        self.files()
            .write(path, offset, data, last)
            .map_err(refused)
    }

    fn file_write_info(&mut self, path: &[u8], i: &FileInfo) -> Result<(), Failure> {
        let i = plccoms_plc::files::FileInfo {
            size: i.size,
            attributes: i.attributes,
            created: i.created,
            modified: i.modified,
        };
        self.files().write_info(path, &i).map_err(refused)
    }

    #[allow(clippy::type_complexity)]
    fn dir_list(
        &mut self,
        path: &[u8],
        start: u32,
        max: usize,
    ) -> Result<(Vec<(Vec<u8>, FileInfo)>, bool), Failure> {
        let all = self.files().list(path).map_err(refused)?;
        let start = (start as usize).min(all.len());
        let page: Vec<_> = all[start..]
            .iter()
            .take(max)
            .map(|e| (e.name.clone(), info(e.info)))
            .collect();
        let more = start + page.len() < all.len();
        Ok((page, more))
    }
}

export_plugin!(Demo);
