//! The command line, as the manual gives it:
//! `plccoms [-dtvh] [-c <config>] [-l <log>]`, plus `-V`/`--version`, and
//! this server's subcommand `plccoms history ...` (the historian's export).

use std::path::PathBuf;

use clap::{ArgAction, Parser, Subcommand};

// The historian owns its subcommand's arguments; the binary only mounts them.
#[cfg(feature = "historian")]
use plccoms_historian::command::HistoryArgs;

/// Log file used with `-d` when `-l` is not given.
pub const DEFAULT_LOG: &str = "PLCComS.log";
/// Pid file used with `-d` when `--pid-file` is not given.
pub const DEFAULT_PID_FILE: &str = "PLCComS.pid";

/// Parsed command line. `Cli::parse()` in `main`; `Cli::parse_from` or
/// `Cli::try_parse_from` in tests.
#[derive(Debug, Clone, PartialEq, Eq, Parser)]
#[command(
    name = "plccoms",
    version,
    about,
    after_help = crate::demo::HELP,
    // `plccoms help history` adds nothing to `plccoms history --help`, and
    // the man page would name a plccoms-help(8) that does not exist.
    disable_help_subcommand = true,
    override_usage = "plccoms [-dtvh] [-c <configuration_file>] [-l <log_file>]"
)]
pub struct Cli {
    /// Run in the background; reports go to the log file (PLCComS.log unless -l is given)
    #[arg(short, long)]
    pub daemon: bool,

    /// Terminate if the configuration file was changed (SIGHUP applies an edit
    /// without a restart)
    #[arg(short, long)]
    pub terminate: bool,

    /// Verbose mode (multiple -v options increase the verbosity)
    #[arg(short, long, action = ArgAction::Count)]
    pub verbose: u8,

    /// Configuration file
    #[arg(
        short,
        long,
        value_name = "configuration_file",
        default_value = "PLCComS.ini",
        global = true
    )]
    pub config: PathBuf,

    /// Log file (without it, reports go to the terminal unless -d is given)
    #[arg(short, long, value_name = "log_file")]
    pub log: Option<PathBuf>,

    /// Pid file, locked while the server runs (with -d: PLCComS.pid unless given; a file left by a crash is taken over)
    #[arg(long, value_name = "pid_file")]
    pub pid_file: Option<PathBuf>,

    #[command(subcommand)]
    pub command: Option<Command>,
}

#[derive(Debug, Clone, PartialEq, Eq, Subcommand)]
pub enum Command {
    /// Write out what the historian recorded (CSV, JSON or Parquet)
    #[cfg(feature = "historian")]
    History(HistoryArgs),
}

impl Cli {
    /// Where the pid goes: `--pid-file`, else `PLCComS.pid` when running as
    /// a daemon, else `None`.
    pub fn pid_path(&self) -> Option<PathBuf> {
        match &self.pid_file {
            Some(path) => Some(path.clone()),
            None if self.daemon => Some(PathBuf::from(DEFAULT_PID_FILE)),
            None => None,
        }
    }

