//! The simulated PLC on a serial line (a real port or one end of a pty pair):
//! the same frames as over UDP, back to back, decoded with the stream codec
//! (`plccoms_plc::epsnet::stream`).
//!
//! Fault injection on a line: `loss` is the fraction of exchanges damaged,
//! each in one of four ways drawn at random — the answer is lost, cut
//! short, has one byte corrupted, or comes after noise. `latency` delays answers as over UDP. With
//! [`SerialLine::emulate`] the answer is also held back for as long as the
//! request and the answer take on a real line at the set speed (10 bits a
//! byte), since a pty passes bytes at memory speed.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use bytes::BytesMut;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_serial::{SerialPortBuilderExt, SerialStream};
use tokio_util::codec::Decoder;

use plccoms_plc::epsnet::stream::{self, StreamCodec, StreamItem, MAX_FRAME};

use crate::server::Rng;
use crate::Shared;

/// A serial line to serve.
#[derive(Debug, Clone)]
pub struct SerialLine {
    /// The device (`/dev/ttyUSB0`, a pty such as socat's `link=` path).
    pub device: String,
    /// Baud; 8N1, no flow control.
    pub speed: u32,
    /// Hold each answer back for the line time of the request and the answer.
    pub emulate: bool,
}

/// What crossed the line, for `status` and benchmarks.
#[derive(Debug, Default)]
pub struct LineStats {
    pub rx_bytes: AtomicU64,
    pub tx_bytes: AtomicU64,
    pub rx_frames: AtomicU64,
    pub tx_frames: AtomicU64,
    /// Bytes skipped while resynchronising.
    pub rx_skipped: AtomicU64,
}

impl LineStats {
    pub fn text(&self) -> String {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        format!(
            "rx_bytes={} tx_bytes={} rx_frames={} tx_frames={} rx_skipped={}",
            get(&self.rx_bytes),
            get(&self.tx_bytes),
            get(&self.rx_frames),
            get(&self.tx_frames),
            get(&self.rx_skipped)
        )
    }
}

/// One way an exchange is damaged on the line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Damage {
    /// No answer reaches the line.
    Lost,
    /// The answer stops after this many bytes.
    Truncated(usize),
    /// The byte at this index is XORed with the mask.
    Corrupted(usize, u8),
    /// This many noise bytes come before the answer.
    Noise(usize),
}

impl Damage {
    /// Draws a damage for an answer of `len` bytes.
    pub fn draw(rng: &mut Rng, len: usize) -> Damage {
        let index = |rng: &mut Rng| ((rng.next_f64() * len as f64) as usize).min(len - 1);
        match (rng.next_f64() * 4.0) as u32 {
            _ if len <= 1 => Damage::Lost,
            0 => Damage::Lost,
            1 => Damage::Truncated(index(rng).max(1)),
            2 => Damage::Corrupted(index(rng), 1 + (rng.next_f64() * 255.0) as u8),
            _ => Damage::Noise(1 + (rng.next_f64() * 16.0) as usize),
        }
    }

    /// The bytes that reach the line instead of `answer`.
    pub fn apply(self, mut answer: Vec<u8>, rng: &mut Rng) -> Vec<u8> {
        match self {
            Damage::Lost => Vec::new(),
            Damage::Truncated(at) => {
                answer.truncate(at);
                answer
            }
            Damage::Corrupted(at, mask) => {
                if let Some(byte) = answer.get_mut(at) {
                    *byte ^= mask;
                }
                answer
            }
            Damage::Noise(n) => {
                let mut out: Vec<u8> = (0..n).map(|_| (rng.next_f64() * 256.0) as u8).collect();
                out.extend(answer);
                out
            }
        }
    }
}

/// Opens the simulator's end of the line.
pub fn open(line: &SerialLine) -> std::io::Result<SerialStream> {
    tokio_serial::new(&line.device, line.speed)
        .exclusive(false)
        .open_native_async()
        .map_err(|e| std::io::Error::other(format!("{}: {e}", line.device)))
}

