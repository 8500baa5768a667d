//! `plccoms history`: the samples of a section's variables in a time range,
//! as CSV (long or wide), JSON or Parquet, to a file or standard output.
//!
//! ```text
//! plccoms history -c PLCComS.ini --section Demo --vars 'SIN*,COS*' --from -1h [--to now]
//!                 [--format csv|json|parquet] [--out FILE] [--wide]
//! ```

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::SystemTime;

use clap::Args;

use super::export::{self, ExportError, Format};
use super::query::Query;
use super::{history_dir, time};
use plccoms_core::changes::unix_ms;
use plccoms_core::config;

/// The end of `plccoms history --help`.
const HISTORY_HELP: &str = "\
--out: the export is written to .<name>.<pid>.tmp beside FILE and renamed over \
FILE only when it ran to the end; until then FILE stays as it was, and an export \
that fails or is killed leaves no FILE that looks complete (a killed one leaves \
its .tmp file). A FILE that is a symbolic link is refused.

Long form: time,name,value,text,quality (time ISO 8601 UTC with ms; value a \
number, BOOL 0/1; text a string, DATE, DT, TOD or TIME in ISO 8601). Wide \
form: time,quality and a column per variable. Gaps are rows whose quality is \
not good: __LINK (link_lost), __SERVER (stopped), __DAMAGED; wide, a row of \
empty cells. README, History, describes the forms and a forward fill that \
keeps to good stretches.

CSV: a name or text value beginning with = + - @ TAB or CR that does not read \
as a number is written with a ' before it, so that a spreadsheet shows it as text \
instead of running it as a formula; numbers, negative ones included, are never \
changed. JSON and Parquet hold the values as they are.

Exit status: 0 all exported; 2 exported to the end, but without the samples of \
damaged packed blocks, which standard error names (file and time range); \
1 failed (--out untouched).";

/// `plccoms history -c <ini> --section S --vars <masks> --from T --to T
/// [--format csv|json|parquet] [--out FILE] [--wide]`
#[derive(Debug, Clone, PartialEq, Eq, Args)]
#[command(after_help = HISTORY_HELP)]
pub struct HistoryArgs {
    /// Section whose history is read
    #[arg(long)]
    pub section: String,
    /// Variables: names or masks with *, comma-separated
    #[arg(long, default_value = "*")]
    pub vars: String,
    /// Start (included): ISO 8601 UTC (2026-05-01T12:00:00Z, 2026-05-01) or relative (-1h, -7d)
    #[arg(long, allow_hyphen_values = true)]
    pub from: String,
    /// End (excluded), as --from; default now
    #[arg(long, default_value = "now", allow_hyphen_values = true)]
    pub to: String,
    /// Output format
    #[arg(long, value_enum, default_value = "csv")]
    pub format: Format,
    /// Output file (default: standard output); written beside it and renamed at the end, never through a symbolic link
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
    /// One row per time and one column per variable, instead of one row per sample
    #[arg(long)]
    pub wide: bool,
}

/// The exit status when the export was written to the end without the
/// samples of damaged blocks (named on standard error).
pub const EXIT_DAMAGED: u8 = 2;

/// Exit status 0: all exported; [`EXIT_DAMAGED`]: exported without the
/// damaged ranges it names; 1: failed (nothing written to `--out`).
pub fn run(config_path: &Path, args: &HistoryArgs) -> ExitCode {
    match export_to(config_path, args) {
        Ok(None) => ExitCode::SUCCESS,
        Ok(Some(damaged)) => {
            eprintln!("plccoms history: {damaged}");
            ExitCode::from(EXIT_DAMAGED)
        }
        Err(message) => {
            eprintln!("plccoms history: {message}");
            ExitCode::FAILURE
        }
    }
}

/// What an export wrote despite damage: rows written, ranges left out.
fn written(result: Result<u64, ExportError>) -> Result<(u64, Option<String>), String> {
    match result {
        Ok(rows) => Ok((rows, None)),
        Err(e @ ExportError::Damaged { rows, .. }) => Ok((rows, Some(e.to_string()))),
        Err(e) => Err(e.to_string()),
    }
}

