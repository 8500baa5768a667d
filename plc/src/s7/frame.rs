//! S7comm frames: the COTP TPDUs that ISO-on-TCP carries ([`Tpdu`]), the
//! jobs a client sends ([`Job`]) and the answers it gets ([`Answer`]).
//! Plain data with their byte forms; [`super::codec`] adds TPKT framing.
//! Every parser returns a [`FrameError`] naming the byte at fault; none
//! panics on what the wire brings.

use bytes::{BufMut, Bytes, BytesMut};

use super::{Region, ReturnCode};

/// Why bytes are not a frame.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct FrameError(pub String);

fn short(what: &str, need: usize, have: usize) -> FrameError {
    FrameError(format!("{what}: {need} bytes needed, {have} there"))
}

/// A COTP TPDU (ISO 8073 class 0).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Tpdu {
    /// CR: the client's connection request naming both TSAPs.
    ConnectRequest(Tsaps),
    /// CC: the server's confirm.
    ConnectConfirm(Tsaps),
    /// DT with EOT: one whole S7 PDU.
    Data(Bytes),
    /// DR, ER or anything else the server may send to end the connection.
    Other(u8),
}

/// The TSAPs of a connection and the TPDU size (code 0x0A = 1024 bytes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tsaps {
    pub local: u16,
    pub remote: u16,
    pub tpdu_size: u8,
}

impl Tsaps {
    /// A PG connection to the CPU in `rack`/`slot`, as Snap7 makes it.
    pub fn rack_slot(rack: u8, slot: u8) -> Tsaps {
        Tsaps {
            local: 0x0100,
            remote: 0x0100 | (u16::from(rack & 7) << 5) | u16::from(slot & 31),
            tpdu_size: 0x0A,
        }
    }
}

const CR: u8 = 0xE0;
const CC: u8 = 0xD0;
const DT: u8 = 0xF0;

impl Tpdu {
    /// The TPDU's bytes (what a TPKT carries).
    pub fn encode(&self, out: &mut BytesMut) {
        match self {
            Tpdu::ConnectRequest(t) | Tpdu::ConnectConfirm(t) => {
                let code = if matches!(self, Tpdu::ConnectRequest(_)) {
                    CR
                } else {
                    CC
                };
                // Length indicator, code, dst ref, src ref, class 0, then
                // TPDU size, calling and called TSAP.
                out.put_slice(&[17, code, 0, 0, 0, 1, 0]);
                out.put_slice(&[0xC0, 1, t.tpdu_size]);
                out.put_slice(&[0xC1, 2]);
                out.put_u16(t.local);
                out.put_slice(&[0xC2, 2]);
                out.put_u16(t.remote);
            }
            Tpdu::Data(pdu) => {
                out.put_slice(&[2, DT, 0x80]);
                out.put_slice(pdu);
            }
            Tpdu::Other(code) => out.put_slice(&[1, *code]),
        }
    }

    /// A TPDU from the bytes a TPKT carried.
    pub fn parse(bytes: &[u8]) -> Result<Tpdu, FrameError> {
        let li = usize::from(*bytes.first().ok_or_else(|| short("COTP header", 1, 0))?);
        if li == 0 || li + 1 > bytes.len() {
            return Err(FrameError(format!(
                "COTP length indicator {li} does not fit the {} bytes received",
                bytes.len()
            )));
        }
        let code = bytes[1] & 0xF0;
        match code {
            DT => {
                if li != 2 {
                    return Err(FrameError(format!("COTP DT length indicator {li}, not 2")));
                }
                if bytes[2] & 0x80 == 0 {
                    return Err(FrameError(
                        "COTP DT without end of TSDU: fragmented PDUs are not supported".into(),
                    ));
                }
                Ok(Tpdu::Data(Bytes::copy_from_slice(&bytes[3..])))
            }
            CR | CC => {
                if li < 6 {
                    return Err(FrameError(format!("COTP CR/CC length indicator {li} < 6")));
                }
                let mut tsaps = Tsaps {
                    local: 0,
                    remote: 0,
                    tpdu_size: 0x0A,
                };
                let mut at = 7;
                while at + 2 <= li + 1 {
                    let (kind, len) = (bytes[at], usize::from(bytes[at + 1]));
                    let value = bytes.get(at + 2..at + 2 + len).ok_or_else(|| {
                        FrameError(format!(
                            "COTP parameter 0x{kind:02X} at byte {at} runs past the TPDU"
                        ))
                    })?;
                    let word = || (len == 2).then(|| u16::from_be_bytes([value[0], value[1]]));
                    match kind {
                        0xC0 if len == 1 => tsaps.tpdu_size = value[0],
                        0xC1 => tsaps.local = word().unwrap_or(0),
                        0xC2 => tsaps.remote = word().unwrap_or(0),
                        _ => {}
                    }
                    at += 2 + len;
                }
                Ok(if code == CR {
                    Tpdu::ConnectRequest(tsaps)
                } else {
                    Tpdu::ConnectConfirm(tsaps)
                })
            }
            other => Ok(Tpdu::Other(other)),
        }
    }
}