    /// Where reports go: the `-l` file, else `PLCComS.log` when running as a
    /// daemon, else `None` (the terminal).
    pub fn log_path(&self) -> Option<PathBuf> {
        match &self.log {
            Some(path) => Some(path.clone()),
            None if self.daemon => Some(PathBuf::from(DEFAULT_LOG)),
            None => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;
    use plccoms_historian::export::Format;

    fn cli(args: &[&str]) -> Cli {
        Cli::try_parse_from(std::iter::once("plccoms").chain(args.iter().copied()))
            .unwrap_or_else(|e| panic!("{args:?}: {e}"))
    }

    #[test]
    fn defaults() {
        let c = cli(&[]);
        assert_eq!(
            c,
            Cli {
                daemon: false,
                terminate: false,
                verbose: 0,
                config: PathBuf::from("PLCComS.ini"),
                log: None,
                pid_file: None,
                command: None,
            }
        );
        assert_eq!(c.log_path(), None);
    }

    #[test]
    fn combined_short_flags() {
        let c = cli(&["-dtv"]);
        assert!(c.daemon && c.terminate);
        assert_eq!(c.verbose, 1);
        assert_eq!(cli(&["-vvv"]).verbose, 3);
        assert_eq!(cli(&["-v", "-v", "--verbose"]).verbose, 3);
        let c = cli(&["-dvc", "my.ini"]);
        assert!(c.daemon);
        assert_eq!(c.config, PathBuf::from("my.ini"));
    }

    #[test]
    fn long_forms() {
        let c = cli(&[
            "--daemon",
            "--terminate",
            "--verbose",
            "--config",
            "/etc/plccoms/PLCComS.ini",
            "--log=/var/log/plccoms.log",
            "--pid-file=/run/plccoms.pid",
        ]);
        assert_eq!(
            c,
            Cli {
                daemon: true,
                terminate: true,
                verbose: 1,
                config: PathBuf::from("/etc/plccoms/PLCComS.ini"),
                log: Some(PathBuf::from("/var/log/plccoms.log")),
                pid_file: Some(PathBuf::from("/run/plccoms.pid")),
                command: None,
            }
        );
        assert_eq!(c.pid_path(), Some(PathBuf::from("/run/plccoms.pid")));
        assert_eq!(cli(&["-d"]).pid_path(), Some(PathBuf::from("PLCComS.pid")));
        assert_eq!(cli(&[]).pid_path(), None);
        let c = cli(&["-c", "a.ini", "-l", "a.log"]);
        assert_eq!((c.config, c.log), ("a.ini".into(), Some("a.log".into())));
    }

    #[test]
    fn history_subcommand() {
        let c = cli(&[
            "history",
            "-c",
            "a.ini",
            "--section",
            "Demo",
            "--vars",
            "SIN*,X",
            "--from",
            "-1h",
            "--format",
            "parquet",
            "--out",
            "x.parquet",
            "--wide",
        ]);
        assert_eq!(c.config, PathBuf::from("a.ini"));
        assert_eq!(
            c.command,
            Some(Command::History(HistoryArgs {
                section: "Demo".into(),
                vars: "SIN*,X".into(),
                from: "-1h".into(),
                to: "now".into(),
                format: Format::Parquet,
                out: Some("x.parquet".into()),
                wide: true,
            }))
        );
        // -c before the subcommand works too; --from is required.
        assert_eq!(
            cli(&[
                "-c",
                "b.ini",
                "history",
                "--section",
                "S",
                "--from",
                "2026-01-01"
            ])
            .config,
            PathBuf::from("b.ini")
        );
        assert!(Cli::try_parse_from(["plccoms", "history", "--section", "S"]).is_err());
    }

    #[test]
    fn log_path() {
        assert_eq!(cli(&["-d"]).log_path(), Some(PathBuf::from("PLCComS.log")));
        assert_eq!(
            cli(&["-l", "x.log"]).log_path(),
            Some(PathBuf::from("x.log"))
        );
        assert_eq!(
            cli(&["-d", "-l", "x.log"]).log_path(),
            Some(PathBuf::from("x.log"))
        );
        assert_eq!(cli(&["-v"]).log_path(), None);
    }

    #[test]
    fn help_mentions_every_option() {
        let help = Cli::command().render_long_help().to_string();
        for option in [
            "-d, --daemon",
            "-t, --terminate",
            "-v, --verbose",
            "-c, --config",
            "-l, --log",
            "-h, --help",
            "-V, --version",
            "PLCComS.ini",
            "plccoms [-dtvh] [-c <configuration_file>] [-l <log_file>]",
            "SIMULATED DEMO PLC",
        ] {
            assert!(help.contains(option), "{option} missing from:\n{help}");
        }
        let err = Cli::try_parse_from(["plccoms", "--help"]).unwrap_err();
        assert_eq!(err.kind(), clap::error::ErrorKind::DisplayHelp);
        let err = Cli::try_parse_from(["plccoms", "-h"]).unwrap_err();
        assert_eq!(err.kind(), clap::error::ErrorKind::DisplayHelp);
        let err = Cli::try_parse_from(["plccoms", "--version"]).unwrap_err();
        assert_eq!(err.kind(), clap::error::ErrorKind::DisplayVersion);
    }

    #[test]
    fn bad_arguments_are_rejected() {
        for args in [&["-x"][..], &["-c"], &["--log"], &["extra"]] {
            let argv = std::iter::once("plccoms").chain(args.iter().copied());
            assert!(Cli::try_parse_from(argv).is_err(), "{args:?}");
        }
    }

    #[test]
    fn definition_is_consistent() {
        Cli::command().debug_assert();
    }
}
