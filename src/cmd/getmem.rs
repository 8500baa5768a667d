//! `GETMEM:<name|%addr> <size>`: `size` bytes of PLC memory from the
//! variable's or the address's first byte, as `GETMEM:<name>[N]=<N raw
//! bytes>` blocks of at most MEM_BLKSIZE, then `GETMEM:<name>[0]=`.
//!
//! The name is printed as the client wrote it (the manual's example keeps
//! the client's spelling). An unparsable address, a bit address, a size of
//! 0 or over [`MAX_SIZE`] is ERROR 81; an unknown variable name ERROR 33; a
//! read the PLC refuses (past the end of an area) ERROR 80.

use plccoms_protocol::address::parse_direct;
use plccoms_protocol::answer::{write_error, ErrorCode};
use plccoms_protocol::request::{parse_getmem, ArgError};

use super::error;
use super::get::ReadThen;
use crate::backend::ReadRequest;
use crate::poller::{LinkError, ReadReply};
use crate::session::{Pending, Session};

/// Largest block one GETMEM reads.
pub const MAX_SIZE: u32 = 1024 * 1024;

pub async fn apply(session: &mut Session, args: &[u8], context: &[u8]) {
    let (name, size) = match parse_getmem(args) {
        Ok(parts) => parts,
        Err(ArgError::Incomplete) => return error(session, ErrorCode::Incomplete, context),
        Err(ArgError::Bad) => return error(session, ErrorCode::MemSet, args),
    };
    let (area, offset) = if name.first() == Some(&b'%') {
        match parse_direct(name) {
            Some(address) if address.bit.is_none() => (address.area, address.offset),
            _ => return error(session, ErrorCode::MemSet, name),
        }
    } else {
        let Some(id) = session.vars.table().lookup(name) else {
            return error(session, ErrorCode::UnknownVariable, context);
        };
        let var = session.vars.table().var(id);
        (var.area, var.offset)
    };
    if size == 0 || size > MAX_SIZE || offset.checked_add(size).is_none() {
        return error(session, ErrorCode::MemSet, name);
    }
    let request = ReadRequest {
        area,
        offset,
        len: size,
    };
    let rx = session.shared.poller.read(vec![request]).await;
    let then = ReadThen::Mem {
        name: name.to_vec(),
    };
    session.pending.push_back(Pending::Read { rx, then });
}

/// Writes the blocks once the PLC answered.
pub fn complete(session: &Session, name: &[u8], reply: ReadReply, out: &mut Vec<u8>) {
    let eol = session.conn.eol;
    match reply {
        Ok(answers) => match answers.into_iter().next() {
            Some(Ok(bytes)) => {
                let blksize = session.shared.global.mem_blksize;
                super::write_blocks(out, b"GETMEM", name, &bytes, blksize, eol);
            }
            _ => {
                write_error(out, ErrorCode::MemGet, name);
                out.extend_from_slice(eol);
            }
        },
        Err(LinkError::Offline) => {
            write_error(out, ErrorCode::ConnectPlc, b"");
            out.extend_from_slice(eol);
        }
        Err(LinkError::Plc(_)) => {
            write_error(out, ErrorCode::MemGet, name);
            out.extend_from_slice(eol);
        }
    }
}