/// One item of a read or write: `len` bytes from `start` of `region`, or
/// the one bit `bit` of byte `start` (a bit-transport item, so a write
/// keeps the byte's other bits).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Item {
    pub region: Region,
    pub start: u32,
    pub bit: Option<u8>,
    pub len: u16,
}

impl Item {
    /// Bytes of an item in a read or write job's parameters.
    pub const SPEC_LEN: usize = 12;

    /// `len` bytes from `start`.
    pub fn bytes(region: Region, start: u32, len: u16) -> Item {
        Item {
            region,
            start,
            bit: None,
            len,
        }
    }

    fn encode(&self, out: &mut BytesMut) {
        let (transport, address) = match self.bit {
            Some(bit) => (0x01, self.start * 8 + u32::from(bit & 7)),
            None => (0x02, self.start * 8),
        };
        out.put_slice(&[0x12, 0x0A, 0x10, transport]);
        out.put_u16(if self.bit.is_some() { 1 } else { self.len });
        out.put_u16(self.region.db());
        out.put_u8(self.region.code());
        out.put_slice(&address.to_be_bytes()[1..]);
    }

    /// An item from its 12 bytes (the simulated PLC's side).
    pub fn parse(spec: &[u8]) -> Result<Item, FrameError> {
        if spec.len() < Item::SPEC_LEN || spec[0] != 0x12 || spec[2] != 0x10 {
            return Err(FrameError(
                "item is not an S7-ANY address (0x12 .. 0x10)".into(),
            ));
        }
        let len = u16::from_be_bytes([spec[4], spec[5]]);
        let db = u16::from_be_bytes([spec[6], spec[7]]);
        let region = match spec[8] {
            0x81 => Region::Inputs,
            0x82 => Region::Outputs,
            0x83 => Region::Merkers,
            0x84 => Region::Db(db),
            other => return Err(FrameError(format!("area 0x{other:02X} is not served"))),
        };
        let address = u32::from_be_bytes([0, spec[9], spec[10], spec[11]]);
        let (bit, len) = match spec[3] {
            0x01 => (Some((address & 7) as u8), 1),
            0x02 => (None, len),
            other => {
                return Err(FrameError(format!(
                    "transport size 0x{other:02X} is not served"
                )))
            }
        };
        Ok(Item {
            region,
            start: address / 8,
            bit,
            len,
        })
    }
}

/// What a client asks.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Job {
    /// Setup communication: parallel jobs offered and the PDU size asked for.
    Setup {
        jobs: u16,
        pdu: u16,
    },
    Read(Vec<Item>),
    /// Items with their data (one byte, 0 or 1, for a bit item).
    Write(Vec<(Item, Bytes)>),
    /// Read a system status list part (userdata, CPU functions).
    ReadSzl {
        id: u16,
        index: u16,
    },
}

/// Bytes of a job's header (ROSCTR 1 and 7).
pub const JOB_HEADER: usize = 10;
/// Bytes of an ack-data header (ROSCTR 3: with error class and code).
pub const ACK_HEADER: usize = 12;
/// Bytes a read answer spends on each item besides its data (return code,
/// transport size, length), and at most one more to pad it to even.
pub const ANSWER_ITEM_HEAD: usize = 4;
/// A read or write job's function code and item count.
pub const PARAM_HEAD: usize = 2;

