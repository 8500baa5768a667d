//! `GETINFO:[key]`: information about the server, its PLC and its clients.
//! The bare form lists every key in the vendor's order and ends with
//! `GETINFO:`; a named key answers one line (NETWORK its list, terminated).
//! A Modbus section lists PROTOCOL, MODBUS_PORT and MODBUS_UNIT in place of
//! EPSADDR and EPSPORT, MODBUS_TAGS (`2/33 [tags.csv]`: the system
//! variables, all variables, the tag file) in place of PUBFILE, and no
//! VERSION_EPSNET: nothing EPSNET speaks for it. Asked by name, those keys
//! still answer (PUBFILE as MODBUS_TAGS: no FIXED.pub is read). An S7
//! section likewise, with S7_PORT and S7_TAGS (VERSION_PLC names the PDU
//! the CPU granted). An EPSNET
//! section's list is the vendor's (its PROTOCOL answers when asked by
//! name).

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
    "S7_PORT",
    "OPCUA_URL",
    "SERIAL_DEVICE",
    "PUBFILE",
    "MODBUS_TAGS",
    "S7_TAGS",
    "NETWORK",
];

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], out: &mut Vec<u8>) -> Reply {
    let eol = cx.client.eol;
    let mut text = String::new();
    let history = cx.section.info_lines();
    if args.is_empty() {
        for key in KEYS {
            lines(cx, key, &mut text, true);
        }
        // This server's own keys, after the vendor's, only where they apply.
        for (key, value) in history.iter().flatten() {
            line(&mut text, key, value);
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
        if let Some((key, value)) = history.iter().flatten().find(|(k, _)| *k == key) {
            line(&mut text, key, value);
        } else if !KEYS.contains(&key.as_str()) {
            return error(cx, ErrorCode::GetInfoUnknown, context, out);
        } else {
            lines(cx, &key, &mut text, false);
        }
    }
    out.reserve(text.len() + 16);
    for line in text.lines() {
        out.extend_from_slice(line.as_bytes());
        out.extend_from_slice(eol);
    }
    Reply::Done
}

/// This server's `major.minor` (`-V` prints the whole version).
const SERVER_VERSION: &str = concat!(
    env!("CARGO_PKG_VERSION_MAJOR"),
    ".",
    env!("CARGO_PKG_VERSION_MINOR")
);
/// The rust-ini release the configuration is read with.
const INI_VERSION: &str = "0.21";

/// The vendor's shape, `Ver 5.5 Sep  9 2020 16:10:19`: `major.minor`, then
/// the build's date as C's `__DATE__ __TIME__` (build.rs), so clients that
/// parse PLCComS's answer parse this one.
fn version(major_minor: &str) -> String {
    format!("Ver {major_minor} {}", env!("PLCCOMS_BUILD_DATE"))
}

/// Appends the lines of `key`, each ended by `\n`.
fn lines(cx: &Cx<'_>, key: &str, text: &mut String, listing_all: bool) {
    // The settings as SETCONF left them, and the link as it is.
    let state = cx.section.state();
    let (config, link) = (&state.config, &state.link);
    let modbus = config.protocol.is_modbus();
    let s7 = config.protocol == plccoms_core::config::Protocol::S7;
    let opcua = config.protocol == plccoms_core::config::Protocol::Opcua;
    // The full list shows what the section's protocol has.
    let shown = match key {
        "PROTOCOL" => modbus || s7 || opcua,
        "MODBUS_PORT" | "MODBUS_UNIT" | "MODBUS_TAGS" => modbus,
        "S7_PORT" | "S7_TAGS" => s7,
        "OPCUA_URL" => opcua,
        "VERSION_EPSNET" | "EPSADDR" | "EPSPORT" => !modbus && !s7 && !opcua,
        "IPADDR" => !opcua,
        // An OPC UA section's variable list (OPCUA_VARS.csv) shows here.
        "PUBFILE" => !modbus && !s7,
        _ => true,
    };
    if listing_all && !shown {
        return;
    }
    match key {
        "PROTOCOL" => line(text, key, config.protocol.name()),
        "MODBUS_PORT" => line(text, key, &config.modbus.port.to_string()),
        "MODBUS_UNIT" => line(text, key, &config.modbus.unit.to_string()),
        "S7_PORT" => line(text, key, &config.s7.port.to_string()),
        "OPCUA_URL" => line(text, key, config.opcua_client.url.as_deref().unwrap_or("")),
        // The EPSNET code and the ini parser are built with the server.
        "VERSION" | "VERSION_EPSNET" => line(text, key, &version(SERVER_VERSION)),
        "VERSION_INI" => line(text, key, &version(INI_VERSION)),
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
        // Asked by name on an EPSNET section: it has no tag file.
        "MODBUS_TAGS" if !modbus => line(text, key, ""),
        "S7_TAGS" if !s7 => line(text, key, ""),
        "PUBFILE" | "MODBUS_TAGS" | "S7_TAGS" => {
            let table = cx.client.vars.table();
            let files = match (&table.user_file, modbus || s7 || opcua) {
                (Some(user), false) => format!("{},{}", table.fixed_file, user),
                (None, false) => table.fixed_file.clone(),
                // The backend answers the system variables: no fixed file.
                (user, true) => user.clone().unwrap_or_default(),
            };
            line(
                text,
                key,
                &format!("{}/{} [{}]", table.fixed_count(), table.len(), files),
            );
        }
        "NETWORK" => {
            let max = cx.section.global().net_connect_max;
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

#[cfg(test)]
mod tests {
    use super::*;

    /// What a client of PLCComS reads from `Ver 5.5 Sep  9 2020 16:10:19`:
    /// two numbers, a month, a day, a year and a time.
    fn parse(answer: &str) -> Option<(u32, u32, &str, u32, u32, &str)> {
        let rest = answer.strip_prefix("Ver ")?;
        let (number, date) = rest.split_once(' ')?;
        let (major, minor) = number.split_once('.')?;
        let mut words = date.split_whitespace();
        let month = words.next()?;
        let day = words.next()?.parse().ok()?;
        let year = words.next()?.parse().ok()?;
        let time = words.next()?;
        let months = "Jan Feb Mar Apr May Jun Jul Aug Sep Oct Nov Dec";
        let clock = time.len() == 8 && time.as_bytes()[2] == b':' && time.as_bytes()[5] == b':';
        (words.next().is_none() && month.len() == 3 && months.contains(month) && clock).then_some((
            major.parse().ok()?,
            minor.parse().ok()?,
            month,
            day,
            year,
            time,
        ))
    }

    #[test]
    fn versions_have_the_vendors_shape() {
        assert_eq!(
            parse("Ver 5.5 Sep  9 2020 16:10:19"),
            Some((5, 5, "Sep", 9, 2020, "16:10:19"))
        );
        assert_eq!(parse("Ver 0.1.0 (plccoms)"), None);
        for answer in [version(SERVER_VERSION), version(INI_VERSION)] {
            let (_, _, _, day, year, _) = parse(&answer).unwrap_or_else(|| panic!("{answer:?}"));
            assert!((1..=31).contains(&day) && year >= 2024, "{answer:?}");
            // C's __DATE__ pads the day to two places: the date is 20 long.
            let date = answer.splitn(3, ' ').nth(2).unwrap();
            assert_eq!(date.len(), "Sep  9 2020 16:10:19".len(), "{answer:?}");
        }
    }
}
