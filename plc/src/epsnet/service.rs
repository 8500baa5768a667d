//! EPSNET services: the one table of service codes, and the payload of every
//! request and answer.
//!
//! Public (documented byte for byte): SETTID is FC 0x63 with request byte
//! 0x08, `YY MM DD hh mm ss ww`, answered `E5`; the error bytes 0x02, 0x03,
//! 0x04, 0x09, 0x0C.
//!
//! **Everything else here is this project's choice, unverified against a real
//! PLC.** It follows SETTID's shape: every request is a variable frame with
//! FC = [`FC_REQUEST`] (0x63) whose first data byte is the request code from
//! [`SERVICES`]. Answers:
//! - `E5` for a request that succeeded and returns nothing (writes, SETTID);
//! - a variable frame with FC = [`FC_ANSWER`] and data
//!   `<request code> 00 <payload>` for a request that returns data;
//! - a variable frame with FC = [`FC_ANSWER`] and data `<request code> <error
//!   byte>` (non-zero) for a refused request.
//!
//! Multi-byte protocol fields are big-endian (like DPLEN); memory contents are
//! raw PLC bytes (little-endian values). Areas travel as their letter
//! (`X`, `Y`, `S`, `R`). File times travel as the 8 raw `ttida` bytes (the
//! little-endian bytes of `FileInfo::created`/`modified`).
//!
//! | service        | FC   | req  | request data after req                        | answer payload                     |
//! |----------------|------|------|-----------------------------------------------|------------------------------------|
//! | IDENT          | 0x63 | 0x01 | —                                             | identification string (cp1250)    |
//! | GETSW          | 0x63 | 0x02 | —                                             | status word u16, bit 0 = RUN       |
//! | SETTID (public)| 0x63 | 0x08 | YY MM DD hh mm ss ww                          | `E5`                               |
//! | READN          | 0x63 | 0x10 | area, offset u32, len u16 (<= 1230)           | len bytes                          |
//! | WRITEN         | 0x63 | 0x11 | area, offset u32, bytes                       | `E5`                               |
//! | WRITEBITS      | 0x63 | 0x12 | area, offset u32, mask u8, value u8           | `E5` (byte = byte & !mask | value & mask) |
//! | FILEINFO       | 0x63 | 0x20 | path                                          | size u64, attr u32, created, modified |
//! | FILEREAD       | 0x63 | 0x21 | offset u64, len u16 (<= 1150), path           | up to len bytes (fewer at the end) |
//! | FILEWRITE      | 0x63 | 0x22 | offset u64, flags u8 (bit 0 last), path len u8, path, data | `E5`                  |
//! | FILEWRITEINFO  | 0x63 | 0x23 | attr u32, created, modified, path             | `E5`                               |
//! | DIRLIST        | 0x63 | 0x24 | first entry index u16, path                   | more u8, then entries: size u64, attr u32, created, modified, name len u8, name |
//!
//! A FILEWRITE at offset 0 starts the file anew; blocks must follow each other
//! without gaps; the file appears (atomically) with the block flagged last.

use plccoms_protocol::Area;

use super::frame::{data_frame_len, DataFrame, Frame};
use super::Exception;
use crate::files::{DirEntry, FileInfo};

/// Function code of every request (public for SETTID, adopted for the rest).
pub const FC_REQUEST: u8 = 0x63;
/// Function code of an answer frame that carries data or an error byte.
pub const FC_ANSWER: u8 = 0x08;

pub const IDENT: u8 = 0x01;
pub const GETSW: u8 = 0x02;
pub const SETTID: u8 = 0x08;
pub const READN: u8 = 0x10;
pub const WRITEN: u8 = 0x11;
pub const WRITEBITS: u8 = 0x12;
pub const FILEINFO: u8 = 0x20;
pub const FILEREAD: u8 = 0x21;
pub const FILEWRITE: u8 = 0x22;
pub const FILEWRITEINFO: u8 = 0x23;
pub const DIRLIST: u8 = 0x24;

