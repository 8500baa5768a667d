//! `HIDE:<mask>` and `UNHIDE:<mask>`: hidden variables are skipped by the
//! all-forms of EN, DI and GET. Answered with
//! `WARNING:253 Changed hidden variables in public file: '[<hidden>]'`.

use plccoms_protocol::answer::{ErrorCode, WarningCode};

use super::{error, select, warning, Selection};
use crate::session::Session;

pub fn apply(session: &mut Session, args: &[u8], context: &[u8], hide: bool) {
    // Hiding works on every variable the mask names, hidden or not.
    let selection = select(session.vars.table(), args, |_| false);
    if let Selection::Unknown = selection {
        return error(session, ErrorCode::UnknownVariable, context);
    }
    for id in selection.ids() {
        session.vars.set_hidden(id, hide);
    }
    let count = format!("[{}]", session.vars.hidden_count());
    warning(session, WarningCode::HiddenChanged, count.as_bytes());
}
