//! Run-time control of a simulator over a loopback TCP text port, one command
//! a line, each answered `OK` or `ERR <why>`:
//!
//! ```text
//! loss 0.2          drop 20 % of incoming datagrams (on a serial line:
//!                   damage 20 % of the exchanges, see `serial`)
//! latency 500       delay answers by 500 ms
//! halt | run        PLC state (__PLC_RUN; the program runs only in RUN)
//! pub <file>        load another public file (new program, new __PF_CRC),
//!                   served by the file system under its own name (on a
//!                   Modbus device: a tag file)
//! program demo|idle
//! animate <mask>... animate these variables (none: stop animating)
//! status            OK run|halt crc=XXXXXXXX loss=.. latency=.. program=..
//!                   rx_bytes=.. tx_bytes=.. rx_frames=.. tx_frames=.. rx_skipped=..
//!                   devices=.. changes=..
//! device <i> <cmd>  any command for device i (from 0) alone
//! ```
//!
//! A simulator of several devices (`--devices`) applies a command without
//! `device` to all of them; `status` then shows the first device, and
//! `changes` (variable changes the animation made) counts all.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::{TcpListener, TcpStream};

use super::{lock, Shared};

/// Longest command line accepted.
const MAX_LINE: usize = 4096;
/// Control connections served at once.
const MAX_CLIENTS: usize = 8;

pub(crate) async fn serve(listener: TcpListener, devices: Arc<[Arc<Shared>]>) {
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_CLIENTS));
    loop {
        let Ok((stream, _)) = listener.accept().await else {
            tokio::time::sleep(Duration::from_millis(10)).await;
            continue;
        };
        let Ok(permit) = slots.clone().try_acquire_owned() else {
            continue;
        };
        let devices = devices.clone();
        tokio::spawn(async move {
            let _ = client(stream, &devices).await;
            drop(permit);
        });
    }
}

async fn client(stream: TcpStream, devices: &[Arc<Shared>]) -> std::io::Result<()> {
    let (read, mut write) = stream.into_split();
    let mut reader = BufReader::new(read);
    let mut line = Vec::new();
    loop {
        line.clear();
        let n = (&mut reader)
            .take(MAX_LINE as u64 + 1)
            .read_until(b'\n', &mut line)
            .await?;
        if n == 0 {
            return Ok(());
        }
        let answer = if line.len() > MAX_LINE && !line.ends_with(b"\n") {
            // Skip the rest of the over-long line.
            let mut rest = Vec::new();
            while !rest.ends_with(b"\n") {
                rest.clear();
                if (&mut reader)
                    .take(MAX_LINE as u64)
                    .read_until(b'\n', &mut rest)
                    .await?
                    == 0
                {
                    return Ok(());
                }
            }
            "ERR line too long".to_string()
        } else {
            match command_all(String::from_utf8_lossy(&line).trim(), devices) {
                Ok(text) => text,
                Err(why) => format!("ERR {why}"),
            }
        };
        write.write_all(answer.as_bytes()).await?;
        write.write_all(b"\n").await?;
    }
}

/// Runs one command line on every device, or on the one `device <i>` names.
pub(crate) fn command_all(line: &str, devices: &[Arc<Shared>]) -> Result<String, String> {
    let (word, rest) = line.split_once(char::is_whitespace).unwrap_or((line, ""));
    if word.eq_ignore_ascii_case("device") {
        let (index, rest) = rest
            .trim()
            .split_once(char::is_whitespace)
            .unwrap_or((rest.trim(), ""));
        let index: usize = index
            .parse()
            .map_err(|_| format!("bad device number '{index}'"))?;
        let device = devices
            .get(index)
            .ok_or_else(|| format!("no device {index} (0..{})", devices.len()))?;
        return command(rest.trim(), device, std::slice::from_ref(device));
    }
    let mut answer = Err("no device".to_string());
    for (i, device) in devices.iter().enumerate() {
        let this = command(line, device, devices);
        if i == 0 {
            answer = this;
        }
        // A command one device refuses, all refuse (same arguments).
        if answer.is_err() || word.eq_ignore_ascii_case("status") {
            break;
        }
    }
    answer
}

/// Runs one command line on `shared`; `status` counts `all`.
fn command(line: &str, shared: &Shared, all: &[Arc<Shared>]) -> Result<String, String> {
    let (word, rest) = line.split_once(char::is_whitespace).unwrap_or((line, ""));
    let rest = rest.trim();
    match word.to_ascii_lowercase().as_str() {
        "loss" => {
            let fraction: f64 = rest.parse().map_err(|_| format!("bad fraction '{rest}'"))?;
            if !(0.0..=1.0).contains(&fraction) {
                return Err("loss must be within 0..1".into());
            }
            shared.set_loss(fraction);
        }
        "latency" => {
            let ms: u64 = rest
                .parse()
                .map_err(|_| format!("bad milliseconds '{rest}'"))?;
            shared.set_latency(Duration::from_millis(ms));
        }
        "halt" => shared.set_run(false),
        "run" => shared.set_run(true),
        "pub" => {
            if rest.is_empty() {
                return Err("pub needs a file".into());
            }
            let bytes = std::fs::read(rest).map_err(|e| format!("{rest}: {e}"))?;
            let name = Path::new(rest).file_name().and_then(|n| n.to_str());
            let crc = shared.load_pub(&bytes, name);
            return Ok(format!("OK crc={crc:08X}"));
        }
        "program" => shared.set_program(rest.parse()?),
        "animate" => {
            let masks: Vec<String> = rest.split_whitespace().map(str::to_string).collect();
            shared.set_animate(&masks);
        }
        "status" => {
            let state = lock(&shared.state);
            let device = lock(&shared.device);
            let first = format!(
                "OK {} crc={:08X} loss={} latency={} program={:?} {}",
                if device.run() { "run" } else { "halt" },
                device.pf_crc(),
                state.loss,
                state.latency.as_millis(),
                state.program.kind(),
                shared.line.text(),
            );
            drop((state, device));
            let changes: u64 = all.iter().map(|d| d.changes()).sum();
            return Ok(format!("{first} devices={} changes={changes}", all.len()));
        }
        "" => return Err("empty command".into()),
        other => return Err(format!("unknown command '{other}'")),
    }
    Ok("OK".into())
}