impl Job {
    /// The job's S7 PDU, numbered `pdu_ref`.
    pub fn encode(&self, pdu_ref: u16, out: &mut BytesMut) {
        let mut params = BytesMut::new();
        let mut data = BytesMut::new();
        let rosctr = match self {
            Job::Setup { jobs, pdu } => {
                params.put_slice(&[0xF0, 0]);
                params.put_u16(*jobs);
                params.put_u16(*jobs);
                params.put_u16(*pdu);
                1
            }
            Job::Read(items) => {
                params.put_slice(&[0x04, items.len() as u8]);
                items.iter().for_each(|i| i.encode(&mut params));
                1
            }
            Job::Write(items) => {
                params.put_slice(&[0x05, items.len() as u8]);
                for (n, (item, bytes)) in items.iter().enumerate() {
                    item.encode(&mut params);
                    let (transport, bits) = match item.bit {
                        Some(_) => (0x03, 1),
                        None => (0x04, bytes.len() as u16 * 8),
                    };
                    data.put_slice(&[0, transport]);
                    data.put_u16(bits);
                    data.put_slice(bytes);
                    if bytes.len() % 2 == 1 && n + 1 < items.len() {
                        data.put_u8(0);
                    }
                }
                1
            }
            Job::ReadSzl { id, index } => {
                params.put_slice(&[0x00, 0x01, 0x12, 0x04, 0x11, 0x44, 0x01, 0x00]);
                data.put_slice(&[0xFF, 0x09, 0x00, 0x04]);
                data.put_u16(*id);
                data.put_u16(*index);
                7
            }
        };
        out.put_slice(&[0x32, rosctr, 0, 0]);
        out.put_u16(pdu_ref);
        out.put_u16(params.len() as u16);
        out.put_u16(data.len() as u16);
        out.put_slice(&params);
        out.put_slice(&data);
    }

    /// A job from its S7 PDU, with its number (the simulated PLC's side).
    pub fn parse(pdu: &[u8]) -> Result<(u16, Job), FrameError> {
        let head = Head::parse(pdu)?;
        let (params, data) = (head.params, head.data);
        match (head.rosctr, params.first()) {
            (1, Some(0xF0)) if params.len() >= 8 => Ok((
                head.pdu_ref,
                Job::Setup {
                    jobs: u16::from_be_bytes([params[2], params[3]]),
                    pdu: u16::from_be_bytes([params[6], params[7]]),
                },
            )),
            (1, Some(0x04 | 0x05)) => {
                let count = usize::from(*params.get(1).ok_or_else(|| short("item count", 2, 1))?);
                let need = PARAM_HEAD + count * Item::SPEC_LEN;
                if params.len() < need {
                    return Err(short("item specifications", need, params.len()));
                }
                let items = params[PARAM_HEAD..need]
                    .chunks_exact(Item::SPEC_LEN)
                    .map(Item::parse)
                    .collect::<Result<Vec<_>, _>>()?;
                if params[0] == 0x04 {
                    return Ok((head.pdu_ref, Job::Read(items)));
                }
                let mut at = 0;
                let mut written = Vec::with_capacity(items.len());
                for item in items {
                    let h = data
                        .get(at..at + 4)
                        .ok_or_else(|| short("write data item", at + 4, data.len()))?;
                    let len = match h[1] {
                        0x03..=0x05 => usize::from(u16::from_be_bytes([h[2], h[3]])).div_ceil(8),
                        _ => usize::from(u16::from_be_bytes([h[2], h[3]])),
                    };
                    let bytes = data
                        .get(at + 4..at + 4 + len)
                        .ok_or_else(|| short("write data", at + 4 + len, data.len()))?;
                    written.push((item, Bytes::copy_from_slice(bytes)));
                    at += 4 + len + len % 2;
                }
                Ok((head.pdu_ref, Job::Write(written)))
            }
            (7, _) if params.len() >= 8 && params[5] == 0x44 && params[6] == 0x01 => {
                let d = data
                    .get(4..8)
                    .ok_or_else(|| short("SZL request", 8, data.len()))?;
                Ok((
                    head.pdu_ref,
                    Job::ReadSzl {
                        id: u16::from_be_bytes([d[0], d[1]]),
                        index: u16::from_be_bytes([d[2], d[3]]),
                    },
                ))
            }
            (rosctr, function) => Err(FrameError(format!(
                "job ROSCTR {rosctr} function {function:02X?} is not served"
            ))),
        }
    }
}

/// An S7 PDU's header and the parameters and data it frames.
struct Head<'a> {
    rosctr: u8,
    pdu_ref: u16,
    /// Error class and code of an ack-data (0: none).
    error: u16,
    params: &'a [u8],
    data: &'a [u8],
}

