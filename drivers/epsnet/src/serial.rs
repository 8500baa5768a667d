//! EPSNET on a serial line (RS-232, RS-485): the same frames as over UDP,
//! back to back on the line (`plccoms_plc::epsnet::stream`), one request
//! outstanding at a time, its answer matched by order.
//!
//! - Line: SERIAL_SPEED baud, 8 data bits, no parity, 1 stop bit (the
//!   project's choice, see `plccoms_plc::epsnet::frame`).
//! - RTS, as the manual describes SERIAL_RTS and `[*]` SERIAL_DEVICE_CFG: a
//!   GPIO pin number drives that pin high while a frame is sent (RS-485
//!   direction control, through `/sys/class/gpio`), and hardware flow
//!   control (RTS/CTS) is used when no pin is set (or the pin is -1).
//! - Before each request, whatever the line brought since the last answer is
//!   discarded (a late answer to an earlier attempt, noise), so it cannot be
//!   taken for the answer to this one.
//! - Garbage and damaged frames are skipped by the stream decoder and
//!   counted as bad answers; a frame that stops half-way is abandoned once
//!   the line has been idle for [`idle_gap`], so the next frame is found.
//! - The port is opened at each connection: an adapter unplugged and plugged
//!   back, or a device that appears later, is found again.

use std::path::PathBuf;
use std::time::Duration;

use async_trait::async_trait;
use bytes::BytesMut;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::time::Instant;
use tokio_serial::{SerialPort, SerialPortBuilderExt, SerialStream};
use tokio_util::codec::Decoder;

use super::{EpsnetClient, Exchange, Timing, Transport};
use plccoms_core::config::serial::{pin_of, DevicePin};
use plccoms_core::driver::{Answer, PlcError};
use plccoms_core::rs485::Gpio;
use plccoms_plc::epsnet::service::{Request, Response};
use plccoms_plc::epsnet::stream::{self, StreamCodec, StreamItem, MAX_FRAME};

/// SERIAL_SPEED when the section does not set it (the manual's example).
pub const DEFAULT_SPEED: u32 = 115_200;

pub use plccoms_core::rs485::SYSFS_GPIO;

/// How the line's RTS is driven.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Rts {
    /// RTS/CTS hardware flow control (no GPIO pin set).
    Hardware,
    /// This GPIO pin is high while a frame is sent, no flow control.
    Gpio(u32),
    /// Neither (the simulated PLC's side of a test line).
    Off,
}

/// Settings of one EPSNET serial link (the PLC section's INI keys).
#[derive(Debug, Clone)]
pub struct SerialConfig {
    /// SERIAL_DEVICE.
    pub device: String,
    /// SERIAL_SPEED, baud.
    pub speed: u32,
    pub rts: Rts,
    /// The GPIO sysfs folder ([`SYSFS_GPIO`]; another for tests).
    pub gpio_root: PathBuf,
    /// EPSADDR, EPSTOUT, EPSTOUT_STEP and the retries, as over UDP.
    pub timing: Timing,
}

impl SerialConfig {
    pub fn new(device: &str) -> Self {
        SerialConfig {
            device: device.to_string(),
            speed: DEFAULT_SPEED,
            rts: Rts::Hardware,
            gpio_root: PathBuf::from(SYSFS_GPIO),
            timing: Timing {
                eps_addr: None,
                timeout: Duration::from_millis(1000),
                timeout_step: Duration::from_millis(500),
                retries: 1,
            },
        }
    }
}

/// The RTS of `device`: SERIAL_RTS if set, else its pin in
/// SERIAL_DEVICE_CFG (parsed by config), else hardware flow control.
pub fn rts_of(device: &str, serial_rts: Option<u32>, device_cfg: &[DevicePin]) -> Rts {
    serial_rts
        .or_else(|| pin_of(device_cfg, device))
        .map_or(Rts::Hardware, Rts::Gpio)
}

/// How long a line must be quiet before a frame that stopped half-way is
/// given up: 30 character times, at least 20 ms (a sender does not pause
/// inside a frame; a loaded machine may, a little).
pub fn idle_gap(speed: u32) -> Duration {
    byte_time(speed, 30).max(Duration::from_millis(20))
}

/// Time `bytes` take on the line at `speed` baud, 10 bits each (8N1).
pub fn byte_time(speed: u32, bytes: usize) -> Duration {
    Duration::from_secs_f64(bytes as f64 * 10.0 / f64::from(speed.max(1)))
}

