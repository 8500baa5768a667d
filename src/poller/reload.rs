//! Where a section's public files come from, and building its variable table
//! from them: at start-up, when the PLC's program changes (`__PF_CRC`), and on
//! `SETCONF:pubfile` or a new PLC address.

use std::path::{Path, PathBuf};

use tracing::{info, warn};

use crate::backend::PlcBackend;
use crate::config::Section;
use crate::vars::VarTable;
use plccoms_plc::pubfile::{self, PubFile};
use plccoms_plc::MemoryMap;

/// Largest public file fetched from a PLC.
const MAX_PUBFILE: u64 = 64 * 1024 * 1024;

/// The standard fixed public file, used when PUBFILE_FIXED is not set.
pub const STANDARD_FIXED: &[u8] =
    b" __PLC_RUN S B 2 .2 BOOL PUB_INOUT\r\n __PF_CRC S B 70 DWORD PUB_INOUT\r\n";

/// A user public file as loaded: its name (as GETINFO and warnings show it)
/// and its bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UserFile {
    pub name: String,
    pub bytes: Vec<u8>,
}

/// Everything needed to (re)load a section's public files.
#[derive(Debug, Clone)]
pub struct PubSource {
    pub section: Section,
    /// The configuration file's folder.
    pub dir: PathBuf,
    pub fixed_name: String,
    pub fixed: PubFile,
}

impl PubSource {
    /// Reads the fixed file (PUBFILE_FIXED beside the configuration, or the
    /// standard one when the key is not set).
    pub fn new(section: &Section, dir: &Path) -> Result<PubSource, String> {
        let (fixed_name, fixed) = match &section.pubfile_fixed {
            Some(name) => {
                let path = dir.join(name);
                let file = pubfile::load(&path)
                    .map_err(|e| format!("fixed public file {}: {e}", path.display()))?;
                (name.clone(), file)
            }
            None => ("FIXED.pub".to_string(), pubfile::parse(STANDARD_FIXED)),
        };
        Ok(PubSource {
            section: section.clone(),
            dir: dir.to_path_buf(),
            fixed_name,
            fixed,
        })
    }

    /// Where a PUBFILE value lives on this machine: `//name` in the root
    /// folder (the configuration's, or the section's subfolder with
    /// PUBFILE_WRITE), anything else relative to the configuration.
    pub fn local_path(&self, name: &str) -> PathBuf {
        let root = if self.section.pubfile_write {
            self.dir.join(&self.section.name)
        } else {
            self.dir.clone()
        };
        match name.strip_prefix("//") {
            Some(rest) => root.join(rest),
            None => self.dir.join(name),
        }
    }

    /// The user public file: the local file if there is one, else fetched
    /// from the PLC (and stored locally with PUBFILE_WRITE). `None` when the
    /// section names none.
    pub async fn load_user(
        &self,
        backend: Option<&mut (dyn PlcBackend + 'static)>,
    ) -> Result<Option<UserFile>, String> {
        let Some(name) = &self.section.pubfile else {
            return Ok(None);
        };
        let local = self.local_path(name);
        let display = file_name(name);
        if local.is_file() {
            let bytes = std::fs::read(&local)
                .map_err(|e| format!("public file {}: {e}", local.display()))?;
            return Ok(Some(UserFile {
                name: display,
                bytes,
            }));
        }
        if name.starts_with("../") {
            return Err(format!(
                "public file {} not found (paths starting with ../ are local only)",
                local.display()
            ));
        }
        let Some(backend) = backend else {
            return Err(format!(
                "public file {} not found, and there is no PLC to fetch it from",
                local.display()
            ));
        };
        let bytes = fetch_file(backend, plc_path(name).as_bytes())
            .await
            .map_err(|e| {
                format!(
                    "public file {name} is neither at {} nor readable from the PLC: {e}",
                    local.display()
                )
            })?;
        info!(section = %self.section.name, "public file {name} fetched from the PLC ({} bytes)", bytes.len());
        if self.section.pubfile_write {
            if let Some(parent) = local.parent() {
                let _ = std::fs::create_dir_all(parent);
            }
            if let Err(e) = std::fs::write(&local, &bytes) {
                warn!(section = %self.section.name, "cannot store {}: {e}", local.display());
            }
        }
        Ok(Some(UserFile {
            name: display,
            bytes,
        }))
    }

    /// The variable table of the fixed file and `user`; bad lines are logged.
    pub fn build(&self, user: Option<&UserFile>) -> Result<VarTable, String> {
        let parsed = user.map(|u| (u.name.as_str(), pubfile::parse(&u.bytes)));
        let mut warnings = Vec::new();
        let table = VarTable::build(
            &self.fixed_name,
            &self.fixed,
            parsed.as_ref().map(|(name, file)| (*name, file)),
            &MemoryMap::FOXTROT,
            &mut warnings,
        )
        .map_err(|e| e.to_string())?;
        for warning in &warnings {
            warn!(section = %self.section.name, "public file {warning}");
        }
        Ok(table)
    }
}

/// The CRC that `__PF_CRC` must match for `user` (PUBFILE_CRC): its trailer.
pub fn trailer_crc(user: &UserFile) -> Option<u32> {
    pubfile::parse(&user.bytes).crc
}

/// The name a PUBFILE value has in the PLC's file system.
pub fn plc_path(name: &str) -> &str {
    name.trim_start_matches('/')
}

fn file_name(name: &str) -> String {
    name.rsplit(['/', '\\']).next().unwrap_or(name).to_string()
}

/// Reads a whole file from the PLC's file system.
pub async fn fetch_file(backend: &mut dyn PlcBackend, path: &[u8]) -> Result<Vec<u8>, String> {
    backend.connect().await.map_err(|e| e.to_string())?;
    let info = backend
        .file_info(path)
        .await
        .map_err(|e| e.to_string())?
        .map_err(|e| format!("the PLC answered {e}"))?;
    if info.size > MAX_PUBFILE {
        return Err(format!(
            "{} bytes is more than the {MAX_PUBFILE} accepted",
            info.size
        ));
    }
    let block = backend.max_file_block().max(1);
    let mut bytes = Vec::with_capacity(info.size as usize);
    loop {
        let chunk = backend
            .read_file(path, bytes.len() as u64, block)
            .await
            .map_err(|e| e.to_string())?
            .map_err(|e| format!("the PLC answered {e}"))?;
        let done = (chunk.len() as u32) < block;
        bytes.extend_from_slice(&chunk);
        if done || bytes.len() as u64 >= info.size {
            break;
        }
        if bytes.len() as u64 > MAX_PUBFILE {
            return Err("the file grew past the accepted size while reading".to_string());
        }
    }
    Ok(bytes)
}
