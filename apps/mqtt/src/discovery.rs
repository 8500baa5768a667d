//! Home Assistant MQTT discovery (MQTT_HA_DISCOVERY = Yes): one retained
//! config message per published variable on
//! `homeassistant/<component>/<id>/config`, one device per section.
//!
//! | variable | component |
//! | --- | --- |
//! | BOOL, writable | `switch` |
//! | BOOL | `binary_sensor` (`__PLC_RUN`: `device_class: running`) |
//! | integer, REAL, LREAL, writable | `number` |
//! | integer, REAL, LREAL | `sensor` |
//! | DT (and a Modbus TS48) | `sensor`, `device_class: timestamp` |
//! | DATE | `sensor`, `device_class: date` |
//! | TIME, TOD | `sensor` (no device class: Home Assistant has none for a duration given as ISO 8601 text, nor for a time of day) |
//! | STRING, writable | `text` |
//! | STRING | `sensor` |
//!
//! "Writable" means all of: matched by MQTT_WRITE, a section that is not
//! READ_ONLY, a variable its backend can write (not a Modbus input or
//! discrete input, not `access ro`), and not a system variable (`__*`).
//! Times are never writable entities: `/set` takes their ISO forms, but
//! Home Assistant has no entity that sends them.
//!
//! A number's entity carries the variable's unit (`unit_of_measurement`)
//! and, where the unit implies one, its `device_class` (°C/°F/K
//! temperature, W/kW power, Wh/kWh/MWh energy, V voltage, A current,
//! Pa/hPa/bar pressure, Hz frequency). The name is the tag file's
//! description when it has one, else the variable's name. A number
//! `sensor` is a `measurement` (energy: `total_increasing`, a meter's
//! counter), except system variables and CRCs, which have no state class;
//! system variables are `diagnostic` entities. A `number` has the tag
//! file's `min`, `max` (else its type's range; a REAL or LREAL without them
//! -1e9 to 1e9 in a box, [`REAL_LIMIT`]) and a step of 10^-decimals (else 1
//! for an integer, 0.001, the smallest Home Assistant takes, for a REAL).
//!
//! `<id>` (also the `unique_id`) is made of the prefix, the section and
//! the variable's name only, so it is the same across restarts and
//! public-file reloads, and Home Assistant keeps the entity and its
//! settings. Entities are available while both the section's `status` and
//! its `plc` topic say `online`.
//!
//! The configs are sent on each connection, on a new table, when the PLC's
//! identification changes, and when Home Assistant says `online` on
//! [`HA_STATUS`] (any client of the broker can): one announcement at a
//! time, made config by config as the connection has room, and an `online`
//! while one is pending or running is absorbed by it.
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
use plccoms_core::config::{self, MqttFormat, Protocol};
use plccoms_core::vars::Var;

pub const PREFIX: &str = "homeassistant";
/// Home Assistant announces itself here (`online`) when it starts: configs
/// are sent again then.
pub const HA_STATUS: &str = "homeassistant/status";

/// The range of a writable REAL or LREAL whose tag file gives none (a
/// public file never does): Home Assistant needs one, and its default
/// (1 to 100) would refuse most values, while ±3.4e38 makes no sense to
/// anyone.
pub const REAL_LIMIT: f64 = 1e9;

/// The smallest step Home Assistant's MQTT number takes.
const MIN_STEP: f64 = 0.001;

/// The section-wide parts of every config.
pub struct Device<'a> {
    pub prefix: &'a str,
    pub section: &'a str,
    pub topics: &'a Topics,
    pub format: MqttFormat,
    pub qos: u8,
    pub maker: &'a Maker,
}

/// Who made the device, as Home Assistant's device page shows it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Maker {
    pub manufacturer: String,
    pub model: String,
    /// The PLC's identification, once known.
    pub hw_version: Option<String>,
}

