//! `HIDE:<mask>` and `UNHIDE:<mask>`: hidden variables are skipped by the
//! all-forms of EN, DI and GET. Answered with
//! `WARNING:253 Changed hidden variables in public file: '[<hidden>]'`.

use plccoms_protocol::answer::{ErrorCode, WarningCode};

use super::{error, select, warning, Cx, Reply, Selection};

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], hide: bool, out: &mut Vec<u8>) -> Reply {
    // Hiding works on every variable the mask names, hidden or not.
    let selection = select(cx.client.vars.table(), args, |_| false);
    if let Selection::Unknown = selection {
        return error(cx, ErrorCode::UnknownVariable, context, out);
    }
    for id in selection.ids() {
        cx.client.vars.set_hidden(id, hide);
    }
    let count = format!("[{}]", cx.client.vars.hidden_count());
    warning(cx, WarningCode::HiddenChanged, count.as_bytes(), out)
}
