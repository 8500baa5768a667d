//! The backend plugin ABI of plccoms in Rust: the types and constants of
//! `include/plccoms_plugin.h` (which documents them), `#[repr(C)]`, for the
//! server that loads plugins and for plugins written in Rust; and, for the
//! latter, [`Plugin`] and [`export_plugin!`], which implement the C side of
//! the ABI over a Rust type.

use std::ffi::{c_char, c_void, CStr};

pub const ABI_VERSION: u32 = 1;
/// The one symbol a plugin exports.
pub const ENTRY: &[u8] = b"plccoms_plugin_entry\0";

pub const OK: i32 = 0;
pub const ERR_TIMEOUT: i32 = -1;
pub const ERR_IO: i32 = -2;
pub const ERR_PROTOCOL: i32 = -3;
pub const ERR_UNSUPPORTED: i32 = -4;

pub const ERROR_LEN: usize = 256;
pub const IDENT_LEN: usize = 64;
pub const NAME_LEN: usize = 255;

/// `plccoms_error`.
#[repr(C)]
pub struct PluginError {
    pub text: [c_char; ERROR_LEN],
}

/// `plccoms_key`.
#[repr(C)]
pub struct Key {
    pub key: *const c_char,
    pub value: *const c_char,
}

/// `plccoms_file_info`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FileInfo {
    pub size: u64,
    pub attributes: u32,
    pub reserved: u32,
    pub created: u64,
    pub modified: u64,
}

/// `plccoms_dir_entry`.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct DirEntry {
    pub info: FileInfo,
    pub name_len: u32,
    pub name: [u8; NAME_LEN],
}

impl Default for DirEntry {
    fn default() -> Self {
        DirEntry {
            info: FileInfo::default(),
            name_len: 0,
            name: [0; NAME_LEN],
        }
    }
}

pub type Handle = *mut c_void;

/// `plccoms_plugin_api`. Function pointers are `Option`s: a plugin's NULL
/// is `None` (the same representation).
#[repr(C)]
#[derive(Clone, Copy)]
pub struct PluginApi {
    pub abi_version: u32,
    pub struct_size: u32,
    pub max_read_block: u32,
    pub max_file_block: u32,
    pub open: Option<unsafe extern "C" fn(*const Key, usize, *mut Handle, *mut PluginError) -> i32>,
    pub close: Option<unsafe extern "C" fn(Handle)>,
    pub identify: Option<
        unsafe extern "C" fn(Handle, *mut c_char, usize, *mut usize, *mut PluginError) -> i32,
    >,
    pub status: Option<unsafe extern "C" fn(Handle, *mut i32, *mut PluginError) -> i32>,
    pub read: Option<
        unsafe extern "C" fn(Handle, c_char, u32, *mut u8, u32, *mut u32, *mut PluginError) -> i32,
    >,
    pub write:
        Option<unsafe extern "C" fn(Handle, c_char, u32, *const u8, u32, *mut PluginError) -> i32>,
    pub write_bits:
        Option<unsafe extern "C" fn(Handle, c_char, u32, u8, u8, *mut PluginError) -> i32>,
    pub file_info: Option<
        unsafe extern "C" fn(Handle, *const u8, usize, *mut FileInfo, *mut PluginError) -> i32,
    >,
    #[allow(clippy::type_complexity)]
    pub file_read: Option<
        unsafe extern "C" fn(
            Handle,
            *const u8,
            usize,
            u64,
            *mut u8,
            u32,
            *mut u32,
            *mut PluginError,
        ) -> i32,
    >,
    #[allow(clippy::type_complexity)]
    pub file_write: Option<
        unsafe extern "C" fn(
            Handle,
            *const u8,
            usize,
            u64,
            *const u8,
            u32,
            i32,
            *mut PluginError,
        ) -> i32,
    >,
    pub file_write_info: Option<
        unsafe extern "C" fn(Handle, *const u8, usize, *const FileInfo, *mut PluginError) -> i32,
    >,
    #[allow(clippy::type_complexity)]
    pub dir_list: Option<
        unsafe extern "C" fn(
            Handle,
            *const u8,
            usize,
            u32,
            *mut DirEntry,
            u32,
            *mut u32,
            *mut i32,
            *mut PluginError,
        ) -> i32,
    >,
}

