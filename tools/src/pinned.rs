//! Starting a bench's process on chosen CPUs (`taskset -c`), shared by the
//! benches that part the cores between server, client and simulators.

use std::ffi::OsStr;
use std::process::Command;

/// `program`, under `taskset -c cpus` when given (a `taskset` CPU list,
/// e.g. `0-7`); its pid is the program's, as taskset execs it.
pub fn command(program: impl AsRef<OsStr>, cpus: Option<&str>) -> Command {
    match cpus {
        Some(cpus) => {
            let mut command = Command::new("taskset");
            command.args(["-c", cpus]).arg(program);
            command
        }
        None => Command::new(program),
    }
}