/// The table: name, request code, whether the code is public.
pub const SERVICES: &[(&str, u8, bool)] = &[
    ("IDENT", IDENT, false),
    ("GETSW", GETSW, false),
    ("SETTID", SETTID, true),
    ("READN", READN, false),
    ("WRITEN", WRITEN, false),
    ("WRITEBITS", WRITEBITS, false),
    ("FILEINFO", FILEINFO, false),
    ("FILEREAD", FILEREAD, false),
    ("FILEWRITE", FILEWRITE, false),
    ("FILEWRITEINFO", FILEWRITEINFO, false),
    ("DIRLIST", DIRLIST, false),
];

/// Largest memory block per READN (the vendor server's limit).
pub const MAX_READ: u32 = 1230;
/// Largest file block per FILEREAD / FILEWRITE (the vendor server's limit).
pub const MAX_FILE_BLOCK: u32 = 1150;
/// Largest path accepted in a file request.
pub const MAX_PATH: usize = 255;
/// Largest answer payload a DIRLIST page may carry.
pub const MAX_DIR_PAGE: usize = MAX_READ as usize;
/// Longest identification string a PLC answers.
pub const MAX_IDENT: usize = 64;
/// Bytes of an encoded `FileInfo`.
pub const FILE_INFO_LEN: usize = 28;

/// PLC clock setting, as SETTID carries it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlcTime {
    pub year: u16,
    pub month: u8,
    pub day: u8,
    pub hour: u8,
    pub minute: u8,
    pub second: u8,
    /// 1 = Monday .. 7 = Sunday.
    pub weekday: u8,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Request {
    Ident,
    Status,
    SetTime(PlcTime),
    Read {
        area: Area,
        offset: u32,
        len: u16,
    },
    Write {
        area: Area,
        offset: u32,
        data: Vec<u8>,
    },
    WriteBits {
        area: Area,
        offset: u32,
        mask: u8,
        value: u8,
    },
    FileInfo {
        path: Vec<u8>,
    },
    FileRead {
        path: Vec<u8>,
        offset: u64,
        len: u16,
    },
    FileWrite {
        path: Vec<u8>,
        offset: u64,
        last: bool,
        data: Vec<u8>,
    },
    FileWriteInfo {
        path: Vec<u8>,
        info: FileInfo,
    },
    DirList {
        path: Vec<u8>,
        start: u16,
    },
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Response {
    /// `E5`: done, nothing to return.
    Done,
    Ident(Vec<u8>),
    Status {
        run: bool,
    },
    Data(Vec<u8>),
    FileInfo(FileInfo),
    DirPage {
        entries: Vec<DirEntry>,
        more: bool,
    },
}

/// An answer frame that does not fit the request it should answer.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ServiceError {
    #[error("answer frame has FC 0x{0:02X}, expected 0x{FC_ANSWER:02X}")]
    BadFc(u8),
    #[error("answer for request 0x{found:02X}, expected 0x{expected:02X}")]
    WrongRequest { expected: u8, found: u8 },
    #[error("answer to request 0x{0:02X} too short")]
    TooShort(u8),
    #[error("answer to request 0x{0:02X} malformed: {1}")]
    Malformed(u8, &'static str),
    #[error("E5 answer to request 0x{0:02X}, which returns data")]
    UnexpectedAck(u8),
}

fn area_code(area: Area) -> u8 {
    area.letter() as u8
}

fn put_info(out: &mut Vec<u8>, info: &FileInfo, with_size: bool) {
    if with_size {
        out.extend_from_slice(&info.size.to_be_bytes());
    }
    out.extend_from_slice(&info.attributes.to_be_bytes());
    out.extend_from_slice(&info.created.to_le_bytes());
    out.extend_from_slice(&info.modified.to_le_bytes());
}

/// A cursor over untrusted bytes: every read is checked.
struct Reader<'a>(&'a [u8]);

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        if self.0.len() < n {
            return None;
        }
        let (head, tail) = self.0.split_at(n);
        self.0 = tail;
        Some(head)
    }
    fn u8(&mut self) -> Option<u8> {
        self.take(1).map(|b| b[0])
    }
    fn u16(&mut self) -> Option<u16> {
        self.take(2).map(|b| u16::from_be_bytes([b[0], b[1]]))
    }
    fn u32(&mut self) -> Option<u32> {
        self.take(4)
            .and_then(|b| b.try_into().ok())
            .map(u32::from_be_bytes)
    }
    fn u64(&mut self) -> Option<u64> {
        self.take(8)
            .and_then(|b| b.try_into().ok())
            .map(u64::from_be_bytes)
    }
    fn u64_le(&mut self) -> Option<u64> {
        self.take(8)
            .and_then(|b| b.try_into().ok())
            .map(u64::from_le_bytes)
    }
    fn area(&mut self) -> Option<Area> {
        self.u8().and_then(Area::from_letter)
    }
    fn info(&mut self, with_size: bool) -> Option<FileInfo> {
        let size = if with_size { self.u64()? } else { 0 };
        Some(FileInfo {
            size,
            attributes: self.u32()?,
            created: self.u64_le()?,
            modified: self.u64_le()?,
        })
    }
    fn rest(&mut self) -> &'a [u8] {
        std::mem::take(&mut self.0)
    }
}

