//! The variable table of one PLC section: the fixed public file's variables
//! followed by the user's (a public file, or a Modbus tag file), looked up by
//! upper-case cp1250 name. Each variable carries its [`Codec`]: how its bytes
//! become the client's value and back ([`Var::decode`], [`Var::encode`], the
//! one place for both).

use std::hash::BuildHasher;

use plccoms_protocol::{cp1250, Mask};

use plccoms_plc::modbus::tags::TagFile;
use plccoms_plc::pubfile::{self, PubFile};
pub use plccoms_plc::value_codec::{Codec, EncodeError};
/// A table's variable (its name upper case, as the server prints it), and
/// a file's (name as written, with its line).
pub use plccoms_plc::var::{Var, VarDef, VarInfo};
use plccoms_plc::MemoryMap;

/// Index of a variable in its table.
pub type VarId = u32;

pub const PLC_RUN: &[u8] = b"__PLC_RUN";
pub const PF_CRC: &[u8] = b"__PF_CRC";

/// The standard fixed public file, used when PUBFILE_FIXED is not set.
pub const STANDARD_FIXED: &[u8] =
    b" __PLC_RUN S B 2 .2 BOOL PUB_INOUT\r\n __PF_CRC S B 70 DWORD PUB_INOUT\r\n";

/// The variables of a file and its warnings, ready for [`VarTable::build`].
#[derive(Debug, Clone, Default)]
pub struct VarFile {
    pub vars: Vec<VarDef>,
    pub warnings: Vec<String>,
    /// Problems beyond `warnings`, counted only.
    pub more_warnings: usize,
    /// The line of the first variable past [`pubfile::MAX_VARS`]: the file
    /// is refused.
    pub too_many: Option<usize>,
}

impl From<&PubFile> for VarFile {
    fn from(file: &PubFile) -> VarFile {
        VarFile {
            vars: file.vars.clone(),
            warnings: file.warnings.iter().map(|w| w.to_string()).collect(),
            more_warnings: file.more_warnings,
            too_many: file.too_many,
        }
    }
}

impl From<&TagFile> for VarFile {
    fn from(file: &TagFile) -> VarFile {
        let vars = file.tags.iter().map(|t| (t.var(), t.line));
        VarFile::of_tags(vars, &file.warnings, file.more_warnings, file.too_many)
    }
}

impl From<&plccoms_plc::s7::tags::TagFile> for VarFile {
    fn from(file: &plccoms_plc::s7::tags::TagFile) -> VarFile {
        let vars = file.tags.iter().map(|t| (t.var(), t.line));
        VarFile::of_tags(vars, &file.warnings, file.more_warnings, file.too_many)
    }
}

impl VarFile {
    /// A tag file's variables (with their lines) and problems.
    fn of_tags(
        vars: impl Iterator<Item = (Var, usize)>,
        warnings: &[plccoms_plc::modbus::tags::TagWarning],
        more_warnings: usize,
        too_many: Option<usize>,
    ) -> VarFile {
        VarFile {
            vars: vars.map(|(var, line)| VarDef { var, line }).collect(),
            warnings: warnings.iter().map(|w| w.to_string()).collect(),
            more_warnings,
            too_many,
        }
    }
}