impl<'a> Head<'a> {
    fn parse(pdu: &'a [u8]) -> Result<Head<'a>, FrameError> {
        if pdu.len() < JOB_HEADER {
            return Err(short("S7 header", JOB_HEADER, pdu.len()));
        }
        if pdu[0] != 0x32 {
            return Err(FrameError(format!(
                "S7 protocol id 0x{:02X}, not 0x32",
                pdu[0]
            )));
        }
        let rosctr = pdu[1];
        let (header, error) = match rosctr {
            2 | 3 => {
                if pdu.len() < ACK_HEADER {
                    return Err(short("S7 ack header", ACK_HEADER, pdu.len()));
                }
                (ACK_HEADER, u16::from_be_bytes([pdu[10], pdu[11]]))
            }
            _ => (JOB_HEADER, 0),
        };
        let word = |at: usize| usize::from(u16::from_be_bytes([pdu[at], pdu[at + 1]]));
        let (plen, dlen) = (word(6), word(8));
        if header + plen + dlen != pdu.len() {
            return Err(FrameError(format!(
                "S7 header announces {plen} parameter and {dlen} data bytes, {} follow",
                pdu.len() - header
            )));
        }
        Ok(Head {
            rosctr,
            pdu_ref: u16::from_be_bytes([pdu[4], pdu[5]]),
            error,
            params: &pdu[header..header + plen],
            data: &pdu[header + plen..],
        })
    }
}

/// What a server answers to a job.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Answer {
    Setup {
        jobs: u16,
        pdu: u16,
    },
    /// Each item's data, or its return code.
    Read(Vec<Result<Bytes, ReturnCode>>),
    Write(Vec<Result<(), ReturnCode>>),
    /// The SZL's records (after its id, index, record length and count), or
    /// why not.
    Szl(Result<Bytes, ReturnCode>),
    /// The whole job refused (its header's error class and code).
    Refused(ReturnCode),
}

impl Answer {
    /// An answer and its number from the S7 PDU a server sent; `job` is
    /// the kind of job it answers (the answer's own function code names it
    /// too; they must agree).
    pub fn parse(pdu: &[u8]) -> Result<(u16, Answer), FrameError> {
        let head = Head::parse(pdu)?;
        let (params, data) = (head.params, head.data);
        if head.rosctr == 7 {
            return Ok((head.pdu_ref, parse_szl(params, data)?));
        }
        if !matches!(head.rosctr, 2 | 3) {
            return Err(FrameError(format!(
                "ROSCTR {} is not an answer",
                head.rosctr
            )));
        }
        if head.error != 0 {
            return Ok((head.pdu_ref, Answer::Refused(ReturnCode::Job(head.error))));
        }
        let count = || usize::from(params.get(1).copied().unwrap_or(0));
        let answer = match params.first() {
            Some(0xF0) if params.len() >= 8 => Answer::Setup {
                jobs: u16::from_be_bytes([params[2], params[3]]),
                pdu: u16::from_be_bytes([params[6], params[7]]),
            },
            Some(0x04) => {
                let mut items = Vec::with_capacity(count());
                let mut at = 0;
                for n in 0..count() {
                    let h = data.get(at..at + ANSWER_ITEM_HEAD).ok_or_else(|| {
                        FrameError(format!(
                            "read answer item {n}: header at data byte {at} missing"
                        ))
                    })?;
                    if h[0] != 0xFF {
                        items.push(Err(ReturnCode::Item(h[0])));
                        // A refused item may still carry its transport
                        // size and a zero length.
                        at += ANSWER_ITEM_HEAD;
                        continue;
                    }
                    let raw = usize::from(u16::from_be_bytes([h[2], h[3]]));
                    let len = match h[1] {
                        // Bit, byte/word/dword, integer: a length in bits.
                        0x03..=0x05 => raw.div_ceil(8),
                        _ => raw,
                    };
                    let bytes = data.get(at + 4..at + 4 + len).ok_or_else(|| {
                        FrameError(format!(
                            "read answer item {n}: {len} data bytes at data byte {} run past the {} received",
                            at + 4,
                            data.len()
                        ))
                    })?;
                    items.push(Ok(Bytes::copy_from_slice(bytes)));
                    at += 4 + len + len % 2;
                }
                Answer::Read(items)
            }
            Some(0x05) => {
                let codes = data
                    .get(..count())
                    .ok_or_else(|| short("write answer's return codes", count(), data.len()))?;
                Answer::Write(
                    codes
                        .iter()
                        .map(|&c| {
                            if c == 0xFF {
                                Ok(())
                            } else {
                                Err(ReturnCode::Item(c))
                            }
                        })
                        .collect(),
                )
            }
            other => {
                return Err(FrameError(format!(
                    "answer with function {other:02X?} not understood"
                )))
            }
        };
        Ok((head.pdu_ref, answer))
    }