impl Maker {
    /// The maker of a section's device by its backend: a Tecomat PLC (with
    /// its identification `ident`, once connected), or a Modbus TCP device
    /// known by its address.
    pub fn of(section: &config::Section, ident: Option<&str>) -> Maker {
        match section.protocol {
            Protocol::Epsnet => Maker {
                manufacturer: "Teco".into(),
                model: "Tecomat PLC".into(),
                hw_version: ident.map(str::to_string).filter(|i| !i.is_empty()),
            },
            Protocol::ModbusRtu => Maker {
                manufacturer: "Modbus RTU device".into(),
                model: format!(
                    "{} unit {}",
                    section.serial_device.as_deref().unwrap_or("?"),
                    section.modbus.unit
                ),
                hw_version: None,
            },
            Protocol::ModbusTcp | Protocol::ModbusRtuTcp => Maker {
                manufacturer: if section.protocol == Protocol::ModbusTcp {
                    "Modbus TCP device".into()
                } else {
                    "Modbus RTU device".into()
                },
                model: format!(
                    "{}:{} unit {}",
                    section
                        .ipaddr
                        .map_or_else(|| "?".to_string(), |a| a.to_string()),
                    section.modbus.port,
                    section.modbus.unit
                ),
                hw_version: None,
            },
            Protocol::S7 => Maker {
                manufacturer: "Siemens".into(),
                model: format!(
                    "S7 CPU at {}:{}",
                    section
                        .ipaddr
                        .map_or_else(|| "?".to_string(), |a| a.to_string()),
                    section.s7.port
                ),
                hw_version: ident.map(str::to_string).filter(|i| !i.is_empty()),
            },
            Protocol::Ads => Maker {
                manufacturer: "Beckhoff".into(),
                model: "TwinCAT PLC (ADS)".into(),
                hw_version: ident.map(str::to_string).filter(|i| !i.is_empty()),
            },
            Protocol::Opcua => Maker {
                manufacturer: "OPC UA server".into(),
                model: section.opcua_client.url.clone().unwrap_or_default(),
                hw_version: ident.map(str::to_string).filter(|i| !i.is_empty()),
            },
        }
    }
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

/// Integers, REAL and LREAL: a number to Home Assistant (times are text).
fn is_number(ty: IecType) -> bool {
    !matches!(
        ty,
        IecType::Bool
            | IecType::String(_)
            | IecType::Date
            | IecType::Dt
            | IecType::Tod
            | IecType::Time
    )
}

fn is_real(ty: IecType) -> bool {
    matches!(ty, IecType::Real | IecType::Lreal)
}

/// A system variable (`__PLC_RUN`, `__PF_CRC`, ...): the server's or the
/// PLC's own, never a writable entity.
fn is_system(var: &Var) -> bool {
    var.name.starts_with(b"__")
}

/// Whether a variable is announced as an entity that writes: `mqtt_write`
/// is MQTT_WRITE's verdict, `read_only` the section's READ_ONLY.
pub fn writable(var: &Var, read_only: bool, mqtt_write: bool) -> bool {
    mqtt_write && !read_only && var.writable && !is_system(var) && {
        let ty = var.ty;
        !matches!(
            ty,
            IecType::Date | IecType::Dt | IecType::Tod | IecType::Time
        )
    }
}

fn component(var: &Var, writable: bool) -> &'static str {
    match (var.ty, writable) {
        (IecType::Bool, true) => "switch",
        (IecType::Bool, false) => "binary_sensor",
        (ty, true) if is_number(ty) => "number",
        (IecType::String(_), true) => "text",
        _ => "sensor",
    }
}

/// The device class a unit implies, for a number.
fn unit_class(unit: &str) -> Option<&'static str> {
    Some(match unit {
        "°C" | "°F" | "K" => "temperature",
        "W" | "kW" => "power",
        "Wh" | "kWh" | "MWh" => "energy",
        "V" => "voltage",
        "A" => "current",
        "Pa" | "hPa" | "bar" => "pressure",
        "Hz" => "frequency",
        _ => return None,
    })
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

