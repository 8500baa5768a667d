//! In-process backend: reads and writes a `Device` held in this process. Used
//! by tests, and by the embedded simulator when no network hop is wanted.

use std::sync::{Arc, Mutex};

use async_trait::async_trait;

use plccoms_core::driver::{
    Answer, DirEntry, FileInfo, PlcBackend, PlcError, PlcStatus, ReadRequest, Refusal, WriteRequest,
};
use plccoms_plc::epsnet::Exception;
use plcsim::{Device, FileStore};

/// Same block limit as EPSNET, so plans made against this backend are the
/// plans a real PLC gets.
pub const MAX_READ_BLOCK: u32 = 1230;
pub const MAX_FILE_BLOCK: u32 = 1150;

#[derive(Clone)]
pub struct MemoryBackend {
    device: Arc<Mutex<Device>>,
}

impl MemoryBackend {
    pub fn new(device: Arc<Mutex<Device>>) -> Self {
        MemoryBackend { device }
    }

    pub fn device(&self) -> &Arc<Mutex<Device>> {
        &self.device
    }

    /// Runs a file service on the device's file store; a device without one
    /// answers "service not activated", as a PLC without a file system would.
    /// The simulated PLC refuses in EPSNET's terms.
    fn with_files<T>(&self, f: impl FnOnce(&mut FileStore) -> Result<T, Exception>) -> Answer<T> {
        match self.lock().files.as_mut() {
            Some(files) => f(files).map_err(Refusal::Epsnet),
            None => Err(Refusal::NOT_ACTIVATED),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Device> {
        // A panic elsewhere while holding the lock leaves plain bytes behind,
        // which are still a valid image.
        self.device
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

#[async_trait]
impl PlcBackend for MemoryBackend {
    fn describe(&self) -> String {
        "in-process memory".to_string()
    }

    fn max_read_block(&self, _area: plccoms_protocol::Area) -> u32 {
        MAX_READ_BLOCK
    }

    fn max_file_block(&self) -> u32 {
        MAX_FILE_BLOCK
    }

    async fn connect(&mut self) -> Result<String, PlcError> {
        Ok(self.lock().ident.clone())
    }

    async fn read(&mut self, requests: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        let device = self.lock();
        Ok(requests
            .iter()
            .map(|r| {
                device
                    .read(r.area, r.offset, r.len)
                    .map_err(Refusal::Epsnet)
            })
            .collect())
    }

    async fn write(&mut self, requests: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        let mut device = self.lock();
        Ok(requests
            .iter()
            .map(|r| {
                device
                    .write(r.area, r.offset, &r.data)
                    .map_err(Refusal::Epsnet)
            })
            .collect())
    }

    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        Ok(PlcStatus {
            run: self.lock().run(),
        })
    }

    async fn file_info(&mut self, path: &[u8]) -> Result<Answer<FileInfo>, PlcError> {
        Ok(self.with_files(|files| files.info(path)))
    }

    async fn read_file(
        &mut self,
        path: &[u8],
        offset: u64,
        len: u32,
    ) -> Result<Answer<Vec<u8>>, PlcError> {
        if len > MAX_FILE_BLOCK {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        Ok(self.with_files(|files| files.read(path, offset, len)))
    }

    async fn write_file(
        &mut self,
        path: &[u8],
        offset: u64,
        data: &[u8],
        last: bool,
    ) -> Result<Answer<()>, PlcError> {
        if data.len() > MAX_FILE_BLOCK as usize {
            return Ok(Err(Refusal::BAD_PARAMETERS));
        }
        Ok(self.with_files(|files| files.write(path, offset, data, last)))
    }

    async fn write_file_info(
        &mut self,
        path: &[u8],
        info: &FileInfo,
    ) -> Result<Answer<()>, PlcError> {
        Ok(self.with_files(|files| files.write_info(path, info)))
    }

    async fn list_dir(&mut self, path: &[u8]) -> Result<Answer<Vec<DirEntry>>, PlcError> {
        Ok(self.with_files(|files| files.list(path)))
    }
}
