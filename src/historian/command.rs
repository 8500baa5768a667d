//! `plccoms history`: the samples of a section's variables in a time range,
//! as CSV (long or wide), JSON or Parquet, to a file or standard output.
//!
//! ```text
//! plccoms history -c PLCComS.ini --section Demo --vars 'SIN*,COS*' --from -1h [--to now]
//!                 [--format csv|json|parquet] [--out FILE] [--wide]
//! ```

use std::io::Write;
use std::path::Path;
use std::process::ExitCode;
use std::time::SystemTime;

use super::export::{self, Format};
use super::query::Query;
use super::{history_dir, time};
use crate::changes::unix_ms;
use crate::cli::HistoryArgs;
use crate::config;

pub fn run(config_path: &Path, args: &HistoryArgs) -> ExitCode {
    match export_to(config_path, args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("plccoms history: {message}");
            ExitCode::FAILURE
        }
    }
}

fn export_to(config_path: &Path, args: &HistoryArgs) -> Result<(), String> {
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
    let rows = match &args.out {
        Some(path) => {
            let file = std::fs::File::create(path)
                .map_err(|e| format!("cannot create {}: {e}", path.display()))?;
            let rows =
                export::export(&query, args.format, args.wide, file).map_err(|e| e.to_string())?;
            eprintln!("{rows} rows written to {}", path.display());
            rows
        }
        None => {
            if args.format == Format::Parquet && is_terminal() {
                return Err("Parquet is binary: give --out FILE or redirect the output".into());
            }
            let rows = export::export(&query, args.format, args.wide, std::io::stdout())
                .map_err(|e| e.to_string())?;
            let _ = std::io::stdout().flush();
            rows
        }
    };
    let _ = rows;
    Ok(())
}

fn is_terminal() -> bool {
    use std::io::IsTerminal;
    std::io::stdout().is_terminal()
}