/// Opens a serial device at `speed` baud, 8N1, with `rts`'s flow control.
pub fn open_port(device: &str, speed: u32, rts: &Rts) -> std::io::Result<SerialStream> {
    let flow = match rts {
        Rts::Hardware => tokio_serial::FlowControl::Hardware,
        Rts::Gpio(_) | Rts::Off => tokio_serial::FlowControl::None,
    };
    tokio_serial::new(device, speed)
        .data_bits(tokio_serial::DataBits::Eight)
        .parity(tokio_serial::Parity::None)
        .stop_bits(tokio_serial::StopBits::One)
        .flow_control(flow)
        // Not exclusive: a SETCONF opens the device anew while the link it
        // may fall back to still holds it.
        .exclusive(false)
        .open_native_async()
        .map_err(std::io::Error::from)
}

/// The serial transport.
pub struct Serial {
    config: SerialConfig,
    port: Option<SerialStream>,
    gpio: Option<Gpio>,
    codec: StreamCodec,
    buf: BytesMut,
}

/// EPSNET on a serial line.
pub type SerialBackend = EpsnetClient<Serial>;

impl EpsnetClient<Serial> {
    pub fn new(config: SerialConfig) -> Self {
        let timing = config.timing.clone();
        EpsnetClient::with_transport(
            Serial {
                config,
                port: None,
                gpio: None,
                codec: StreamCodec,
                buf: BytesMut::with_capacity(MAX_FRAME),
            },
            timing,
        )
    }

    pub fn config(&self) -> &SerialConfig {
        &self.transport().config
    }
}

impl Serial {
    /// Drops what the line brought since the last answer, and on a retry
    /// what an earlier attempt may have left unsent.
    fn discard_input(&mut self, retry: bool) {
        self.buf.clear();
        if let Some(port) = &self.port {
            let which = if retry {
                tokio_serial::ClearBuffer::All
            } else {
                tokio_serial::ClearBuffer::Input
            };
            let _ = port.clear(which);
        }
    }

    async fn send(&mut self, bytes: &[u8]) -> Result<(), PlcError> {
        let port = self.port.as_mut().ok_or(PlcError::NotConfigured)?;
        if let Some(gpio) = &self.gpio {
            gpio.set(true)?;
        }
        let sent = async {
            port.write_all(bytes).await?;
            port.flush().await
        }
        .await;
        if let Some(gpio) = &self.gpio {
            // RTS stays up until the last bit has left the UART.
            tokio::time::sleep(byte_time(self.config.speed, bytes.len())).await;
            drain(port);
            gpio.set(false)?;
        }
        sent.map_err(PlcError::Io)
    }

    /// Waits until `deadline` for the answer to `request`. `None`: none
    /// came in time.
    async fn receive(
        &mut self,
        x: &Exchange<'_>,
        request: &Request,
        deadline: Instant,
        last_problem: &mut Option<String>,
    ) -> Result<Option<Answer<Response>>, PlcError> {
        let idle = idle_gap(self.config.speed);
        let device = self.config.device.clone();
        loop {
            while let Some(item) = self.codec.decode(&mut self.buf)? {
                match item {
                    StreamItem::Frame(frame) => match x.match_answer(request, &frame) {
                        Ok(answer) => return Ok(Some(answer)),
                        Err(problem) => {
                            x.bad_answer(&device, &problem);
                            *last_problem = Some(problem);
                        }
                    },
                    StreamItem::Skipped { bytes, why } => {
                        let problem = format!("{bytes} bytes skipped on the line: {why}");
                        x.bad_answer(&device, &problem);
                        *last_problem = Some(problem);
                    }
                }
            }
            let wait_until = if self.buf.is_empty() {
                deadline
            } else {
                deadline.min(Instant::now() + idle)
            };
            let port = self.port.as_mut().ok_or(PlcError::NotConfigured)?;
            match tokio::time::timeout_at(wait_until, port.read_buf(&mut self.buf)).await {
                Ok(Ok(0)) => {
                    return Err(PlcError::Io(std::io::Error::new(
                        std::io::ErrorKind::UnexpectedEof,
                        format!("{device} closed"),
                    )))
                }
                Ok(Ok(_)) => {}
                Ok(Err(e)) => return Err(PlcError::Io(e)),
                Err(_elapsed) if Instant::now() >= deadline => return Ok(None),
                Err(_idle) => {
                    if let Some(StreamItem::Skipped { bytes, why }) =
                        self.codec.abandon_partial(&mut self.buf)
                    {
                        let problem = format!("{bytes} bytes of an unfinished frame: {why}");
                        x.bad_answer(&device, &problem);
                        *last_problem = Some(problem);
                    }
                }
            }
        }
    }
}

