//! A plugin runs inside the server: if it crashes, the server goes with it.
//! This makes sure that is never silent: while a thread is inside a plugin
//! call, a fatal signal (SIGSEGV, SIGBUS, SIGILL, SIGFPE, SIGABRT) first
//! writes one line naming the plugin and the call to the log, then takes its
//! course (the handler installed before, else the default action: the
//! process ends, and a supervisor restarts it). Outside plugin calls the
//! handler only passes the signal on.
//!
//! The handler does nothing but `write(2)` and `sigaction(2)`, both
//! async-signal-safe; what it writes was prepared before the call.

use std::cell::Cell;
use std::os::fd::RawFd;
use std::sync::atomic::{AtomicI32, Ordering};
use std::sync::Once;

const SIGNALS: [(libc::c_int, &[u8]); 5] = [
    (libc::SIGSEGV, b"SIGSEGV"),
    (libc::SIGBUS, b"SIGBUS"),
    (libc::SIGILL, b"SIGILL"),
    (libc::SIGFPE, b"SIGFPE"),
    (libc::SIGABRT, b"SIGABRT"),
];

/// Where the line goes: the log file, else stderr.
static LOG_FD: AtomicI32 = AtomicI32::new(2);

/// The actions in place before ours, by index in [`SIGNALS`]; written once,
/// before our handler is installed.
static mut PREVIOUS: [Option<libc::sigaction>; 5] = [None; 5];

thread_local! {
    /// What this thread is doing inside a plugin: a prepared text.
    static INSIDE: Cell<(*const u8, usize)> = const { Cell::new((std::ptr::null(), 0)) };
}

/// The log file's descriptor, when the log is a file: a duplicate of it,
/// kept open for good. Called again when the log is reopened (SIGHUP), it
/// makes the same descriptor number refer to the new file (`dup2`, atomic
/// for a handler writing meanwhile), so the rotated file is let go.
pub fn set_log_fd(fd: RawFd) {
    let ours = LOG_FD.load(Ordering::Relaxed);
    if ours != libc::STDERR_FILENO {
        // SAFETY: both descriptors are open; `ours` is our own duplicate.
        unsafe { libc::dup2(fd, ours) };
        return;
    }
    // SAFETY: dup of a descriptor the caller owns; the copy is never closed.
    let copy = unsafe { libc::dup(fd) };
    if copy >= 0 {
        LOG_FD.store(copy, Ordering::Relaxed);
    }
}

/// Runs `f`, a call into a plugin described by `note` (e.g. `plugin
/// /opt/x.so (section S): read`), so that a crash in it is logged.
pub fn inside<T>(note: &[u8], f: impl FnOnce() -> T) -> T {
    install();
    INSIDE.with(|c| c.set((note.as_ptr(), note.len())));
    let result = f();
    INSIDE.with(|c| c.set((std::ptr::null(), 0)));
    result
}

fn install() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        for (i, (signal, _)) in SIGNALS.iter().enumerate() {
            // SAFETY: plain sigaction(2) calls with zeroed, then filled,
            // structures; PREVIOUS is written here only, before the handler
            // that reads it can run for this signal.
            unsafe {
                let mut action: libc::sigaction = std::mem::zeroed();
                action.sa_sigaction = on_fatal as *const () as usize;
                action.sa_flags = libc::SA_SIGINFO | libc::SA_ONSTACK;
                libc::sigemptyset(&mut action.sa_mask);
                let mut previous: libc::sigaction = std::mem::zeroed();
                if libc::sigaction(*signal, std::ptr::null(), &mut previous) == 0 {
                    let slot = std::ptr::addr_of_mut!(PREVIOUS[i]);
                    *slot = Some(previous);
                    libc::sigaction(*signal, &action, std::ptr::null_mut());
                }
            }
        }
    });
}

fn write_all(fd: RawFd, bytes: &[u8]) {
    // SAFETY: write(2) of a valid buffer; errors are ignored (nothing else
    // can be done in a signal handler).
    unsafe {
        libc::write(fd, bytes.as_ptr().cast(), bytes.len());
    }
}

extern "C" fn on_fatal(signal: libc::c_int, info: *mut libc::siginfo_t, _: *mut libc::c_void) {
    let Some(index) = SIGNALS.iter().position(|(s, _)| *s == signal) else {
        return;
    };
    let (note, len) = INSIDE
        .try_with(|c| c.get())
        .unwrap_or((std::ptr::null(), 0));
    if !note.is_null() {
        let fd = LOG_FD.load(Ordering::Relaxed);
        write_all(fd, b"plccoms: FATAL: signal ");
        write_all(fd, SIGNALS[index].1);
        write_all(fd, b" inside ");
        // SAFETY: `inside` keeps the note alive while it is set.
        write_all(fd, unsafe { std::slice::from_raw_parts(note, len) });
        write_all(
            fd,
            b"; a crash inside a plugin is not isolated: the server stops\n",
        );
    }
    // SAFETY: restores the action recorded before ours; a fault then
    // repeats under it, a signal sent by a process is raised again.
    unsafe {
        let previous = std::ptr::addr_of!(PREVIOUS[index]).read();
        let mut default: libc::sigaction = std::mem::zeroed();
        default.sa_sigaction = libc::SIG_DFL;
        let action = previous.unwrap_or(default);
        libc::sigaction(signal, &action, std::ptr::null_mut());
        if info.is_null() || (*info).si_code <= 0 {
            libc::raise(signal);
        }
    }
}
