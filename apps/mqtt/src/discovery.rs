//! Home Assistant MQTT discovery (MQTT_HA_DISCOVERY = Yes): one retained
//! config message per published variable on
//! `homeassistant/<component>/<id>/config`, one device per section.
//!
//! | variable                  | component       |
//! | ------------------------- | --------------- |
//! | BOOL, writable            | `switch`        |
//! | BOOL                      | `binary_sensor` |
//! | number, writable          | `number` (min and max of its type) |
//! | number, DATE, DT          | `sensor`        |
//! | STRING (DATE, DT), writable | `text`        |
//! | STRING                    | `sensor`        |
//!
//! "Writable" means matched by MQTT_WRITE in a section that is not
//! READ_ONLY. `<id>` (also the `unique_id`) is made of the prefix, the
//! section and the variable's name only, so it is the same across restarts
//! and public-file reloads, and Home Assistant keeps the entity and its
//! settings. Entities are available while both the section's `status` and
//! its `plc` topic say `online`.
//!
//! The configs are sent on each connection, on a new table, and when Home
//! Assistant says `online` on [`HA_STATUS`] (any client of the broker can):
//! one announcement at a time, made config by config as the connection has
//! room, and an `online` while one is pending or running is absorbed by it.
//!
//! The config topics announced are remembered in the spool folder
//! (`discovery`), so a variable that is gone — from a new public file, a
//! new MQTT_PUBLISH, or discovery turned off — has its config cleared (an
//! empty retained message), after a restart too.

use std::collections::BTreeSet;
use std::io;
use std::path::Path;

use plccoms_protocol::{cp1250, IecType};
use serde_json::{json, Map, Value};

use super::settings::CRC32;
use super::topics::{level, Topics};
use plccoms_core::config::MqttFormat;
use plccoms_core::vars::Var;

pub const PREFIX: &str = "homeassistant";
/// Home Assistant announces itself here (`online`) when it starts: configs
/// are sent again then.
pub const HA_STATUS: &str = "homeassistant/status";

/// The section-wide parts of every config.
pub struct Device<'a> {
    pub prefix: &'a str,
    pub section: &'a str,
    pub topics: &'a Topics,
    pub format: MqttFormat,
    pub qos: u8,
}

/// `text` as an id Home Assistant accepts (`[A-Za-z0-9_-]`): unchanged if it
/// is one, else made one, with a hash of the original so that two names
/// differing only in other characters stay apart.
pub fn object_id(text: &str) -> String {
    let safe: String = text
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    if safe == text {
        safe
    } else {
        format!("{safe}_{:08x}", CRC32.checksum(text.as_bytes()))
    }
}

fn is_numeric(ty: IecType) -> bool {
    !matches!(
        ty,
        IecType::Bool | IecType::String(_) | IecType::Date | IecType::Dt
    )
}

fn component(var: &Var, writable: bool) -> &'static str {
    match (var.ty, writable) {
        (IecType::Bool, true) => "switch",
        (IecType::Bool, false) => "binary_sensor",
        (ty, true) if is_numeric(ty) => "number",
        (_, true) => "text",
        (_, false) => "sensor",
    }
}

fn entity_id(device: &Device<'_>, name: &str) -> String {
    object_id(&format!("{}_{}_{}", device.prefix, device.section, name))
}

/// The topic of a variable's config (what [`config`] makes, without the
/// payload).
pub fn config_topic(device: &Device<'_>, var: &Var, writable: bool) -> String {
    let id = entity_id(device, &cp1250::decode(&var.name));
    format!("{PREFIX}/{}/{id}/config", component(var, writable))
}

/// The topic and payload of a variable's config.
pub fn config(device: &Device<'_>, var: &Var, writable: bool) -> (String, Vec<u8>) {
    let name = cp1250::decode(&var.name).into_owned();
    let id = entity_id(device, &name);
    let state = device.topics.value(&var.name);
    let numeric = is_numeric(var.ty);
    let component = component(var, writable);
    let mut c = Map::new();
    c.insert("name".into(), json!(name));
    c.insert("unique_id".into(), json!(id));
    c.insert("state_topic".into(), json!(state));
    c.insert("qos".into(), json!(device.qos));
    let template = match (device.format, var.ty) {
        (MqttFormat::Json, _) => Some("{{ value_json.value }}"),
        // The plain text of a STRING is quoted, as GET prints it.
        (MqttFormat::Plain, IecType::String(_)) => Some("{{ value[1:-1] }}"),
        (MqttFormat::Plain, _) => None,
    };
    if let Some(template) = template {
        c.insert("value_template".into(), json!(template));
    }
    if writable {
        c.insert(
            "command_topic".into(),
            json!(format!(
                "{}/set",
                device.topics.value_of_level(&level(&var.name))
            )),
        );
    }
    match component {
        "switch" => {
            for (key, value) in [
                ("payload_on", "1"),
                ("payload_off", "0"),
                ("state_on", "1"),
                ("state_off", "0"),
            ] {
                c.insert(key.into(), json!(value));
            }
        }
        "binary_sensor" => {
            c.insert("payload_on".into(), json!("1"));
            c.insert("payload_off".into(), json!("0"));
        }
        "number" => {
            let (min, max, step) = range(var.ty);
            c.insert("min".into(), min);
            c.insert("max".into(), max);
            c.insert("step".into(), json!(step));
            c.insert("mode".into(), json!("box"));
        }
        "text" => {
            if let IecType::String(n) = var.ty {
                c.insert("max".into(), json!(n));
            }
        }
        _ if numeric => {
            c.insert("state_class".into(), json!("measurement"));
        }
        _ => {}
    }
    c.insert(
        "availability".into(),
        json!([{"topic": device.topics.status()}, {"topic": device.topics.plc()}]),
    );
    c.insert("availability_mode".into(), json!("all"));
    c.insert(
        "device".into(),
        json!({
            "identifiers": [object_id(&format!("{}_{}", device.prefix, device.section))],
            "name": device.section,
            "manufacturer": "Teco",
            "model": "Tecomat PLC (plccoms)",
            "sw_version": env!("CARGO_PKG_VERSION"),
        }),
    );
    c.insert(
        "origin".into(),
        json!({"name": "plccoms", "sw_version": env!("CARGO_PKG_VERSION")}),
    );
    let topic = config_topic(device, var, writable);
    (topic, Value::Object(c).to_string().into_bytes())
}