/// Waits until the UART has sent everything written.
fn drain(port: &SerialStream) {
    use std::os::fd::AsRawFd;
    plccoms_core::rs485::drain(port.as_raw_fd());
}

#[async_trait]
impl Transport for Serial {
    fn describe(&self) -> String {
        let rts = match self.config.rts {
            Rts::Hardware => " RTS/CTS".to_string(),
            Rts::Gpio(pin) => format!(" RTS on GPIO {pin}"),
            Rts::Off => String::new(),
        };
        format!(
            "EPSNET/serial {} {} 8N1{rts}",
            self.config.device, self.config.speed
        )
    }

    async fn open(&mut self) -> Result<(), PlcError> {
        self.port = None;
        self.buf.clear();
        let port =
            open_port(&self.config.device, self.config.speed, &self.config.rts).map_err(|e| {
                PlcError::Io(std::io::Error::new(
                    e.kind(),
                    format!("{}: {e}", self.config.device),
                ))
            })?;
        if let (Rts::Gpio(pin), None) = (&self.config.rts, &self.gpio) {
            let gpio = Gpio::open(&self.config.gpio_root, *pin).map_err(|e| {
                PlcError::Io(std::io::Error::new(
                    e.kind(),
                    format!("RTS GPIO {pin} in {}: {e}", self.config.gpio_root.display()),
                ))
            })?;
            self.gpio = Some(gpio);
        }
        let _ = port.clear(tokio_serial::ClearBuffer::All);
        self.port = Some(port);
        Ok(())
    }

    fn is_open(&self) -> bool {
        self.port.is_some()
    }

    async fn exchange(
        &mut self,
        x: &Exchange<'_>,
        requests: &[Request],
        _window: usize,
    ) -> Result<Vec<Answer<Response>>, PlcError> {
        let mut answers = Vec::with_capacity(requests.len());
        for request in requests {
            let bytes = stream::encode(&x.request_frame(request))
                .map_err(|e| PlcError::Protocol(format!("cannot encode request: {e}")))?;
            let mut attempt = 0;
            let mut last_problem = None;
            let answer = loop {
                if !x.may_try(attempt) {
                    let what = format!(
                        "no answer on {} after {attempt} attempts",
                        self.config.device
                    );
                    return Err(x.timed_out(what, last_problem.as_deref()));
                }
                self.discard_input(attempt > 0);
                x.sent(attempt);
                let deadline = Instant::now() + x.wait(attempt);
                if tokio::time::timeout_at(deadline, self.send(&bytes))
                    .await
                    .is_err()
                {
                    last_problem =
                        Some("the line does not take the request (flow control?)".into());
                    attempt += 1;
                    continue;
                }
                let sent = Instant::now();
                let answer = self.receive(x, request, deadline, &mut last_problem);
                let answer = answer.await?;
                if let Some(answer) = answer {
                    x.answered(sent);
                    break answer;
                }
                attempt += 1;
            };
            answers.push(answer);
        }
        Ok(answers)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rts_from_the_section_then_the_device_table() {
        let cfg =
            plccoms_core::config::serial::parse_device_cfg("/dev/ttyS0 -1, /dev/ttyS1 17").unwrap();
        assert_eq!(rts_of("/dev/ttyS1", Some(5), &cfg), Rts::Gpio(5));
        assert_eq!(rts_of("/dev/ttyS1", None, &cfg), Rts::Gpio(17));
        assert_eq!(rts_of("/dev/ttyS0", None, &cfg), Rts::Hardware);
        assert_eq!(rts_of("/dev/ttyUSB0", None, &[]), Rts::Hardware);
    }

    #[test]
    fn idle_gap_and_byte_times() {
        assert_eq!(byte_time(115_200, 11_520), Duration::from_secs(1));
        assert_eq!(idle_gap(115_200), Duration::from_millis(20));
        assert_eq!(idle_gap(9600), Duration::from_micros(31_250));
    }
}
