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

use super::{error, link_error, Cx, ReadThen, Reply};
use plccoms_core::driver::ReadRequest;
use plccoms_core::link::ReadReply;

/// Largest block one GETMEM reads.
pub const MAX_SIZE: u32 = 1024 * 1024;

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], out: &mut Vec<u8>) -> Reply {
    let (name, size) = match parse_getmem(args) {
        Ok(parts) => parts,
        Err(ArgError::Incomplete) => return error(cx, ErrorCode::Incomplete, context, out),
        Err(ArgError::Bad) => return error(cx, ErrorCode::MemSet, args, out),
    };
    let (area, offset) = if name.first() == Some(&b'%') {
        match parse_direct(name) {
            Some(address) if address.bit.is_none() => (address.area, address.offset),
            _ => return error(cx, ErrorCode::MemSet, name, out),
        }
    } else {
        let table = cx.client.vars.table();
        let Some(id) = table.lookup(name) else {
            return error(cx, ErrorCode::UnknownVariable, context, out);
        };
        let var = table.var(id);
        (var.area, var.offset)
    };
    if size == 0 || size > MAX_SIZE || offset.checked_add(size).is_none() {
        return error(cx, ErrorCode::MemSet, name, out);
    }
    let request = ReadRequest {
        area,
        offset,
        len: size,
    };
    let then = ReadThen::Mem {
        name: name.to_vec(),
        size,
    };
    Reply::read(cx.section.read(vec![request]), then)
}

/// Writes the blocks once the PLC answered.
pub fn complete(cx: &Cx<'_>, name: &[u8], reply: ReadReply, out: &mut Vec<u8>) {
    let eol = cx.client.eol;
    match reply {
        Ok(answers) => match answers.into_iter().next() {
            Some(Ok(bytes)) => {
                let blksize = cx.section.global().mem_blksize;
                super::write_blocks(out, b"GETMEM", name, &bytes, blksize, eol);
            }
            _ => {
                write_error(out, ErrorCode::MemGet, name);
                out.extend_from_slice(eol);
            }
        },
        Err(err @ plccoms_core::link::LinkError::Offline) => {
            link_error(err, ErrorCode::MemGet, eol, out)
        }
        Err(_) => {
            write_error(out, ErrorCode::MemGet, name);
            out.extend_from_slice(eol);
        }
    }
}
