//! File attributes, times and directory entries as PLCComS reports them.

pub mod host;

/// File attributes and times as PLCComS reports them (GETFILEINFO). Times are
/// the 8-byte `ttida` structure packed little-endian into a u64: year-1900,
/// month, day, hour, minute, second, 0, 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FileInfo {
    pub size: u64,
    pub attributes: u32,
    pub created: u64,
    pub modified: u64,
}

pub const FILE_ATTRIBUTE_READONLY: u32 = 0x01;
pub const FILE_ATTRIBUTE_HIDDEN: u32 = 0x02;
pub const FILE_ATTRIBUTE_SYSTEM: u32 = 0x04;
pub const FILE_ATTRIBUTE_DIRECTORY: u32 = 0x10;
pub const FILE_ATTRIBUTE_ARCHIVE: u32 = 0x20;

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DirEntry {
    /// cp1250 bytes, as the PLC names it.
    pub name: Vec<u8>,
    pub info: FileInfo,
}