impl From<&plccoms_plc::opcua::tags::TagFile> for VarFile {
    fn from(file: &plccoms_plc::opcua::tags::TagFile) -> VarFile {
        VarFile {
            vars: file.var_defs(),
            warnings: file.warnings.iter().map(|w| w.to_string()).collect(),
            more_warnings: file.more_warnings,
            too_many: file.too_many,
        }
    }
}

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum TableError {
    #[error("fixed public file '{file}' does not define {name}")]
    MissingFixed { file: String, name: &'static str },
    #[error("'{file}' line {line}: more than {max} variables, the most a file may define; the file is refused", max = pubfile::MAX_VARS)]
    TooManyVars { file: String, line: usize },
}

#[derive(Debug, Default)]
pub struct VarTable {
    vars: Vec<Var>,
    /// Ids by folded name, the name read from `vars`: 5 bytes a bucket
    /// instead of a second copy of every name as the key (65 bytes a
    /// variable at 100,000, `tests/memory_per_var.rs`).
    index: hashbrown::HashTable<VarId>,
    /// foldhash rather than SipHash: every GET, SET and EN looks a name up,
    /// and the names come from the public file, not from clients, so
    /// collision flooding is not a concern (seeded per process all the
    /// same).
    hasher: foldhash::fast::RandomState,
    fixed_count: usize,
    plc_run: VarId,
    pf_crc: VarId,
    /// The longest name: no mask with more characters matches anything.
    max_name_len: usize,
    /// Names of the files the table was built from, for GETINFO and warnings.
    pub fixed_file: String,
    pub user_file: Option<String>,
}

impl VarTable {
    /// Builds the table from public files: fixed variables first, then the
    /// user's; on a name clash the fixed file wins. Variables whose address
    /// lies outside `map` are skipped with a warning, like any other bad
    /// public-file line.
    pub fn build(
        fixed_file: &str,
        fixed: &PubFile,
        user: Option<(&str, &PubFile)>,
        map: &MemoryMap,
        warnings: &mut Vec<String>,
    ) -> Result<VarTable, TableError> {
        let user = user.map(|(name, file)| (name, VarFile::from(file)));
        VarTable::build_from(
            fixed_file,
            &VarFile::from(fixed),
            user.as_ref().map(|(name, file)| (*name, file)),
            map,
            warnings,
        )
    }

    /// The standard fixed variables and the public file `text` of a
    /// Foxtrot, warnings dropped: a table without a PLC, for tests, tools
    /// and benchmarks.
    pub fn from_public_text(name: &str, text: &[u8]) -> Result<VarTable, TableError> {
        let fixed = plccoms_plc::pubfile::parse(STANDARD_FIXED);
        let user = plccoms_plc::pubfile::parse(text);
        VarTable::build(
            "FIXED.pub",
            &fixed,
            Some((name, &user)),
            &MemoryMap::FOXTROT,
            &mut Vec::new(),
        )
    }

    /// Builds the table from any files' variables, as [`VarTable::build`].
    pub fn build_from(
        fixed_file: &str,
        fixed: &VarFile,
        user: Option<(&str, &VarFile)>,
        map: &MemoryMap,
        warnings: &mut Vec<String>,
    ) -> Result<VarTable, TableError> {
        for (name, file) in [(fixed_file, fixed)].into_iter().chain(user) {
            if let Some(line) = file.too_many {
                return Err(TableError::TooManyVars {
                    file: name.to_string(),
                    line,
                });
            }
        }
        let mut table = VarTable {
            fixed_file: fixed_file.to_string(),
            user_file: user.map(|(name, _)| name.to_string()),
            ..VarTable::default()
        };
        table.add_file(fixed_file, fixed, true, map, warnings);
        table.fixed_count = table.vars.len();
        if let Some((name, file)) = user {
            table.add_file(name, file, false, map, warnings);
        }
        table.plc_run = table.require(fixed_file, PLC_RUN, "__PLC_RUN")?;
        table.pf_crc = table.require(fixed_file, PF_CRC, "__PF_CRC")?;
        Ok(table)
    }

    fn require(&self, file: &str, name: &[u8], display: &'static str) -> Result<VarId, TableError> {
        match self.get(name) {
            Some(id) if (id as usize) < self.fixed_count => Ok(id),
            _ => Err(TableError::MissingFixed {
                file: file.to_string(),
                name: display,
            }),
        }
    }

    fn add_file(
        &mut self,
        file_name: &str,
        file: &VarFile,
        fixed: bool,
        map: &MemoryMap,
        warnings: &mut Vec<String>,
    ) {
        for warning in &file.warnings {
            warnings.push(format!("{file_name}: {warning}"));
        }
        self.vars.reserve(file.vars.len());
        let (vars, hasher) = (&self.vars, &self.hasher);
        self.index.reserve(file.vars.len(), |&id| {
            hasher.hash_one(&vars[id as usize].name[..])
        });
        for def in &file.vars {
            let pv = &def.var;
            let name: Box<[u8]> = cp1250::to_upper(&pv.name).into_boxed_slice();
            if !map.contains(pv.area, pv.offset, pv.codec.byte_len(pv.ty)) {
                warnings.push(format!(
                    "{file_name}: line {}: {} at {}{} is outside the PLC memory (size {}), skipped",
                    def.line,
                    cp1250::decode(&name),
                    pv.area,
                    pv.offset,
                    map.size(pv.area)
                ));
                continue;
            }
            if let Some(existing) = self.get(&name) {
                // fixed_count is set once the fixed file is in.
                let winner = if (existing as usize) < self.fixed_count && !fixed {
                    "the fixed file's variable wins"
                } else {
                    "the first definition wins"
                };
                warnings.push(format!(
                    "{file_name}: line {}: {} is defined twice, {winner}",
                    def.line,
                    cp1250::decode(&name)
                ));
                continue;
            }
            let id = self.vars.len() as VarId;
            self.max_name_len = self.max_name_len.max(name.len());
            let hash = self.hasher.hash_one(&name[..]);
            self.vars.push(Var { name, ..pv.clone() });
            let (vars, hasher) = (&self.vars, &self.hasher);
            self.index
                .insert_unique(hash, id, |&id| hasher.hash_one(&vars[id as usize].name[..]));
        }
    }

    /// The id of the variable named `name` (folded already).
    fn get(&self, name: &[u8]) -> Option<VarId> {
        let hash = self.hasher.hash_one(name);
        self.index
            .find(hash, |&id| &self.vars[id as usize].name[..] == name)
            .copied()
    }

    pub fn len(&self) -> usize {
        self.vars.len()
    }

    pub fn is_empty(&self) -> bool {
        self.vars.is_empty()
    }

    pub fn fixed_count(&self) -> usize {
        self.fixed_count
    }

    pub fn max_name_len(&self) -> usize {
        self.max_name_len
    }

    pub fn var(&self, id: VarId) -> &Var {
        &self.vars[id as usize]
    }

    /// The variables whose names match any of `masks` (`*` wildcards, any
    /// case), in table order.
    pub fn matching<M: AsRef<[u8]>>(&self, masks: &[M]) -> Vec<VarId> {
        self.select(masks, Mask::matches)
    }

    /// Like [`VarTable::matching`], but system variables (`__...`) only
    /// for masks that begin with `__` ([`Mask::matches_name`]).
    pub fn matching_names<M: AsRef<[u8]>>(&self, masks: &[M]) -> Vec<VarId> {
        self.select(masks, Mask::matches_name)
    }

    /// The variables some mask `matches`, in table order. Masks that are
    /// all plain names (a web page's rows, a client's list) are looked up
    /// in the index: a scan of a 100,000-variable table per name is what
    /// opening such a stream cost before. A plain name equal to a variable's
    /// matches it under either rule (`__` and `%` names included).
    fn select<M: AsRef<[u8]>>(&self, masks: &[M], matches: fn(&Mask, &[u8]) -> bool) -> Vec<VarId> {
        let masks: Vec<Mask> = masks.iter().map(|m| Mask::new(m.as_ref())).collect();
        if masks
            .iter()
            .all(|m| !m.pattern().is_empty() && !m.has_wildcard())
        {
            let mut ids: Vec<VarId> = masks.iter().filter_map(|m| self.get(m.pattern())).collect();
            ids.sort_unstable();
            ids.dedup();
            return ids;
        }
        self.vars
            .iter()
            .enumerate()
            .filter(|(_, var)| masks.iter().any(|m| matches(m, &var.name)))
            .map(|(id, _)| id as VarId)
            .collect()
    }

    pub fn vars(&self) -> &[Var] {
        &self.vars
    }

    /// Looks a name up case-insensitively.
    pub fn lookup(&self, name: &[u8]) -> Option<VarId> {
        if name.iter().all(|b| !b.is_ascii_lowercase() && *b < 0x80) {
            return self.get(name);
        }
        self.get(&cp1250::to_upper(name))
    }

    pub fn plc_run(&self) -> VarId {
        self.plc_run
    }

    pub fn pf_crc(&self) -> VarId {
        self.pf_crc
    }

    pub fn is_fixed(&self, id: VarId) -> bool {
        (id as usize) < self.fixed_count
    }
}

/// A table of the standard fixed file and user variables of the given
/// names and types, laid out one after another in R: a table for tests and
/// examples, which need variables but no public file.
pub fn table_of(vars: &[(&str, &str)]) -> VarTable {
    let mut text = String::new();
    let mut offset = 0;
    for (name, ty) in vars {
        text.push_str(&format!(" {name} R B {offset} {ty} PUB_INOUT\r\n"));
        offset += 16;
    }
    VarTable::from_public_text("test.pub", text.as_bytes()).expect("table")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Plain names take the index, masks the scan: both give what a scan
    /// gives, in table order, once each.
    #[test]
    fn plain_names_are_looked_up_and_agree_with_the_scan() {
        let table = table_of(&[("B", "INT"), ("A", "INT"), ("C_1", "BOOL")]);
        let scan = |masks: &[&str], rule: fn(&Mask, &[u8]) -> bool| -> Vec<VarId> {
            let masks: Vec<Mask> = masks.iter().map(|m| Mask::new(m.as_bytes())).collect();
            (0..table.len() as VarId)
                .filter(|&id| masks.iter().any(|m| rule(m, &table.var(id).name)))
                .collect()
        };
        for masks in [
            &["a", "c_1", "A", "missing"][..],
            &["__plc_run", "b"],
            &["__PF_CRC"],
            &["c*", "a"],
            &["*"],
            &[""],
        ] {
            assert_eq!(
                table.matching(masks),
                scan(masks, Mask::matches),
                "{masks:?}"
            );
            assert_eq!(
                table.matching_names(masks),
                scan(masks, Mask::matches_name),
                "{masks:?}"
            );
        }
        let a = table.lookup(b"A").unwrap();
        let c = table.lookup(b"C_1").unwrap();
        assert_eq!(table.matching(&["c_1", "a", "A"]), {
            let mut ids = vec![a, c];
            ids.sort_unstable();
            ids
        });
    }

    #[test]
    fn a_file_past_the_variable_bound_is_refused_naming_file_and_line() {
        let mut text = Vec::new();
        for i in 0..=pubfile::MAX_VARS {
            text.extend_from_slice(format!(" V{i} R B {} BYTE\r\n", i % 1000).as_bytes());
        }
        let err = VarTable::from_public_text("big.pub", &text).unwrap_err();
        assert_eq!(
            err.to_string(),
            "'big.pub' line 100001: more than 100000 variables, the most a file may define; the file is refused"
        );
        text.truncate(text.len() - b" V100000 R B 0 BYTE\r\n".len());
        let table = VarTable::from_public_text("big.pub", &text).expect("at the bound");
        assert_eq!(table.len(), pubfile::MAX_VARS + 2);
    }
}