    /// The answer's S7 PDU (the simulated PLC's side).
    pub fn encode(&self, pdu_ref: u16, out: &mut BytesMut) {
        let mut params = BytesMut::new();
        let mut data = BytesMut::new();
        let mut error = 0u16;
        let mut rosctr = 3;
        match self {
            Answer::Setup { jobs, pdu } => {
                params.put_slice(&[0xF0, 0]);
                params.put_u16(*jobs);
                params.put_u16(*jobs);
                params.put_u16(*pdu);
            }
            Answer::Read(items) => {
                params.put_slice(&[0x04, items.len() as u8]);
                for (n, item) in items.iter().enumerate() {
                    match item {
                        Ok(bytes) => {
                            data.put_slice(&[0xFF, 0x04]);
                            data.put_u16(bytes.len() as u16 * 8);
                            data.put_slice(bytes);
                            if bytes.len() % 2 == 1 && n + 1 < items.len() {
                                data.put_u8(0);
                            }
                        }
                        Err(code) => {
                            let byte = match code {
                                ReturnCode::Item(c) => *c,
                                ReturnCode::Job(_) => 0x0A,
                            };
                            data.put_slice(&[byte, 0, 0, 0]);
                        }
                    }
                }
            }
            Answer::Write(codes) => {
                params.put_slice(&[0x05, codes.len() as u8]);
                for code in codes {
                    data.put_u8(match code {
                        Ok(()) => 0xFF,
                        Err(ReturnCode::Item(c)) => *c,
                        Err(ReturnCode::Job(_)) => 0x0A,
                    });
                }
            }
            Answer::Szl(result) => {
                rosctr = 7;
                params.put_slice(&[0x00, 0x01, 0x12, 0x08, 0x12, 0x84, 0x01, 0x00, 0, 0, 0, 0]);
                match result {
                    Ok(records) => {
                        data.put_slice(&[0xFF, 0x09]);
                        data.put_u16(records.len() as u16);
                        data.put_slice(records);
                    }
                    Err(_) => data.put_slice(&[0x0A, 0x00, 0x00, 0x00]),
                }
            }
            Answer::Refused(code) => {
                error = match code {
                    ReturnCode::Job(c) => *c,
                    ReturnCode::Item(c) => u16::from(*c),
                };
            }
        }
        out.put_slice(&[0x32, rosctr, 0, 0]);
        out.put_u16(pdu_ref);
        out.put_u16(params.len() as u16);
        out.put_u16(data.len() as u16);
        if rosctr == 3 {
            out.put_u16(error);
        }
        out.put_slice(&params);
        out.put_slice(&data);
    }
}

/// A userdata answer to a read-SZL: its data after the 4-byte item head.
fn parse_szl(params: &[u8], data: &[u8]) -> Result<Answer, FrameError> {
    if params.len() >= 12 && u16::from_be_bytes([params[10], params[11]]) != 0 {
        let code = u16::from_be_bytes([params[10], params[11]]);
        return Ok(Answer::Szl(Err(ReturnCode::Job(code))));
    }
    let h = data
        .get(..4)
        .ok_or_else(|| short("SZL answer", 4, data.len()))?;
    if h[0] != 0xFF {
        return Ok(Answer::Szl(Err(ReturnCode::Item(h[0]))));
    }
    Ok(Answer::Szl(Ok(Bytes::copy_from_slice(&data[4..]))))
}

