//! `SET:<name|%addr>,<value>`: writes the value (a BOOL as its bit only) and
//! answers `DIFF:<NAME>,<value>` with the value read back from the PLC, unless
//! DIFF lines are off for this client. An invalid value, or one the
//! variable's raw type cannot hold (a scaled Modbus tag), is ERROR:35 and
//! nothing is written; a SET of a read-only variable (a Modbus input, or a
//! tag with `access = ro`) is ERROR:30 with the request, as on a `READ_ONLY`
//! section.
//!
//! The write itself is [`Section::start_write`](plccoms_core::section::Section),
//! the one write path of every app; this renders its refusals as
//! `ERROR:` lines.

use std::sync::Arc;

use plccoms_protocol::answer::{write_error, ErrorCode};
use plccoms_protocol::request::{parse_set, ArgError};

use super::{error, Cx, Reply};
use plccoms_core::link::SetReply;
use plccoms_core::section::write::WriteTarget;

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], out: &mut Vec<u8>) -> Reply {
    let (name, text) = match parse_set(args) {
        Ok(parts) => parts,
        Err(ArgError::Incomplete) => return error(cx, ErrorCode::Incomplete, context, out),
        Err(ArgError::Bad) => return error(cx, ErrorCode::BadRequest, context, out),
    };
    let table = cx.client.vars.table().clone();
    match cx.section.start_write(&table, name, text) {
        Ok(pending) => Reply::set(pending.reply, pending.target),
        Err(refusal) => error(cx, refusal.code(), &refusal.context(name, context), out),
    }
}

pub fn complete(cx: &mut Cx<'_>, target: WriteTarget, reply: SetReply, out: &mut Vec<u8>) {
    let eol = cx.client.eol;
    let written = match target.confirm(reply) {
        Ok(written) => written,
        Err(refusal) => {
            // Only refusals of the link's answer get here: no request context.
            write_error(out, refusal.code(), &refusal.context(&[], &[]));
            out.extend_from_slice(eol);
            return;
        }
    };
    if cx.client.diff {
        out.extend_from_slice(b"DIFF:");
        out.extend_from_slice(&written.name);
        out.push(b',');
        out.extend_from_slice(&written.text);
        out.extend_from_slice(eol);
    }
    // The table may have changed while the SET was under way.
    if let Some((table, id)) = written.var {
        if Arc::ptr_eq(&table, cx.client.vars.table()) {
            cx.client
                .vars
                .mark_sent(id, written.seq, Some(written.value));
        }
    }
}