/// `plccoms_plugin_entry`.
pub type EntryFn = unsafe extern "C" fn(u32) -> *const PluginApi;

// ---------------------------------------------------------------------------
// Plugins in Rust.

/// Why a call failed: a status (an EPSNET error byte 1..=255 or an `ERR_*`)
/// and a message.
#[derive(Debug, Clone)]
pub struct Failure {
    pub status: i32,
    pub text: String,
}

impl Failure {
    pub fn new(status: i32, text: impl Into<String>) -> Failure {
        Failure {
            status,
            text: text.into(),
        }
    }
}

/// A PLC reached by a plugin: implement it and [`export_plugin!`] the type.
/// Areas are the letters `X`, `Y`, `S`, `R`; paths are bytes.
pub trait Plugin: Sized + 'static {
    /// Largest read or write block; 0: 1230.
    const MAX_READ_BLOCK: u32 = 0;
    /// Whether the file services are there.
    const FILES: bool = false;

    fn open(keys: &[(String, String)]) -> Result<Self, Failure>;
    fn identify(&mut self) -> Result<Vec<u8>, Failure>;
    fn status(&mut self) -> Result<bool, Failure>;
    /// Fills `buf`; returns the bytes written.
    fn read(&mut self, area: u8, offset: u32, buf: &mut [u8]) -> Result<u32, Failure>;
    fn write(&mut self, area: u8, offset: u32, data: &[u8]) -> Result<(), Failure>;
    fn write_bits(&mut self, area: u8, offset: u32, mask: u8, value: u8) -> Result<(), Failure>;

    fn file_info(&mut self, _path: &[u8]) -> Result<FileInfo, Failure> {
        Err(unsupported())
    }
    /// Fills `buf` from `offset`; returns the bytes written.
    fn file_read(&mut self, _path: &[u8], _offset: u64, _buf: &mut [u8]) -> Result<u32, Failure> {
        Err(unsupported())
    }
    fn file_write(
        &mut self,
        _path: &[u8],
        _offset: u64,
        _data: &[u8],
        _last: bool,
    ) -> Result<(), Failure> {
        Err(unsupported())
    }
    fn file_write_info(&mut self, _path: &[u8], _info: &FileInfo) -> Result<(), Failure> {
        Err(unsupported())
    }
    /// Up to `max` entries from `start`: (name, info), and whether more follow.
    #[allow(clippy::type_complexity)]
    fn dir_list(
        &mut self,
        _path: &[u8],
        _start: u32,
        _max: usize,
    ) -> Result<(Vec<(Vec<u8>, FileInfo)>, bool), Failure> {
        Err(unsupported())
    }

    /// The table the entry hands out; a plugin may hand out another (tests
    /// of the server's checks do).
    fn entry(api: &'static PluginApi, abi_version: u32) -> *const PluginApi {
        if abi_version == ABI_VERSION {
            api
        } else {
            std::ptr::null()
        }
    }
}

fn unsupported() -> Failure {
    Failure::new(ERR_UNSUPPORTED, "not supported by this plugin")
}

/// The C side of [`Plugin`]: `extern "C"` functions over the type `P`.
/// Panics become `ERR_PROTOCOL`, never unwind into the server.
pub mod adapter {
    use super::*;
    use std::panic::{catch_unwind, AssertUnwindSafe};