/// The CPU's mode from the SZL 0x0424 records (id, index, record length,
/// count, then 20-byte records): `Some(true)` in RUN, `Some(false)` in
/// STOP, `None` when the records do not say.
pub fn cpu_running(szl: &[u8]) -> Option<bool> {
    let mode = *szl.get(8 + 3)?;
    match mode {
        0x08 => Some(true),
        0x03..=0x06 => Some(false),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pdu(job: &Job) -> Vec<u8> {
        let mut out = BytesMut::new();
        job.encode(7, &mut out);
        out.to_vec()
    }

    #[test]
    fn connect_request_as_snap7_sends_it() {
        let mut out = BytesMut::new();
        Tpdu::ConnectRequest(Tsaps::rack_slot(0, 2)).encode(&mut out);
        assert_eq!(
            out.to_vec(),
            [0x11, 0xE0, 0, 0, 0, 1, 0, 0xC0, 1, 0x0A, 0xC1, 2, 1, 0, 0xC2, 2, 1, 2]
        );
        let back = Tpdu::parse(&out).unwrap();
        assert_eq!(back, Tpdu::ConnectRequest(Tsaps::rack_slot(0, 2)));
        assert_eq!(Tsaps::rack_slot(1, 3).remote, 0x0123);
    }

    #[test]
    fn read_job_items_and_back() {
        let items = vec![
            Item::bytes(Region::Db(1), 2, 4),
            Item {
                region: Region::Merkers,
                start: 10,
                bit: Some(3),
                len: 1,
            },
        ];
        let bytes = pdu(&Job::Read(items.clone()));
        assert_eq!(
            &bytes[..10],
            [0x32, 1, 0, 0, 0, 7, 0, 26, 0, 0],
            "header: 2 + 2 x 12 parameter bytes"
        );
        assert_eq!(
            &bytes[12..24],
            [0x12, 0x0A, 0x10, 0x02, 0, 4, 0, 1, 0x84, 0, 0, 16]
        );
        assert_eq!(
            &bytes[24..36],
            [0x12, 0x0A, 0x10, 0x01, 0, 1, 0, 0, 0x83, 0, 0, 83]
        );
        assert_eq!(Job::parse(&bytes).unwrap(), (7, Job::Read(items)));
    }

    #[test]
    fn write_job_pads_odd_items_but_the_last() {
        let job = Job::Write(vec![
            (Item::bytes(Region::Db(2), 0, 1), Bytes::from_static(&[9])),
            (
                Item::bytes(Region::Db(2), 4, 3),
                Bytes::from_static(&[1, 2, 3]),
            ),
        ]);
        let bytes = pdu(&job);
        let data = &bytes[10 + 26..];
        assert_eq!(data, [0, 4, 0, 8, 9, 0, 0, 4, 0, 24, 1, 2, 3]);
        assert_eq!(Job::parse(&bytes).unwrap(), (7, job));
    }

    #[test]
    fn answers_round_trip() {
        for answer in [
            Answer::Setup { jobs: 1, pdu: 480 },
            Answer::Read(vec![
                Ok(Bytes::from_static(&[1, 2, 3])),
                Err(ReturnCode::NO_OBJECT),
                Ok(Bytes::from_static(&[4])),
            ]),
            Answer::Write(vec![Ok(()), Err(ReturnCode::ACCESS_DENIED)]),
            Answer::Refused(ReturnCode::FUNCTION_NOT_ALLOWED),
            Answer::Szl(Ok(Bytes::from_static(&[4, 0x24, 0, 0, 0, 20, 0, 1]))),
        ] {
            let mut out = BytesMut::new();
            answer.encode(9, &mut out);
            let (n, back) = Answer::parse(&out).unwrap();
            assert_eq!((n, &back), (9, &answer));
        }
    }

    #[test]
    fn broken_answers_are_errors_naming_the_place() {
        let mut out = BytesMut::new();
        Answer::Read(vec![Ok(Bytes::from_static(&[1, 2, 3, 4]))]).encode(1, &mut out);
        let cut = &mut out.to_vec();
        cut[9] = 2; // data length 2, not 8
        cut.truncate(cut.len() - 6);
        let e = Answer::parse(cut).unwrap_err();
        assert!(e.0.contains("item 0"), "{e}");
        assert!(Answer::parse(&[0x32, 3]).is_err());
        assert!(Answer::parse(&[0x31; 12]).unwrap_err().0.contains("0x31"));
    }

    #[test]
    fn cpu_mode_from_szl_0424() {
        let mut szl = vec![0x04, 0x24, 0, 0, 0, 20, 0, 1];
        szl.extend_from_slice(&[0x51, 0x44, 0xFF, 0x08]);
        szl.resize(28, 0);
        assert_eq!(cpu_running(&szl), Some(true));
        szl[11] = 0x04;
        assert_eq!(cpu_running(&szl), Some(false));
        assert_eq!(cpu_running(&szl[..6]), None);
    }
}
