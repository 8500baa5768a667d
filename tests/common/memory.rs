//! In-process backend: reads and writes a `Device` held in this process. Used
//! by tests, and by the embedded simulator when no network hop is wanted.

use std::sync::{Arc, Mutex};

use async_trait::async_trait;

use plccoms_core::driver::{
    Answer, DirEntry, FileInfo, PlcBackend, PlcError, PlcStatus, Pushed, ReadRequest, Refusal,
    WriteRequest,
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

/// What a test adds to the in-process PLC: a hold or a delay before its
/// reads, the uncertain marks it reports. [`Hooked`] does the rest.
#[async_trait]
pub trait Hooks: Send + 'static {
    fn describe(&self) -> String;

    /// The read block (EPSNET's by default).
    fn max_read_block(&self) -> u32 {
        MAX_READ_BLOCK
    }

    /// Long enough by default that a SET a test holds back is not refused
    /// as late.
    fn answer_timeout(&self) -> std::time::Duration {
        std::time::Duration::from_secs(10)
    }

    /// Runs before each read reaches the memory.
    async fn before_read(&mut self, _requests: &[ReadRequest]) {}

    /// Runs before each write reaches the memory.
    fn before_write(&mut self, _requests: &[WriteRequest]) {}

    /// As [`PlcBackend::take_uncertain`].
    fn take_uncertain(&mut self) -> Option<Vec<Box<[u8]>>> {
        None
    }

    /// As [`PlcBackend::take_pushed`], with the memory at hand.
    fn take_pushed(&mut self, _memory: &MemoryBackend) -> Vec<Pushed> {
        Vec::new()
    }

    /// As [`PlcBackend::wait_pushed`]: never, by default.
    async fn wait_pushed(&mut self) -> Result<(), PlcError> {
        std::future::pending().await
    }
}

/// The in-process PLC with a test's [`Hooks`].
pub struct Hooked<H> {
    pub inner: MemoryBackend,
    pub hooks: H,
}

impl<H> Hooked<H> {
    /// `hooks` on a PLC of its own (a Foxtrot's memory, zeroed).
    pub fn new(hooks: H) -> Self {
        let device = Device::new(plccoms_plc::MemoryMap::FOXTROT);
        Hooked {
            inner: MemoryBackend::new(Arc::new(Mutex::new(device))),
            hooks,
        }
    }
}

#[async_trait]
impl<H: Hooks> PlcBackend for Hooked<H> {
    fn describe(&self) -> String {
        self.hooks.describe()
    }

    fn max_read_block(&self, _area: plccoms_protocol::Area) -> u32 {
        self.hooks.max_read_block()
    }

    fn max_file_block(&self) -> u32 {
        MAX_FILE_BLOCK
    }

    fn answer_timeout(&self) -> std::time::Duration {
        self.hooks.answer_timeout()
    }

    async fn connect(&mut self) -> Result<String, PlcError> {
        self.inner.connect().await
    }

    async fn read(&mut self, requests: &[ReadRequest]) -> Result<Vec<Answer<Vec<u8>>>, PlcError> {
        self.hooks.before_read(requests).await;
        self.inner.read(requests).await
    }

    async fn write(&mut self, requests: &[WriteRequest]) -> Result<Vec<Answer<()>>, PlcError> {
        self.hooks.before_write(requests);
        self.inner.write(requests).await
    }

    async fn status(&mut self) -> Result<PlcStatus, PlcError> {
        self.inner.status().await
    }

    fn take_uncertain(&mut self) -> Option<Vec<Box<[u8]>>> {
        self.hooks.take_uncertain()
    }

    fn take_pushed(&mut self) -> Vec<Pushed> {
        self.hooks.take_pushed(&self.inner)
    }

    async fn wait_pushed(&mut self) -> Result<(), PlcError> {
        self.hooks.wait_pushed().await
    }
}