    /// # Safety
    /// `err` is null or points to a `PluginError`.
    unsafe fn report(err: *mut PluginError, result: Result<(), Failure>) -> i32 {
        match result {
            Ok(()) => OK,
            Err(failure) => {
                if let Some(err) = err.as_mut() {
                    let bytes = failure.text.as_bytes();
                    let n = bytes.len().min(ERROR_LEN - 1);
                    for (dst, src) in err.text.iter_mut().zip(&bytes[..n]) {
                        *dst = *src as c_char;
                    }
                    err.text[n] = 0;
                }
                failure.status
            }
        }
    }

    fn guarded(f: impl FnOnce() -> Result<(), Failure>) -> Result<(), Failure> {
        catch_unwind(AssertUnwindSafe(f))
            .unwrap_or_else(|_| Err(Failure::new(ERR_PROTOCOL, "the plugin panicked")))
    }

    /// # Safety
    /// `handle` came from [`open`] for the same `P` and is not closed.
    unsafe fn plugin<'a, P>(handle: Handle) -> &'a mut P {
        &mut *(handle as *mut P)
    }

    /// # Safety
    /// `path` points to `len` bytes (or `len` is 0).
    unsafe fn bytes<'a>(path: *const u8, len: usize) -> &'a [u8] {
        if len == 0 {
            &[]
        } else {
            std::slice::from_raw_parts(path, len)
        }
    }

    /// # Safety
    /// As the header says.
    pub unsafe extern "C" fn open<P: Plugin>(
        keys: *const Key,
        count: usize,
        handle: *mut Handle,
        err: *mut PluginError,
    ) -> i32 {
        let result = guarded(|| {
            let keys: Vec<(String, String)> = (0..count)
                .map(|i| {
                    let k = &*keys.add(i);
                    let text = |p: *const c_char| CStr::from_ptr(p).to_string_lossy().into_owned();
                    (text(k.key), text(k.value))
                })
                .collect();
            let plugin = P::open(&keys)?;
            *handle = Box::into_raw(Box::new(plugin)) as Handle;
            Ok(())
        });
        report(err, result)
    }

    /// # Safety
    /// As the header says.
    pub unsafe extern "C" fn close<P: Plugin>(handle: Handle) {
        if !handle.is_null() {
            drop(Box::from_raw(handle as *mut P));
        }
    }

    /// # Safety
    /// As the header says.
    pub unsafe extern "C" fn identify<P: Plugin>(
        handle: Handle,
        buf: *mut c_char,
        cap: usize,
        len: *mut usize,
        err: *mut PluginError,
    ) -> i32 {
        let result = guarded(|| {
            let ident = plugin::<P>(handle).identify()?;
            let n = ident.len().min(cap);
            std::ptr::copy_nonoverlapping(ident.as_ptr(), buf as *mut u8, n);
            // The real length, even past `cap`: the server checks.
            *len = ident.len();
            Ok(())
        });
        report(err, result)
    }

    /// # Safety
    /// As the header says.
    pub unsafe extern "C" fn status<P: Plugin>(
        handle: Handle,
        run: *mut i32,
        err: *mut PluginError,
    ) -> i32 {
        let result = guarded(|| {
            *run = i32::from(plugin::<P>(handle).status()?);
            Ok(())
        });
        report(err, result)
    }

    /// # Safety
    /// As the header says.
    pub unsafe extern "C" fn read<P: Plugin>(
        handle: Handle,
        area: c_char,
        offset: u32,
        buf: *mut u8,
        len: u32,
        got: *mut u32,
        err: *mut PluginError,
    ) -> i32 {
        let result = guarded(|| {
            let buf = std::slice::from_raw_parts_mut(buf, len as usize);
            *got = plugin::<P>(handle).read(area as u8, offset, buf)?;
            Ok(())
        });
        report(err, result)
    }

    /// # Safety
    /// As the header says.
    pub unsafe extern "C" fn write<P: Plugin>(
        handle: Handle,
        area: c_char,
        offset: u32,
        data: *const u8,
        len: u32,
        err: *mut PluginError,
    ) -> i32 {
        let result =
            guarded(|| plugin::<P>(handle).write(area as u8, offset, bytes(data, len as usize)));
        report(err, result)
    }