/// min, max and step of a number entity for `ty`.
fn range(ty: IecType) -> (Value, Value, f64) {
    let int = |min: i128, max: i128| (json!(min as f64), json!(max as f64), 1.0);
    match ty {
        IecType::Byte | IecType::Usint => int(0, u8::MAX.into()),
        IecType::Word | IecType::Uint => int(0, u16::MAX.into()),
        IecType::Dword | IecType::Udint | IecType::Time | IecType::Tod => int(0, u32::MAX.into()),
        IecType::Lword | IecType::Ulint => int(0, u64::MAX.into()),
        IecType::Sint => int(i8::MIN.into(), i8::MAX.into()),
        IecType::Int => int(i16::MIN.into(), i16::MAX.into()),
        IecType::Dint => int(i32::MIN.into(), i32::MAX.into()),
        IecType::Lint => int(i64::MIN.into(), i64::MAX.into()),
        IecType::Real => (json!(-f32::MAX), json!(f32::MAX), 0.001),
        _ => (json!(-f64::MAX), json!(f64::MAX), 0.001),
    }
}

/// The config topics announced last, from the spool folder.
pub fn load_announced(dir: &Path) -> BTreeSet<String> {
    std::fs::read_to_string(dir.join("discovery"))
        .map(|text| text.lines().map(str::to_string).collect())
        .unwrap_or_default()
}

/// Remembers the config topics announced (written whole, then renamed).
pub fn save_announced(dir: &Path, topics: &BTreeSet<String>) -> io::Result<()> {
    let mut text = String::new();
    for topic in topics {
        text.push_str(topic);
        text.push('\n');
    }
    let tmp = dir.join("discovery.tmp");
    std::fs::write(&tmp, text)?;
    std::fs::rename(tmp, dir.join("discovery"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_core::vars::table_of;

    fn parse(payload: &[u8]) -> Value {
        serde_json::from_slice(payload).unwrap()
    }

    #[test]
    fn components_and_the_fields_home_assistant_needs() {
        let table = table_of(&[
            ("SW", "BOOL"),
            ("T", "REAL"),
            ("S", "STRING[40]"),
            ("N", "INT"),
        ]);
        let topics = Topics::new("plccoms", "Hala 1");
        let device = Device {
            prefix: "plccoms",
            section: "Hala 1",
            topics: &topics,
            format: MqttFormat::Plain,
            qos: 1,
        };
        let var = |name: &[u8]| table.var(table.lookup(name).unwrap());
        let (topic, payload) = config(&device, var(b"SW"), true);
        let id = object_id("plccoms_Hala 1_SW");
        assert_eq!(topic, format!("homeassistant/switch/{id}/config"));
        let c = parse(&payload);
        assert_eq!(c["command_topic"], "plccoms/Hala 1/SW/set");
        assert_eq!(c["state_topic"], "plccoms/Hala 1/SW");
        assert_eq!(c["payload_on"], "1");
        assert_eq!(c["availability"][0]["topic"], "plccoms/Hala 1/status");
        assert_eq!(c["availability"][1]["topic"], "plccoms/Hala 1/plc");
        assert_eq!(c["device"]["name"], "Hala 1");
        assert!(c["unique_id"]
            .as_str()
            .unwrap()
            .starts_with("plccoms_Hala_1_SW_"));
        let (topic, _) = config(&device, var(b"SW"), false);
        assert!(topic.starts_with("homeassistant/binary_sensor/"));
        assert_eq!(config_topic(&device, var(b"SW"), false), topic);
        let c = parse(&config(&device, var(b"N"), true).1);
        assert_eq!(
            (c["min"].as_f64(), c["max"].as_f64()),
            (Some(-32768.0), Some(32767.0))
        );
        let c = parse(&config(&device, var(b"T"), false).1);
        assert_eq!(c["state_class"], "measurement");
        let c = parse(&config(&device, var(b"S"), true).1);
        assert_eq!(
            (c["max"].as_u64(), c["value_template"].as_str()),
            (Some(40), Some("{{ value[1:-1] }}"))
        );
    }

    #[test]
    fn ids_are_safe_and_stay_apart() {
        assert_eq!(object_id("plccoms_Demo_COUNTER"), "plccoms_Demo_COUNTER");
        assert_ne!(object_id("a.b"), object_id("a b"));
        assert!(object_id("p/x_Š")
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_'));
    }

    #[test]
    fn announced_topics_are_remembered() {
        let dir = tempfile::tempdir().unwrap();
        assert!(load_announced(dir.path()).is_empty());
        let set: BTreeSet<String> = ["a/b/config".to_string(), "c/d/config".into()].into();
        save_announced(dir.path(), &set).unwrap();
        assert_eq!(load_announced(dir.path()), set);
    }
}
