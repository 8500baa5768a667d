//! `EN:[mask] [delta]` and `DI:[mask] [delta]`: enable or disable variables
//! for this client, answered with
//! `WARNING:252 Changed active variables in public file: '[<enabled>/<total>]'`.

use plccoms_protocol::answer::{ErrorCode, WarningCode};
use plccoms_protocol::request::parse_mask_delta;
use plccoms_protocol::value::Delta;

use super::{error, select, warning, Selection};
use crate::session::Session;

pub fn apply(session: &mut Session, args: &[u8], context: &[u8], enable: bool) {
    let Ok((mask, delta)) = parse_mask_delta(args) else {
        return error(session, ErrorCode::WrongValue, context);
    };
    let delta = match delta.map(Delta::parse).transpose() {
        Ok(delta) => delta,
        Err(_) => return error(session, ErrorCode::WrongValue, context),
    };
    let selection = select(session.vars.table(), mask, |id| session.vars.is_hidden(id));
    if let Selection::Unknown = selection {
        return error(session, ErrorCode::UnknownVariable, context);
    }
    for id in selection.ids() {
        if enable {
            session.vars.enable(id);
        } else {
            session.vars.disable(id);
        }
        if let Some(delta) = &delta {
            session.vars.set_delta(id, *delta);
        }
    }
    let counts = format!(
        "[{}/{}]",
        session.vars.enabled_total(),
        session.vars.table().len()
    );
    warning(session, WarningCode::ActiveChanged, counts.as_bytes());
}
