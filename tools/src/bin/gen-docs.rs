//! Writes the man pages and shell completions of `plccoms` and `plcsim`,
//! generated from their clap definitions, into `doc/`:
//!
//! ```text
//! cargo run -p plccoms-tools --bin gen-docs            # write them
//! cargo run -p plccoms-tools --bin gen-docs -- --check # exit 1 if any is stale
//! ```
//!
//! The files are committed (the .deb and source installs take them from
//! there); `tools/tests/docs_fresh.rs` runs `--check`.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::CommandFactory;
use clap_complete::Shell;

/// A command whose documents are generated, its man section, and roff
/// sections of its page that are not in `--help`.
struct Program {
    command: clap::Command,
    section: &'static str,
    more: &'static str,
}

const PLCCOMS_MORE: &str = r#".SH SIGNALS
.TP
\fBSIGTERM\fR, \fBSIGINT\fR
Stop accepting, answer what clients already sent, close the PLC links and
log \fIstopped\fR; within 5 s, however many sections.
.TP
\fBSIGHUP\fR
Reopen the log file (logrotate moves it away, then signals) and re-read the
configuration: sections added start, removed ones stop, changed ones restart
alone, the others keep their clients; a file with errors is refused whole;
\fB[*]\fR keys apply at the next restart (\fBsystemctl reload plccoms\fR).
.SH FILES
.TP
\fI/etc/plccoms/PLCComS.ini\fR
The configuration (the .deb's service); the vendor's format, every key
documented in \fI/usr/share/doc/plccoms/PLCComS.ini.example\fR.
.TP
\fI/var/lib/plccoms\fR
The service's working folder; FILES_ROOT = /var/lib/plccoms/files keeps
clients' PC files there.
.TP
\fI/var/log/plccoms/PLCComS.log\fR
The service's log.
.SH SEE ALSO
\fBplcsim\fR(1), \fBlogrotate\fR(8), \fBsystemd.exec\fR(5)
"#;

fn programs() -> [Program; 2] {
    [
        // A daemon: section 8.
        Program {
            command: plccoms::cli::Cli::command(),
            section: "8",
            more: PLCCOMS_MORE,
        },
        Program {
            command: plcsim::cli::Args::command(),
            section: "1",
            more: ".SH SEE ALSO\n\\fBplccoms\\fR(8)\n",
        },
    ]
}

/// Every generated file: its path under `doc/` and its bytes.
fn documents() -> std::io::Result<Vec<(PathBuf, Vec<u8>)>> {
    let mut files = Vec::new();
    for Program {
        mut command,
        section,
        more,
    } in programs()
    {
        let name = command.get_name().to_string();
        let mut page = Vec::new();
        clap_mangen::Man::new(command.clone())
            .section(section)
            .render(&mut page)?;
        page.extend_from_slice(more.as_bytes());
        files.push((PathBuf::from(format!("man/{name}.{section}")), page));
        // Each subcommand its own page, as the main page's SUBCOMMANDS
        // section names it (`plccoms-history(8)`).
        for sub in command.get_subcommands() {
            let sub_name = format!("{name}-{}", sub.get_name());
            let mut page = Vec::new();
            clap_mangen::Man::new(
                sub.clone()
                    .display_name(sub_name.clone())
                    .bin_name(format!("{name} {}", sub.get_name()))
                    .version(env!("CARGO_PKG_VERSION")),
            )
            .section(section)
            .render(&mut page)?;
            page.extend_from_slice(format!(".SH SEE ALSO\n\\fB{name}\\fR({section})\n").as_bytes());
            files.push((PathBuf::from(format!("man/{sub_name}.{section}")), page));
        }
        for (shell, file) in [
            (Shell::Bash, name.clone()),
            (Shell::Zsh, format!("_{name}")),
            (Shell::Fish, format!("{name}.fish")),
        ] {
            let mut script = Vec::new();
            clap_complete::generate(shell, &mut command, &name, &mut script);
            files.push((Path::new("completions").join(file), script));
        }
    }
    Ok(files)
}

fn main() -> ExitCode {
    let check = match std::env::args().nth(1).as_deref() {
        None => false,
        Some("--check") => true,
        Some(other) => {
            eprintln!("gen-docs: unknown argument {other:?} (usage: gen-docs [--check])");
            return ExitCode::from(2);
        }
    };
    let doc = Path::new(env!("CARGO_MANIFEST_DIR")).join("../doc");
    let files = match documents() {
        Ok(files) => files,
        Err(e) => {
            eprintln!("gen-docs: {e}");
            return ExitCode::FAILURE;
        }
    };
    let mut stale = Vec::new();
    for (path, bytes) in files {
        let path = doc.join(path);
        if std::fs::read(&path).ok().as_deref() == Some(&bytes[..]) {
            continue;
        }
        if check {
            stale.push(path);
        } else if let Err(e) = path
            .parent()
            .map_or(Ok(()), std::fs::create_dir_all)
            .and_then(|()| std::fs::write(&path, bytes))
        {
            eprintln!("gen-docs: {}: {e}", path.display());
            return ExitCode::FAILURE;
        } else {
            println!("wrote {}", path.display());
        }
    }
    if stale.is_empty() {
        return ExitCode::SUCCESS;
    }
    for path in &stale {
        eprintln!("stale: {}", path.display());
    }
    eprintln!("run: cargo run -p plccoms-tools --bin gen-docs");
    ExitCode::FAILURE
}
