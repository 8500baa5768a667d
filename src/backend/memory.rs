//! In-process backend: reads and writes a `Device` held in this process. Used
//! by tests, and by the embedded simulator when no network hop is wanted.

use std::sync::{Arc, Mutex};

use async_trait::async_trait;

use super::{
    Answer, DirEntry, FileInfo, PlcBackend, PlcError, PlcStatus, ReadRequest, WriteRequest,
};
use crate::plc::Device;

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

    fn max_read_block(&self) -> u32 {
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
            .map(|r| device.read(r.area, r.offset, r.len))
            .collect())
    }

    async fn write(&mut self, requests: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        let mut device = self.lock();
        Ok(requests
            .iter()
            .map(|r| device.write(r.area, r.offset, &r.data))
            .collect())
    }

    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        Ok(PlcStatus {
            run: self.lock().run(),
        })
    }

    async fn file_info(&mut self, _path: &[u8]) -> Result<Answer<FileInfo>, PlcError> {
        Err(PlcError::Unsupported("files"))
    }

    async fn read_file(
        &mut self,
        _path: &[u8],
        _offset: u64,
        _len: u32,
    ) -> Result<Answer<Vec<u8>>, PlcError> {
        Err(PlcError::Unsupported("files"))
    }

    async fn write_file(
        &mut self,
        _path: &[u8],
        _offset: u64,
        _data: &[u8],
        _last: bool,
    ) -> Result<Answer<()>, PlcError> {
        Err(PlcError::Unsupported("files"))
    }

    async fn write_file_info(
        &mut self,
        _path: &[u8],
        _info: &FileInfo,
    ) -> Result<Answer<()>, PlcError> {
        Err(PlcError::Unsupported("files"))
    }

    async fn list_dir(&mut self, _path: &[u8]) -> Result<Answer<Vec<DirEntry>>, PlcError> {
        Err(PlcError::Unsupported("files"))
    }
}