/// Exports; `Ok(Some(..))` names the damaged ranges left out.
fn export_to(config_path: &Path, args: &HistoryArgs) -> Result<Option<String>, String> {
    let loaded = config::load(config_path).map_err(|e| {
        let mut text = e.to_string();
        for d in e.diagnostics() {
            text.push_str(&format!("\n  {d}"));
        }
        text
    })?;
    let config = loaded.config;
    let section = config
        .sections
        .iter()
        .find(|s| s.name.eq_ignore_ascii_case(&args.section))
        .ok_or_else(|| {
            let names: Vec<&str> = config.sections.iter().map(|s| s.name.as_str()).collect();
            format!(
                "no section [{}] in {} (sections: {})",
                args.section,
                config_path.display(),
                names.join(", ")
            )
        })?;
    let now = unix_ms(SystemTime::now());
    let from = time::parse(&args.from, now).map_err(|e| format!("--from: {e}"))?;
    let to = time::parse(&args.to, now).map_err(|e| format!("--to: {e}"))?;
    if to <= from {
        return Err(format!(
            "--to ({}) is not after --from ({})",
            args.to, args.from
        ));
    }
    let masks = config::history::parse_masks(&args.vars).map_err(|e| format!("--vars {e}"))?;
    let query = Query {
        dir: history_dir(&config.path, &config.global),
        section: section.name.clone(),
        masks,
        from_ms: from,
        to_ms: to,
    };
    match &args.out {
        Some(path) => {
            let (rows, damaged) = write_out(path, |file| {
                written(export::export(&query, args.format, args.wide, file))
            })?;
            if damaged.is_none() {
                eprintln!("{rows} rows written to {}", path.display());
            }
            Ok(damaged)
        }
        None => {
            if args.format == Format::Parquet && is_terminal() {
                return Err("Parquet is binary: give --out FILE or redirect the output".into());
            }
            let result = export::export(&query, args.format, args.wide, std::io::stdout());
            let _ = std::io::stdout().flush();
            Ok(written(result)?.1)
        }
    }
}

/// Writes `--out` through a new file beside it (`.<name>.<pid>.tmp`),
/// renamed over it when the export ran to the end (damaged ranges left out
/// included): until then the file there stays as it was, and a killed
/// export leaves only the temporary file, never one that looks complete.
/// A symbolic link at `path` is refused: an export never writes through
/// one (the rename would replace the link itself, not its target).
fn write_out<T>(
    path: &Path,
    export: impl FnOnce(&mut std::fs::File) -> Result<T, String>,
) -> Result<T, String> {
    if let Ok(meta) = std::fs::symlink_metadata(path) {
        if meta.file_type().is_symlink() {
            let target = std::fs::read_link(path).unwrap_or_default();
            return Err(format!(
                "--out {} is a symbolic link (to {}): not written through; give the file's own path",
                path.display(),
                target.display()
            ));
        }
        if meta.is_dir() {
            return Err(format!("--out {} is a folder", path.display()));
        }
    }
    let name = path
        .file_name()
        .ok_or_else(|| format!("--out {}: not a file name", path.display()))?;
    let mut temp_name = std::ffi::OsString::from(".");
    temp_name.push(name);
    temp_name.push(format!(".{}.tmp", std::process::id()));
    let temp = path.with_file_name(temp_name);
    // create_new: never an existing file, nor through a link planted there.
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&temp)
        .map_err(|e| format!("cannot create {} for --out: {e}", temp.display()))?;
    let result = export(&mut file).and_then(|done| {
        file.sync_all()
            .map_err(|e| format!("writing {}: {e}", temp.display()))?;
        std::fs::rename(&temp, path).map_err(|e| {
            format!(
                "cannot rename {} to {}: {e}",
                temp.display(),
                path.display()
            )
        })?;
        Ok(done)
    });
    if result.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    result
}

fn is_terminal() -> bool {
    use std::io::IsTerminal;
    std::io::stdout().is_terminal()
}