    /// # Safety
    /// As the header says.
    pub unsafe extern "C" fn write_bits<P: Plugin>(
        handle: Handle,
        area: c_char,
        offset: u32,
        mask: u8,
        value: u8,
        err: *mut PluginError,
    ) -> i32 {
        let result = guarded(|| plugin::<P>(handle).write_bits(area as u8, offset, mask, value));
        report(err, result)
    }

    /// # Safety
    /// As the header says.
    pub unsafe extern "C" fn file_info<P: Plugin>(
        handle: Handle,
        path: *const u8,
        path_len: usize,
        info: *mut FileInfo,
        err: *mut PluginError,
    ) -> i32 {
        let result = guarded(|| {
            *info = plugin::<P>(handle).file_info(bytes(path, path_len))?;
            Ok(())
        });
        report(err, result)
    }

    /// # Safety
    /// As the header says.
    #[allow(clippy::too_many_arguments)]
    pub unsafe extern "C" fn file_read<P: Plugin>(
        handle: Handle,
        path: *const u8,
        path_len: usize,
        offset: u64,
        buf: *mut u8,
        cap: u32,
        len: *mut u32,
        err: *mut PluginError,
    ) -> i32 {
        let result = guarded(|| {
            let buf = std::slice::from_raw_parts_mut(buf, cap as usize);
            *len = plugin::<P>(handle).file_read(bytes(path, path_len), offset, buf)?;
            Ok(())
        });
        report(err, result)
    }

    /// # Safety
    /// As the header says.
    #[allow(clippy::too_many_arguments)]
    pub unsafe extern "C" fn file_write<P: Plugin>(
        handle: Handle,
        path: *const u8,
        path_len: usize,
        offset: u64,
        data: *const u8,
        len: u32,
        last: i32,
        err: *mut PluginError,
    ) -> i32 {
        let result = guarded(|| {
            plugin::<P>(handle).file_write(
                bytes(path, path_len),
                offset,
                bytes(data, len as usize),
                last != 0,
            )
        });
        report(err, result)
    }

    /// # Safety
    /// As the header says.
    pub unsafe extern "C" fn file_write_info<P: Plugin>(
        handle: Handle,
        path: *const u8,
        path_len: usize,
        info: *const FileInfo,
        err: *mut PluginError,
    ) -> i32 {
        let result = guarded(|| plugin::<P>(handle).file_write_info(bytes(path, path_len), &*info));
        report(err, result)
    }

    /// # Safety
    /// As the header says.
    #[allow(clippy::too_many_arguments)]
    pub unsafe extern "C" fn dir_list<P: Plugin>(
        handle: Handle,
        path: *const u8,
        path_len: usize,
        start: u32,
        entries: *mut DirEntry,
        cap: u32,
        count: *mut u32,
        more: *mut i32,
        err: *mut PluginError,
    ) -> i32 {
        let result = guarded(|| {
            let (list, has_more) =
                plugin::<P>(handle).dir_list(bytes(path, path_len), start, cap as usize)?;
            let out = std::slice::from_raw_parts_mut(entries, cap as usize);
            for (slot, (name, info)) in out.iter_mut().zip(&list) {
                let n = name.len().min(NAME_LEN);
                slot.info = *info;
                slot.name_len = n as u32;
                slot.name[..n].copy_from_slice(&name[..n]);
            }
            *count = list.len().min(cap as usize) as u32;
            *more = i32::from(has_more || list.len() > cap as usize);
            Ok(())
        });
        report(err, result)
    }
}