impl Request {
    pub fn code(&self) -> u8 {
        match self {
            Request::Ident => IDENT,
            Request::Status => GETSW,
            Request::SetTime(_) => SETTID,
            Request::Read { .. } => READN,
            Request::Write { .. } => WRITEN,
            Request::WriteBits { .. } => WRITEBITS,
            Request::FileInfo { .. } => FILEINFO,
            Request::FileRead { .. } => FILEREAD,
            Request::FileWrite { .. } => FILEWRITE,
            Request::FileWriteInfo { .. } => FILEWRITEINFO,
            Request::DirList { .. } => DIRLIST,
        }
    }

    /// The data of the request frame (request code first).
    pub fn encode(&self) -> Vec<u8> {
        let mut out = vec![self.code()];
        match self {
            Request::Ident | Request::Status => {}
            Request::SetTime(t) => out.extend_from_slice(&[
                t.year.saturating_sub(2000).min(255) as u8,
                t.month,
                t.day,
                t.hour,
                t.minute,
                t.second,
                t.weekday,
            ]),
            Request::Read { area, offset, len } => {
                out.push(area_code(*area));
                out.extend_from_slice(&offset.to_be_bytes());
                out.extend_from_slice(&len.to_be_bytes());
            }
            Request::Write { area, offset, data } => {
                out.push(area_code(*area));
                out.extend_from_slice(&offset.to_be_bytes());
                out.extend_from_slice(data);
            }
            Request::WriteBits {
                area,
                offset,
                mask,
                value,
            } => {
                out.push(area_code(*area));
                out.extend_from_slice(&offset.to_be_bytes());
                out.extend_from_slice(&[*mask, *value]);
            }
            Request::FileInfo { path } => out.extend_from_slice(path),
            Request::FileRead { path, offset, len } => {
                out.extend_from_slice(&offset.to_be_bytes());
                out.extend_from_slice(&len.to_be_bytes());
                out.extend_from_slice(path);
            }
            Request::FileWrite {
                path,
                offset,
                last,
                data,
            } => {
                out.extend_from_slice(&offset.to_be_bytes());
                out.push(u8::from(*last));
                out.push(path.len().min(MAX_PATH) as u8);
                out.extend_from_slice(&path[..path.len().min(MAX_PATH)]);
                out.extend_from_slice(data);
            }
            Request::FileWriteInfo { path, info } => {
                put_info(&mut out, info, false);
                out.extend_from_slice(path);
            }
            Request::DirList { path, start } => {
                out.extend_from_slice(&start.to_be_bytes());
                out.extend_from_slice(path);
            }
        }
        out
    }

    /// The request frame, from `sa` to the PLC at `da`.
    pub fn to_frame(&self, da: u8, sa: u8) -> Frame {
        Frame::Data(DataFrame {
            da,
            sa,
            fc: FC_REQUEST,
            data: self.encode(),
        })
    }

