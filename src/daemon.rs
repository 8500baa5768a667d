//! `-d`: detach into the background. The parent waits until the child is
//! listening (exit 0) or failed to start (prints the reason, exit 1), so a
//! supervisor or script sees start-up errors.

use std::fs::File;
use std::io::{Read, Write};
use std::os::fd::{AsRawFd, OwnedFd, RawFd};

use std::time::{Duration, Instant};

use nix::sys::wait::{waitpid, WaitPidFlag, WaitStatus};
use nix::unistd::{dup2_stderr, dup2_stdin, dup2_stdout, fork, pipe, setsid, ForkResult, Pid};

/// The child's way to tell the waiting parent how start-up went.
pub struct Notifier {
    pipe: Option<File>,
}

impl Notifier {
    /// For a server that did not detach: nobody waits.
    pub fn none() -> Notifier {
        Notifier { pipe: None }
    }

    pub fn ready(&mut self) {
        if let Some(mut pipe) = self.pipe.take() {
            let _ = pipe.write_all(b"OK\n");
        }
    }

    pub fn fail(&mut self, message: &str) {
        if let Some(mut pipe) = self.pipe.take() {
            let _ = writeln!(pipe, "{message}");
        }
    }
}

/// Forks. Returns in the child (detached from the terminal, standard streams
/// on /dev/null) with its notifier; the parent never returns: it exits with
/// the child's start-up result. Call before any thread is started.
pub fn detach() -> Result<Notifier, String> {
    let (read_end, write_end) = pipe().map_err(|e| format!("pipe: {e}"))?;
    // SAFETY: no other thread exists yet (the runtime starts after this), so
    // the child may run arbitrary code.
    match unsafe { fork() }.map_err(|e| format!("fork: {e}"))? {
        ForkResult::Parent { child } => {
            drop(write_end);
            let code = wait_for_child(read_end);
            if code != 0 {
                reap(child);
            }
            std::process::exit(code);
        }
        ForkResult::Child => {
            drop(read_end);
            setsid().map_err(|e| format!("setsid: {e}"))?;
            close_inherited(write_end.as_raw_fd());
            let null = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .open("/dev/null")
                .map_err(|e| format!("/dev/null: {e}"))?;
            dup2_stdin(&null).map_err(|e| format!("dup2: {e}"))?;
            dup2_stdout(&null).map_err(|e| format!("dup2: {e}"))?;
            dup2_stderr(&null).map_err(|e| format!("dup2: {e}"))?;
            Ok(Notifier {
                pipe: Some(File::from(write_end)),
            })
        }
    }
}

/// Closes every descriptor the launcher left open, except the standard
/// streams and `keep`, as a daemon must: a launcher that waits for the end
/// of some pipe would otherwise wait for as long as the server runs.
fn close_inherited(keep: RawFd) {
    let Ok(dir) = std::fs::read_dir("/proc/self/fd") else {
        return;
    };
    let fds: Vec<RawFd> = dir
        .filter_map(|entry| entry.ok()?.file_name().to_str()?.parse().ok())
        .collect();
    for fd in fds {
        if fd > 2 && fd != keep {
            // SAFETY: single-threaded child right after fork; nothing in this
            // process owns these inherited descriptors (the folder listing's
            // own descriptor is closed already: EBADF, harmless).
            unsafe {
                libc::close(fd);
            }
        }
    }
}

/// Waits (5 s at most) for a child that failed to start to end: it has
/// said why, but still holds what it took (the pid file's lock, ports)
/// until it exits, and a script that starts another at once would find
/// them taken.
fn reap(child: Pid) {
    let deadline = Instant::now() + Duration::from_secs(5);
    while Instant::now() < deadline {
        match waitpid(child, Some(WaitPidFlag::WNOHANG)) {
            Ok(WaitStatus::StillAlive) => std::thread::sleep(Duration::from_millis(10)),
            _ => return,
        }
    }
}

fn wait_for_child(read_end: OwnedFd) -> i32 {
    let _ = read_end.as_raw_fd();
    let mut message = String::new();
    let _ = File::from(read_end).read_to_string(&mut message);
    if message.starts_with("OK") {
        0
    } else if message.trim().is_empty() {
        eprintln!("plccoms: the background server ended during start-up; see its log file");
        1
    } else {
        eprint!("plccoms: {message}");
        1
    }
}
