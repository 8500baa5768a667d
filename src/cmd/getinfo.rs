//! `GETINFO:[key]`: information about the server, its PLC and its clients.
//! The bare form lists every key in the vendor's order and ends with
//! `GETINFO:`; a named key answers one line (NETWORK its list, terminated).
//! A Modbus section lists PROTOCOL, MODBUS_PORT and MODBUS_UNIT in place of
//! EPSADDR and EPSPORT; an EPSNET section's list is the vendor's (its
//! PROTOCOL answers when asked by name).

use std::fmt::Write;

use plccoms_protocol::answer::ErrorCode;

use super::{error, Cx, Reply};

const KEYS: &[&str] = &[
    "VERSION",
    "VERSION_EPSNET",
    "VERSION_INI",
    "VERSION_PLC",
    "PROTOCOL",
    "IPADDR",
    "EPSADDR",
    "EPSPORT",
    "MODBUS_PORT",
    "MODBUS_UNIT",
    "SERIAL_DEVICE",
    "PUBFILE",
    "NETWORK",
];

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], out: &mut Vec<u8>) -> Reply {
    let eol = cx.client.eol;
    let mut text = String::new();
    if args.is_empty() {
        for key in KEYS {
            lines(cx, key, &mut text, true);
        }
        text.push_str("GETINFO:\n");
    } else {
        let key = String::from_utf8_lossy(args).to_ascii_uppercase();
        // The manual's table calls it epsnet_version.
        let key = if key == "EPSNET_VERSION" {
            "VERSION_EPSNET".to_string()
        } else {
            key
        };
        if !KEYS.contains(&key.as_str()) {
            return error(cx, ErrorCode::GetInfoUnknown, context, out);
        }
        lines(cx, &key, &mut text, false);
    }
    out.reserve(text.len() + 16);
    for line in text.lines() {
        out.extend_from_slice(line.as_bytes());
        out.extend_from_slice(eol);
    }
    Reply::Done
}

/// Appends the lines of `key`, each ended by `\n`.
fn lines(cx: &Cx<'_>, key: &str, text: &mut String, listing_all: bool) {
    // The settings as SETCONF left them, and the link as it is.
    let state = cx.section.state();
    let (config, link) = (&state.config, &state.link);
    let modbus = config.protocol == "MODBUS_TCP";
    // The full list shows what the section's protocol has.
    let shown = match key {
        "PROTOCOL" | "MODBUS_PORT" | "MODBUS_UNIT" => modbus,
        "EPSADDR" | "EPSPORT" => !modbus,
        _ => true,
    };
    if listing_all && !shown {
        return;
    }
    match key {
        "PROTOCOL" => line(text, key, &config.protocol),
        "MODBUS_PORT" => line(text, key, &config.modbus.port.to_string()),
        "MODBUS_UNIT" => line(text, key, &config.modbus.unit.to_string()),
        "VERSION" => line(
            text,
            key,
            &format!("Ver {} (plccoms)", env!("CARGO_PKG_VERSION")),
        ),
        "VERSION_EPSNET" => line(
            text,
            key,
            &format!("Ver {} (plccoms EPSNET)", env!("CARGO_PKG_VERSION")),
        ),
        "VERSION_INI" => line(text, key, "Ver 0.21 (rust-ini)"),
        "VERSION_PLC" => line(text, key, link.ident.as_deref().unwrap_or("")),
        "IPADDR" => line(
            text,
            key,
            &config
                .ipaddr
                .map(|ip| ip.to_string())
                .unwrap_or_else(|| "0.0.0.0".into()),
        ),
        "EPSADDR" => line(
            text,
            key,
            &link
                .source_address
                .map(|a| a.to_string())
                .unwrap_or_default(),
        ),
        "EPSPORT" => line(text, key, &config.epsport.to_string()),
        "SERIAL_DEVICE" => {
            // Only sections on a serial line show it in the full list.
            if let Some(device) = &config.serial_device {
                let speed = config
                    .serial_speed
                    .map(|s| format!(" {s}"))
                    .unwrap_or_default();
                line(text, key, &format!("{device}{speed}"));
            } else if !listing_all {
                line(text, key, "");
            }
        }
        "PUBFILE" => {
            let table = cx.client.vars.table();
            let files = match &table.user_file {
                Some(user) => format!("{},{}", table.fixed_file, user),
                None => table.fixed_file.clone(),
            };
            line(
                text,
                key,
                &format!("{}/{} [{}]", table.fixed_count(), table.len(), files),
            );
        }
        "NETWORK" => {
            let max = cx.section.global.net_connect_max;
            for (i, client) in cx.section.clients().iter().enumerate() {
                let ip = client.peer.ip().to_string();
                line(
                    text,
                    key,
                    &format!("{}/{} [{:<15} {}]", i + 1, max, ip, client.connected),
                );
            }
            if !listing_all {
                text.push_str("GETINFO:\n");
            }
        }
        _ => {}
    }
}

fn line(text: &mut String, key: &str, value: &str) {
    let _ = writeln!(text, "GETINFO:{key},{value}");
}