/// The topic and payload of a variable's config; `writable` as
/// [`writable`] says.
pub fn config(device: &Device<'_>, var: &Var, writable: bool) -> (String, Vec<u8>) {
    let name = cp1250::decode(&var.name).into_owned();
    let info = var.info.as_deref();
    let description = info.map(|i| i.description.trim()).filter(|d| !d.is_empty());
    let unit = info.map(|i| i.unit.trim()).filter(|u| !u.is_empty());
    let system = is_system(var);
    let number = is_number(var.ty);
    let component = component(var, writable);
    let mut c = Map::new();
    c.insert("name".into(), json!(description.unwrap_or(&name)));
    c.insert("unique_id".into(), json!(entity_id(device, &name)));
    c.insert("state_topic".into(), json!(device.topics.value(&var.name)));
    c.insert("qos".into(), json!(device.qos));
    let template = match (device.format, var.ty) {
        // Home Assistant renders a JSON true as `True`.
        (MqttFormat::Json, IecType::Bool) => Some("{{ 'true' if value_json.value else 'false' }}"),
        (MqttFormat::Json, _) => Some("{{ value_json.value }}"),
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
    if system {
        c.insert("entity_category".into(), json!("diagnostic"));
    }
    // The unit and its device class: numbers only (Home Assistant takes a
    // unit as the promise of a numeric state).
    let class = unit.filter(|_| number).and_then(unit_class);
    if number {
        if let Some(unit) = unit {
            c.insert("unit_of_measurement".into(), json!(unit));
        }
        if let Some(class) = class {
            c.insert("device_class".into(), json!(class));
        }
    }
    let decimals = info.and_then(|i| i.decimals);
    match component {
        "switch" | "binary_sensor" => {
            c.insert("payload_on".into(), json!("true"));
            c.insert("payload_off".into(), json!("false"));
            if component == "switch" {
                c.insert("state_on".into(), json!("true"));
                c.insert("state_off".into(), json!("false"));
            } else if &*var.name == b"__PLC_RUN" {
                c.insert("device_class".into(), json!("running"));
            }
        }
        "number" => {
            let (min, max, mode) =
                range(var.ty, info.and_then(|i| i.min), info.and_then(|i| i.max));
            let step = match decimals {
                _ if !is_real(var.ty) => 1.0,
                Some(d) => 10f64.powi(-i32::from(d)).max(MIN_STEP),
                None => MIN_STEP,
            };
            c.insert("min".into(), json!(min));
            c.insert("max".into(), json!(max));
            c.insert("step".into(), json!(step));
            c.insert("mode".into(), json!(mode));
        }
        "text" => {
            if let IecType::String(n) = var.ty {
                c.insert("max".into(), json!(n));
            }
        }
        _ => match var.ty {
            IecType::Dt => {
                c.insert("device_class".into(), json!("timestamp"));
            }
            IecType::Date => {
                c.insert("device_class".into(), json!("date"));
            }
            ty if is_number(ty) => {
                let crc = name.to_ascii_uppercase().contains("CRC");
                let state_class = match class {
                    _ if system || crc => None,
                    Some("energy") => Some("total_increasing"),
                    _ => Some("measurement"),
                };
                if let Some(state_class) = state_class {
                    c.insert("state_class".into(), json!(state_class));
                }
                if let Some(d) = decimals.filter(|_| is_real(ty)) {
                    c.insert("suggested_display_precision".into(), json!(d));
                }
            }
            _ => {}
        },
    }
    c.insert(
        "availability".into(),
        json!([{"topic": device.topics.status()}, {"topic": device.topics.plc()}]),
    );
    c.insert("availability_mode".into(), json!("all"));
    let mut block = json!({
        "identifiers": [object_id(&format!("{}_{}", device.prefix, device.section))],
        "name": device.section,
        "manufacturer": device.maker.manufacturer,
        "model": device.maker.model,
    });
    if let Some(hw) = &device.maker.hw_version {
        block["hw_version"] = json!(hw);
    }
    c.insert("device".into(), block);
    c.insert(
        "origin".into(),
        json!({"name": "plccoms", "sw_version": env!("CARGO_PKG_VERSION")}),
    );
    let topic = config_topic(device, var, writable);
    (topic, Value::Object(c).to_string().into_bytes())
}

/// min, max and mode of a number entity for `ty`, with the tag file's
/// `min` and `max` where given (a range Home Assistant refuses, min not
/// below max, is left out).
fn range(ty: IecType, min: Option<f64>, max: Option<f64>) -> (f64, f64, &'static str) {
    let (lo, hi) = match ty {
        IecType::Byte | IecType::Usint => (0.0, u8::MAX.into()),
        IecType::Word | IecType::Uint => (0.0, u16::MAX.into()),
        IecType::Dword | IecType::Udint => (0.0, u32::MAX.into()),
        IecType::Lword | IecType::Ulint => (0.0, u64::MAX as f64),
        IecType::Sint => (i8::MIN.into(), i8::MAX.into()),
        IecType::Int => (i16::MIN.into(), i16::MAX.into()),
        IecType::Dint => (i32::MIN.into(), i32::MAX.into()),
        IecType::Lint => (i64::MIN as f64, i64::MAX as f64),
        _ => (-REAL_LIMIT, REAL_LIMIT),
    };
    let given = |x: Option<f64>| x.filter(|x| x.is_finite());
    let (min, max) = (given(min), given(max));
    let (lo2, hi2) = (min.unwrap_or(lo), max.unwrap_or(hi));
    if lo2 < hi2 {
        let mode = if min.is_some() && max.is_some() {
            "auto"
        } else {
            "box"
        };
        (lo2, hi2, mode)
    } else {
        (lo, hi, "box")
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

    /// The first section of an ini text.
    fn section(ini: &str) -> config::Section {
        let loaded = config::parse(Path::new("t.ini"), &format!("[*]\n{ini}")).unwrap();
        loaded.config.sections[0].clone()
    }

    fn maker() -> Maker {
        Maker::of(&section("[A]\nSERVER_PORT = 5010\n"), None)
    }

    #[test]
    fn the_device_is_named_by_its_backend() {
        let epsnet = section("[A]\nIPADDR = 10.0.0.5\nSERVER_PORT = 5010\n");
        let m = Maker::of(&epsnet, Some("TC700 CP-7004"));
        assert_eq!(
            (
                m.manufacturer.as_str(),
                m.model.as_str(),
                m.hw_version.as_deref()
            ),
            ("Teco", "Tecomat PLC", Some("TC700 CP-7004"))
        );
        let modbus = section(
            "[M]\nPROTOCOL = MODBUS_TCP\nIPADDR = 10.0.0.7\nMODBUS_PORT = 1502\nMODBUS_UNIT = 3\nMODBUS_TAGS = t.csv\nSERVER_PORT = 5011\n",
        );
        let m = Maker::of(&modbus, Some("ignored"));
        assert_eq!(
            (m.manufacturer.as_str(), m.model.as_str(), m.hw_version),
            ("Modbus TCP device", "10.0.0.7:1502 unit 3", None)
        );
    }

    #[test]
    fn components_and_the_fields_home_assistant_needs() {
        let table = table_of(&[
            ("SW", "BOOL"),
            ("T", "REAL"),
            ("S", "STRING[40]"),
            ("N", "INT"),
            ("STAMP", "DT"),
            ("DAY", "DATE"),
            ("DUR", "TIME"),
            ("__PLC_RUN", "BOOL"),
            ("__PF_CRC", "UDINT"),
        ]);
        let topics = Topics::new("plccoms", "Hala 1");
        let maker = maker();
        let device = Device {
            prefix: "plccoms",
            section: "Hala 1",
            topics: &topics,
            format: MqttFormat::Plain,
            qos: 1,
            maker: &maker,
        };
        let var = |name: &[u8]| table.var(table.lookup(name).unwrap());
        let (topic, payload) = config(&device, var(b"SW"), true);
        let id = object_id("plccoms_Hala 1_SW");
        assert_eq!(topic, format!("homeassistant/switch/{id}/config"));
        let c = parse(&payload);
        assert_eq!(c["command_topic"], "plccoms/Hala 1/SW/set");
        assert_eq!(c["state_topic"], "plccoms/Hala 1/SW");
        assert_eq!(
            (c["payload_on"].as_str(), c["state_off"].as_str()),
            (Some("true"), Some("false"))
        );
        assert_eq!(c["availability"][0]["topic"], "plccoms/Hala 1/status");
        assert_eq!(c["availability"][1]["topic"], "plccoms/Hala 1/plc");
        assert_eq!(c["device"]["name"], "Hala 1");
        assert_eq!(c["device"]["manufacturer"], "Teco");
        assert!(c["unique_id"]
            .as_str()
            .unwrap()
            .starts_with("plccoms_Hala_1_SW_"));
        let (topic, _) = config(&device, var(b"SW"), false);
        assert!(topic.starts_with("homeassistant/binary_sensor/"));
        assert_eq!(config_topic(&device, var(b"SW"), false), topic);
        let c = parse(&config(&device, var(b"N"), true).1);
        assert_eq!(
            (c["min"].as_f64(), c["max"].as_f64(), c["step"].as_f64()),
            (Some(-32768.0), Some(32767.0), Some(1.0))
        );
        let c = parse(&config(&device, var(b"T"), true).1);
        assert_eq!(
            (c["min"].as_f64(), c["max"].as_f64(), c["mode"].as_str()),
            (Some(-REAL_LIMIT), Some(REAL_LIMIT), Some("box"))
        );
        let c = parse(&config(&device, var(b"T"), false).1);
        assert_eq!(c["state_class"], "measurement");
        let c = parse(&config(&device, var(b"S"), true).1);
        assert_eq!(
            (c["max"].as_u64(), c.get("value_template")),
            (Some(40), None)
        );
        // Times: sensors, never writable, a device class where one fits.
        for (name, class) in [
            (&b"STAMP"[..], Some("timestamp")),
            (b"DAY", Some("date")),
            (b"DUR", None),
        ] {
            assert!(!writable(var(name), false, true));
            let (topic, payload) = config(&device, var(name), false);
            assert!(topic.starts_with("homeassistant/sensor/"));
            let c = parse(&payload);
            assert_eq!(c["device_class"].as_str(), class);
            assert!(c.get("state_class").is_none());
        }
        // System variables: diagnostic, never writable, no state class.
        assert!(!writable(var(b"__PF_CRC"), false, true));
        let c = parse(&config(&device, var(b"__PF_CRC"), false).1);
        assert_eq!(c["entity_category"], "diagnostic");
        assert!(c.get("state_class").is_none());
        let (topic, payload) = config(&device, var(b"__PLC_RUN"), false);
        assert!(topic.starts_with("homeassistant/binary_sensor/"));
        assert_eq!(parse(&payload)["device_class"], "running");
        // READ_ONLY and MQTT_WRITE.
        assert!(writable(var(b"N"), false, true));
        assert!(!writable(var(b"N"), true, true));
        assert!(!writable(var(b"N"), false, false));
    }

    #[test]
    fn json_booleans_render_as_the_payloads_compared() {
        let table = table_of(&[("SW", "BOOL")]);
        let topics = Topics::new("plccoms", "H");
        let maker = maker();
        let device = Device {
            prefix: "plccoms",
            section: "H",
            topics: &topics,
            format: MqttFormat::Json,
            qos: 1,
            maker: &maker,
        };
        let c = parse(&config(&device, table.var(0), true).1);
        assert_eq!(
            c["value_template"],
            "{{ 'true' if value_json.value else 'false' }}"
        );
    }

    #[test]
    fn units_imply_device_classes_and_ranges_come_from_the_tag_file() {
        assert_eq!(unit_class("°C"), Some("temperature"));
        assert_eq!(unit_class("kWh"), Some("energy"));
        assert_eq!(unit_class("hPa"), Some("pressure"));
        assert_eq!(unit_class("%"), None);
        assert_eq!(
            range(IecType::Real, Some(5.0), Some(30.0)),
            (5.0, 30.0, "auto")
        );
        assert_eq!(range(IecType::Int, Some(0.0), None), (0.0, 32767.0, "box"));
        // A range Home Assistant would refuse is left out.
        assert_eq!(
            range(IecType::Real, Some(30.0), Some(5.0)),
            (-REAL_LIMIT, REAL_LIMIT, "box")
        );
        assert_eq!(range(IecType::Real, Some(f64::NAN), None).0, -REAL_LIMIT);
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
