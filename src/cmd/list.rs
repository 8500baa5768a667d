//! `LIST:[mask]`: `LIST:<NAME>,<TYPE>` per variable, `*` when disabled for
//! this client, `~` when hidden, then `LIST:`.

use std::io::Write;

use plccoms_protocol::mask::Mask;

use crate::session::Session;

pub fn apply(session: &mut Session, args: &[u8]) {
    let mask = Mask::new(args);
    let all = mask.is_all();
    let eol = session.conn.eol;
    let vars = &session.vars;
    let table = vars.table();
    let mut out = Vec::with_capacity(if all { table.len() * 32 } else { 256 });
    for (id, var) in table.vars().iter().enumerate() {
        if !all && !mask.matches(&var.name) {
            continue;
        }
        let id = id as u32;
        out.extend_from_slice(b"LIST:");
        out.extend_from_slice(&var.name);
        let _ = write!(out, ",{}", var.ty);
        if !vars.is_enabled(id) {
            out.push(b'*');
        }
        if vars.is_hidden(id) {
            out.push(b'~');
        }
        out.extend_from_slice(eol);
    }
    out.extend_from_slice(b"LIST:");
    out.extend_from_slice(eol);
    session.answer(out);
}