    /// Parses a request frame's FC and data (the PLC side). The error is the
    /// byte the PLC answers with.
    pub fn decode(fc: u8, data: &[u8]) -> Result<Request, Exception> {
        if fc != FC_REQUEST {
            return Err(Exception::UnknownService);
        }
        let mut r = Reader(data);
        let code = r.u8().ok_or(Exception::BadParameters)?;
        let bad = Exception::BadParameters;
        let request = match code {
            IDENT => Request::Ident,
            GETSW => Request::Status,
            SETTID => {
                let b = r.take(7).ok_or(bad)?;
                Request::SetTime(PlcTime {
                    year: 2000 + u16::from(b[0]),
                    month: b[1],
                    day: b[2],
                    hour: b[3],
                    minute: b[4],
                    second: b[5],
                    weekday: b[6],
                })
            }
            READN => Request::Read {
                area: r.area().ok_or(bad)?,
                offset: r.u32().ok_or(bad)?,
                len: r.u16().ok_or(bad)?,
            },
            WRITEN => Request::Write {
                area: r.area().ok_or(bad)?,
                offset: r.u32().ok_or(bad)?,
                data: r.rest().to_vec(),
            },
            WRITEBITS => Request::WriteBits {
                area: r.area().ok_or(bad)?,
                offset: r.u32().ok_or(bad)?,
                mask: r.u8().ok_or(bad)?,
                value: r.u8().ok_or(bad)?,
            },
            FILEINFO => Request::FileInfo {
                path: r.rest().to_vec(),
            },
            FILEREAD => Request::FileRead {
                offset: r.u64().ok_or(bad)?,
                len: r.u16().ok_or(bad)?,
                path: r.rest().to_vec(),
            },
            FILEWRITE => {
                let offset = r.u64().ok_or(bad)?;
                let flags = r.u8().ok_or(bad)?;
                let path_len = r.u8().ok_or(bad)?;
                let path = r.take(usize::from(path_len)).ok_or(bad)?.to_vec();
                Request::FileWrite {
                    path,
                    offset,
                    last: flags & 1 != 0,
                    data: r.rest().to_vec(),
                }
            }
            FILEWRITEINFO => Request::FileWriteInfo {
                info: r.info(false).ok_or(bad)?,
                path: r.rest().to_vec(),
            },
            DIRLIST => Request::DirList {
                start: r.u16().ok_or(bad)?,
                path: r.rest().to_vec(),
            },
            _ => return Err(Exception::UnknownService),
        };
        if !r.0.is_empty() {
            return Err(bad);
        }
        Ok(request)
    }

    /// Largest wire length of the answer frame, for packing requests so the
    /// answer datagram fits too.
    pub fn max_answer_len(&self) -> usize {
        let payload = match self {
            Request::Ident => MAX_IDENT,
            Request::Status => 2,
            Request::Read { len, .. } | Request::FileRead { len, .. } => usize::from(*len),
            Request::FileInfo { .. } => FILE_INFO_LEN,
            Request::DirList { .. } => MAX_DIR_PAGE,
            Request::SetTime(_)
            | Request::Write { .. }
            | Request::WriteBits { .. }
            | Request::FileWrite { .. }
            | Request::FileWriteInfo { .. } => 0,
        };
        data_frame_len(2 + payload)
    }
}

/// The answer frame for `code` (PLC side).
pub fn answer_frame(da: u8, sa: u8, code: u8, answer: &Result<Response, Exception>) -> Frame {
    let mut data = vec![code];
    match answer {
        Err(e) => {
            let byte = e.to_byte();
            // 0 means success on the wire; never send it as an error.
            data.push(if byte == 0 { 0x0C } else { byte });
        }
        Ok(Response::Done) => return Frame::Ack,
        Ok(response) => {
            data.push(0);
            encode_payload(response, &mut data);
        }
    }
    Frame::Data(DataFrame {
        da,
        sa,
        fc: FC_ANSWER,
        data,
    })
}

fn encode_payload(response: &Response, out: &mut Vec<u8>) {
    match response {
        Response::Done => {}
        Response::Ident(bytes) | Response::Data(bytes) => out.extend_from_slice(bytes),
        Response::Status { run } => out.extend_from_slice(&u16::from(*run).to_be_bytes()),
        Response::FileInfo(info) => put_info(out, info, true),
        Response::DirPage { entries, more } => {
            out.push(u8::from(*more));
            for entry in entries {
                put_info(out, &entry.info, true);
                let len = entry.name.len().min(MAX_PATH);
                out.push(len as u8);
                out.extend_from_slice(&entry.name[..len]);
            }
        }
    }
}