/// Serves the line until the task is aborted or the line fails.
pub(crate) async fn serve(mut port: SerialStream, line: SerialLine, shared: Arc<Shared>) {
    let mut codec = StreamCodec;
    let mut buf = BytesMut::with_capacity(MAX_FRAME);
    let stats = &shared.line;
    // A frame stopped half-way is given up after this quiet time.
    let idle = Duration::from_millis(20);
    loop {
        while let Ok(Some(item)) = codec.decode(&mut buf) {
            let frame = match item {
                StreamItem::Frame(frame) => frame,
                StreamItem::Skipped { bytes, why } => {
                    tracing::debug!("plcsim: {bytes} bytes skipped on the line: {why}");
                    stats.rx_skipped.fetch_add(bytes as u64, Ordering::Relaxed);
                    continue;
                }
            };
            stats.rx_frames.fetch_add(1, Ordering::Relaxed);
            let request_len = frame.encoded_len();
            let Some((answer, latency, damage)) = shared.handle_frame(&frame) else {
                continue;
            };
            let Ok(mut bytes) = stream::encode(&answer) else {
                continue;
            };
            let mut delay = latency;
            if line.emulate {
                let on_line = request_len + bytes.len();
                delay += Duration::from_secs_f64(on_line as f64 * 10.0 / f64::from(line.speed));
            }
            if let Some(damage) = damage {
                bytes = shared.damage(damage, bytes);
            }
            if !delay.is_zero() {
                tokio::time::sleep(delay).await;
            }
            if bytes.is_empty() {
                continue;
            }
            if !send(&mut port, &bytes, &line, stats).await {
                return;
            }
        }
        if read_more(&mut port, &mut buf, stats, idle).await {
            if let Some(StreamItem::Skipped { bytes, .. }) = codec.abandon_partial(&mut buf) {
                stats.rx_skipped.fetch_add(bytes as u64, Ordering::Relaxed);
            }
        }
    }
}

/// Writes an answer to the line and counts it; `false` when the line fails.
pub(crate) async fn send(
    port: &mut SerialStream,
    bytes: &[u8],
    line: &SerialLine,
    stats: &LineStats,
) -> bool {
    if port.write_all(bytes).await.is_err() || port.flush().await.is_err() {
        tracing::warn!("plcsim: cannot write to {}", line.device);
        return false;
    }
    stats.tx_frames.fetch_add(1, Ordering::Relaxed);
    stats
        .tx_bytes
        .fetch_add(bytes.len() as u64, Ordering::Relaxed);
    true
}

/// Reads more of the line into `buf` (waiting for the other end while it is
/// gone); `true` when the line stayed quiet for `idle` with part of a frame
/// in `buf`, which the caller then gives up.
pub(crate) async fn read_more(
    port: &mut SerialStream,
    buf: &mut BytesMut,
    stats: &LineStats,
    idle: Duration,
) -> bool {
    let read = if buf.is_empty() {
        Ok(port.read_buf(buf).await)
    } else {
        tokio::time::timeout(idle, port.read_buf(buf)).await
    };
    match read {
        Ok(Ok(0)) | Ok(Err(_)) => {
            // The other end is gone (a pty's peer closed): wait for it.
            tokio::time::sleep(Duration::from_millis(50)).await;
            false
        }
        Ok(Ok(n)) => {
            stats.rx_bytes.fetch_add(n as u64, Ordering::Relaxed);
            false
        }
        Err(_idle) => true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_damage_changes_the_bytes() {
        let mut rng = Rng::new(7);
        let answer: Vec<u8> = (0..20).collect();
        for _ in 0..200 {
            let damage = Damage::draw(&mut rng, answer.len());
            let out = damage.apply(answer.clone(), &mut rng);
            assert_ne!(out, answer, "{damage:?}");
            match damage {
                Damage::Lost => assert!(out.is_empty()),
                Damage::Truncated(n) => assert_eq!(out.len(), n),
                Damage::Corrupted(..) => assert_eq!(out.len(), answer.len()),
                Damage::Noise(n) => assert_eq!(&out[n..], &answer[..]),
            }
        }
        assert_eq!(Damage::draw(&mut rng, 1), Damage::Lost);
    }
}
