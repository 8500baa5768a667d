//! A deliberately bad backend plugin, for the tests of the server's side of
//! the plugin ABI. A memory of 64 KiB per area that misbehaves as the
//! section's `SHM_SOCKET` says:
//!
//! | SHM_SOCKET | behaviour |
//! |---|---|
//! | 0 | good |
//! | 1 | wrong lengths: reads report one byte less than asked |
//! | 2 | bad codes: reads answer status 1000, writes -77, SETs of bits the EPSNET byte 0x0C with an unterminated 256-byte message |
//! | 3 | slow: every read sleeps `SHM_PORT` ms (default 5000) |
//! | 4 | crash: reads sleep `SHM_PORT` ms (default 0), then dereference NULL |
//! | 5 | open fails with an I/O error and a message |
//! | 6 | the identification is longer than its buffer |
//! | 7 | refusing writes: reads good, writes and SETs of bits as in 2 |
//!
//! and `BAD_PLUGIN_ENTRY` in the environment: `null` (no table), `version`
//! (ABI version 99), `short` (a struct_size too small), `nofn` (no read).

use std::time::Duration;

use plccoms_plugin_abi::{export_plugin, Failure, Plugin, PluginApi, ABI_VERSION, ERR_IO};

const SIZE: usize = 65536;

pub struct Bad {
    mode: u32,
    delay: Duration,
    memory: Vec<u8>,
}

impl Plugin for Bad {
    fn open(keys: &[(String, String)]) -> Result<Self, Failure> {
        let key = |name: &str| {
            keys.iter()
                .find(|(k, _)| k == name)
                .and_then(|(_, v)| v.parse::<u64>().ok())
        };
        let mode = key("SHM_SOCKET").unwrap_or(0) as u32;
        if mode == 5 {
            return Err(Failure::new(ERR_IO, "bad plugin: no PLC on this bus"));
        }
        Ok(Bad {
            mode,
            delay: Duration::from_millis(key("SHM_PORT").unwrap_or(if mode == 3 {
                5000
            } else {
                0
            })),
            memory: vec![0; SIZE * 4],
        })
    }

    fn identify(&mut self) -> Result<Vec<u8>, Failure> {
        if self.mode == 6 {
            return Ok(vec![b'X'; 200]);
        }
        Ok(b"BAD PLUGIN 1.0".to_vec())
    }

    fn status(&mut self) -> Result<bool, Failure> {
        Ok(true)
    }

    fn read(&mut self, area: u8, offset: u32, buf: &mut [u8]) -> Result<u32, Failure> {
        match self.mode {
            1 => return Ok(buf.len() as u32 - 1),
            2 => return Err(Failure::new(1000, "status out of range")),
            3 => std::thread::sleep(self.delay),
            4 => {
                std::thread::sleep(self.delay);
                // SAFETY: none: this plugin crashes on purpose.
                unsafe {
                    let null: *mut u8 = std::ptr::null_mut();
                    std::ptr::write_volatile(null, 1);
                }
            }
            _ => {}
        }
        let at = slot(area, offset, buf.len())?;
        buf.copy_from_slice(&self.memory[at..at + buf.len()]);
        Ok(buf.len() as u32)
    }

    fn write(&mut self, area: u8, offset: u32, data: &[u8]) -> Result<(), Failure> {
        if matches!(self.mode, 2 | 7) {
            return Err(Failure::new(-77, "a status no one defined"));
        }
        let at = slot(area, offset, data.len())?;
        self.memory[at..at + data.len()].copy_from_slice(data);
        Ok(())
    }

    fn write_bits(&mut self, area: u8, offset: u32, mask: u8, value: u8) -> Result<(), Failure> {
        if matches!(self.mode, 2 | 7) {
            // Longer than the message buffer: the adapter cuts it and ends it.
            return Err(Failure::new(0x0C, "x".repeat(1000)));
        }
        let at = slot(area, offset, 1)?;
        self.memory[at] = (self.memory[at] & !mask) | (value & mask);
        Ok(())
    }

    fn entry(api: &'static PluginApi, abi_version: u32) -> *const PluginApi {
        let bad = |api: PluginApi| Box::leak(Box::new(api)) as *const PluginApi;
        match std::env::var("BAD_PLUGIN_ENTRY").as_deref() {
            Ok("null") => std::ptr::null(),
            Ok("version") => bad(PluginApi {
                abi_version: 99,
                ..*api
            }),
            Ok("short") => bad(PluginApi {
                struct_size: 8,
                ..*api
            }),
            Ok("nofn") => bad(PluginApi { read: None, ..*api }),
            _ if abi_version == ABI_VERSION => api,
            _ => std::ptr::null(),
        }
    }
}

/// Where `len` bytes of `area` at `offset` are, or the PLC's "out of range".
fn slot(area: u8, offset: u32, len: usize) -> Result<usize, Failure> {
    let index = match area {
        b'X' => 0,
        b'Y' => 1,
        b'S' => 2,
        b'R' => 3,
        _ => return Err(Failure::new(0x0C, "no such area")),
    };
    let offset = offset as usize;
    if offset + len > SIZE {
        return Err(Failure::new(0x0C, "out of range"));
    }
    Ok(index * SIZE + offset)
}

export_plugin!(Bad);
