//! `EN:[mask] [delta]` and `DI:[mask] [delta]`: enable or disable variables
//! for this client, answered with
//! `WARNING:252 Changed active variables in public file: '[<enabled>/<total>]'`.

use plccoms_protocol::answer::{ErrorCode, WarningCode};
use plccoms_protocol::request::parse_mask_delta;
use plccoms_protocol::value::Delta;

use super::{error, select, warning, Cx, Reply, Selection};

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], enable: bool, out: &mut Vec<u8>) -> Reply {
    let Ok((mask, delta)) = parse_mask_delta(args) else {
        return error(cx, ErrorCode::WrongValue, context, out);
    };
    let delta = match delta.map(Delta::parse).transpose() {
        Ok(delta) => delta,
        Err(_) => return error(cx, ErrorCode::WrongValue, context, out),
    };
    let vars = &mut cx.client.vars;
    let selection = select(vars.table(), mask, |id| vars.is_hidden(id));
    if let Selection::Unknown = selection {
        return error(cx, ErrorCode::UnknownVariable, context, out);
    }
    for id in selection.ids() {
        if enable {
            vars.enable(id);
        } else {
            vars.disable(id);
        }
        if let Some(delta) = &delta {
            vars.set_delta(id, *delta);
        }
    }
    let counts = format!("[{}/{}]", vars.enabled_total(), vars.table().len());
    warning(cx, WarningCode::ActiveChanged, counts.as_bytes(), out)
}