/// Exports `plccoms_plugin_entry` for a type implementing [`Plugin`].
#[macro_export]
macro_rules! export_plugin {
    ($ty:ty) => {
        static PLCCOMS_PLUGIN_API: $crate::PluginApi = $crate::PluginApi {
            abi_version: $crate::ABI_VERSION,
            struct_size: ::std::mem::size_of::<$crate::PluginApi>() as u32,
            max_read_block: <$ty as $crate::Plugin>::MAX_READ_BLOCK,
            max_file_block: 0,
            open: Some($crate::adapter::open::<$ty>),
            close: Some($crate::adapter::close::<$ty>),
            identify: Some($crate::adapter::identify::<$ty>),
            status: Some($crate::adapter::status::<$ty>),
            read: Some($crate::adapter::read::<$ty>),
            write: Some($crate::adapter::write::<$ty>),
            write_bits: Some($crate::adapter::write_bits::<$ty>),
            file_info: if <$ty as $crate::Plugin>::FILES {
                Some($crate::adapter::file_info::<$ty>)
            } else {
                None
            },
            file_read: if <$ty as $crate::Plugin>::FILES {
                Some($crate::adapter::file_read::<$ty>)
            } else {
                None
            },
            file_write: if <$ty as $crate::Plugin>::FILES {
                Some($crate::adapter::file_write::<$ty>)
            } else {
                None
            },
            file_write_info: if <$ty as $crate::Plugin>::FILES {
                Some($crate::adapter::file_write_info::<$ty>)
            } else {
                None
            },
            dir_list: if <$ty as $crate::Plugin>::FILES {
                Some($crate::adapter::dir_list::<$ty>)
            } else {
                None
            },
        };

        /// The plugin's one export (see plccoms_plugin.h).
        #[no_mangle]
        pub extern "C" fn plccoms_plugin_entry(abi_version: u32) -> *const $crate::PluginApi {
            <$ty as $crate::Plugin>::entry(&PLCCOMS_PLUGIN_API, abi_version)
        }
    };
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::{offset_of, size_of};

    /// The C compiler's sizes and offsets of the header's structs (the
    /// machine's `cc`, which Rust's toolchain needs as its linker anyway).
    fn c_layout() -> Vec<usize> {
        let dir = std::env::temp_dir().join(format!("plccoms-abi-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let source = dir.join("layout.c");
        let exe = dir.join("layout");
        std::fs::write(
            &source,
            r#"#include <stdio.h>
#include <stddef.h>
#include "plccoms_plugin.h"
int main(void) {
    printf("%zu %zu %zu %zu %zu %zu %zu %zu %zu\n",
        sizeof(plccoms_error), sizeof(plccoms_key), sizeof(plccoms_file_info),
        sizeof(plccoms_dir_entry), offsetof(plccoms_dir_entry, name),
        sizeof(plccoms_plugin_api), offsetof(plccoms_plugin_api, open),
        offsetof(plccoms_plugin_api, write_bits), offsetof(plccoms_plugin_api, dir_list));
    return 0;
}
"#,
        )
        .unwrap();
        let include = concat!(env!("CARGO_MANIFEST_DIR"), "/include");
        let status = std::process::Command::new("cc")
            .args(["-std=c99", "-Wall", "-Werror", "-I", include, "-o"])
            .arg(&exe)
            .arg(&source)
            .status()
            .expect("run cc");
        assert!(status.success(), "the header does not compile");
        let out = std::process::Command::new(&exe).output().unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        String::from_utf8(out.stdout)
            .unwrap()
            .split_whitespace()
            .map(|n| n.parse().unwrap())
            .collect()
    }

    #[test]
    fn the_header_and_these_types_agree() {
        assert_eq!(
            c_layout(),
            [
                size_of::<PluginError>(),
                size_of::<Key>(),
                size_of::<FileInfo>(),
                size_of::<DirEntry>(),
                offset_of!(DirEntry, name),
                size_of::<PluginApi>(),
                offset_of!(PluginApi, open),
                offset_of!(PluginApi, write_bits),
                offset_of!(PluginApi, dir_list),
            ]
        );
    }
}