/// Wire size of one directory entry in a DIRLIST answer.
pub fn dir_entry_len(entry: &DirEntry) -> usize {
    FILE_INFO_LEN + 1 + entry.name.len().min(MAX_PATH)
}

/// Interprets the answer frame to `request` (client side). The outer error
/// is a frame that makes no sense; the inner one is the PLC's error byte.
pub fn decode_answer(
    request: &Request,
    frame: &Frame,
) -> Result<Result<Response, Exception>, ServiceError> {
    let code = request.code();
    let f = match frame {
        Frame::Ack => {
            return match request {
                Request::SetTime(_)
                | Request::Write { .. }
                | Request::WriteBits { .. }
                | Request::FileWrite { .. }
                | Request::FileWriteInfo { .. } => Ok(Ok(Response::Done)),
                _ => Err(ServiceError::UnexpectedAck(code)),
            }
        }
        Frame::Data(f) => f,
    };
    if f.fc != FC_ANSWER {
        return Err(ServiceError::BadFc(f.fc));
    }
    let mut r = Reader(&f.data);
    let found = r.u8().ok_or(ServiceError::TooShort(code))?;
    if found != code {
        return Err(ServiceError::WrongRequest {
            expected: code,
            found,
        });
    }
    let status = r.u8().ok_or(ServiceError::TooShort(code))?;
    if status != 0 {
        return Ok(Err(Exception::from_byte(status)));
    }
    let malformed = |what| ServiceError::Malformed(code, what);
    let response = match request {
        Request::Ident => Response::Ident(r.rest().to_vec()),
        Request::Status => {
            let word = r.u16().ok_or(malformed("status word"))?;
            Response::Status { run: word & 1 != 0 }
        }
        Request::Read { len, .. } => {
            let data = r.rest();
            if data.len() != usize::from(*len) {
                return Err(malformed("data length differs from request"));
            }
            Response::Data(data.to_vec())
        }
        Request::FileRead { len, .. } => {
            let data = r.rest();
            if data.len() > usize::from(*len) {
                return Err(malformed("more data than requested"));
            }
            Response::Data(data.to_vec())
        }
        Request::FileInfo { .. } => Response::FileInfo(r.info(true).ok_or(malformed("file info"))?),
        Request::DirList { .. } => {
            let more = r.u8().ok_or(malformed("more flag"))? != 0;
            let mut entries = Vec::new();
            while !r.0.is_empty() {
                let info = r.info(true).ok_or(malformed("entry info"))?;
                let len = r.u8().ok_or(malformed("entry name length"))?;
                let name = r.take(usize::from(len)).ok_or(malformed("entry name"))?;
                entries.push(DirEntry {
                    name: name.to_vec(),
                    info,
                });
            }
            Response::DirPage { entries, more }
        }
        Request::SetTime(_)
        | Request::Write { .. }
        | Request::WriteBits { .. }
        | Request::FileWrite { .. }
        | Request::FileWriteInfo { .. } => Response::Done,
    };
    if !r.0.is_empty() {
        return Err(malformed("trailing bytes"));
    }
    Ok(Ok(response))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(request: Request) {
        let bytes = request.encode();
        assert_eq!(Request::decode(FC_REQUEST, &bytes), Ok(request));
    }

    #[test]
    fn requests_round_trip() {
        round_trip(Request::Ident);
        round_trip(Request::Status);
        round_trip(Request::SetTime(PlcTime {
            year: 2024,
            month: 3,
            day: 15,
            hour: 13,
            minute: 45,
            second: 30,
            weekday: 5,
        }));
        round_trip(Request::Read {
            area: Area::R,
            offset: 70000,
            len: 1230,
        });
        round_trip(Request::Write {
            area: Area::S,
            offset: 2,
            data: vec![1, 2, 3],
        });
        round_trip(Request::WriteBits {
            area: Area::R,
            offset: 5,
            mask: 0x02,
            value: 0x02,
        });
        round_trip(Request::FileInfo {
            path: b"a/b.txt".to_vec(),
        });
        round_trip(Request::FileRead {
            path: b"x".to_vec(),
            offset: 1 << 33,
            len: 1150,
        });
        round_trip(Request::FileWrite {
            path: b"dir/f".to_vec(),
            offset: 1150,
            last: true,
            data: vec![9; 10],
        });
        round_trip(Request::FileWriteInfo {
            path: b"f".to_vec(),
            info: FileInfo {
                size: 0,
                attributes: 1,
                created: 7,
                modified: 8,
            },
        });
        round_trip(Request::DirList {
            path: b"/".to_vec(),
            start: 3,
        });
    }

    #[test]
    fn settid_is_the_public_form() {
        let t = PlcTime {
            year: 2024,
            month: 3,
            day: 15,
            hour: 13,
            minute: 45,
            second: 30,
            weekday: 5,
        };
        assert_eq!(
            Request::SetTime(t).to_frame(0, 0x7D),
            Frame::Data(DataFrame {
                da: 0,
                sa: 0x7D,
                fc: 0x63,
                data: vec![0x08, 24, 3, 15, 13, 45, 30, 5]
            })
        );
        let answer = answer_frame(0x7D, 0, SETTID, &Ok(Response::Done));
        assert_eq!(answer, Frame::Ack);
    }

    #[test]
    fn answers_round_trip_and_errors_carry_the_byte() {
        let read = Request::Read {
            area: Area::R,
            offset: 0,
            len: 3,
        };
        let frame = answer_frame(1, 0, READN, &Ok(Response::Data(vec![1, 2, 3])));
        assert_eq!(
            decode_answer(&read, &frame),
            Ok(Ok(Response::Data(vec![1, 2, 3])))
        );
        for e in [0x02, 0x03, 0x04, 0x09, 0x0C] {
            let frame = answer_frame(1, 0, READN, &Err(Exception::from_byte(e)));
            assert_eq!(
                decode_answer(&read, &frame),
                Ok(Err(Exception::from_byte(e)))
            );
        }
        let short = answer_frame(1, 0, READN, &Ok(Response::Data(vec![1, 2])));
        assert!(decode_answer(&read, &short).is_err());
        let wrong = answer_frame(1, 0, GETSW, &Ok(Response::Status { run: true }));
        assert!(matches!(
            decode_answer(&read, &wrong),
            Err(ServiceError::WrongRequest { .. })
        ));
        let list = Request::DirList {
            path: vec![],
            start: 0,
        };
        let entries = vec![DirEntry {
            name: b"a.txt".to_vec(),
            info: FileInfo {
                size: 5,
                attributes: 0x20,
                created: 1,
                modified: 2,
            },
        }];
        let frame = answer_frame(
            1,
            0,
            DIRLIST,
            &Ok(Response::DirPage {
                entries: entries.clone(),
                more: true,
            }),
        );
        assert_eq!(
            decode_answer(&list, &frame),
            Ok(Ok(Response::DirPage {
                entries,
                more: true
            }))
        );
    }

    #[test]
    fn bad_requests_get_error_bytes() {
        assert_eq!(Request::decode(0x10, &[1]), Err(Exception::UnknownService));
        assert_eq!(
            Request::decode(FC_REQUEST, &[0x7F]),
            Err(Exception::UnknownService)
        );
        assert_eq!(
            Request::decode(FC_REQUEST, &[]),
            Err(Exception::BadParameters)
        );
        assert_eq!(
            Request::decode(FC_REQUEST, &[READN, b'Q', 0, 0, 0, 0, 0, 1]),
            Err(Exception::BadParameters)
        );
        assert_eq!(
            Request::decode(FC_REQUEST, &[READN, b'R', 0, 0]),
            Err(Exception::BadParameters)
        );
        assert_eq!(
            Request::decode(FC_REQUEST, &[IDENT, 0]),
            Err(Exception::BadParameters)
        );
    }
}
