//! The MQTT keys' settings — in `[*]` the broker, the client and the spool;
//! in a PLC section what it publishes and what may be written — and the
//! checks the table's kinds cannot express (a broker URL, a topic prefix, a
//! deadband, keys that go together), reported with their lines like every
//! other bad value.

use std::collections::HashMap;

use plccoms_protocol::Delta;

use super::broker::BrokerUrl;
use super::diag::{Diagnostic, Diags, Severity};
use super::ini::Entry;

/// The MQTT keys of `[*]`. MQTT is off while `url` is `None`.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct MqttGlobal {
    /// MQTT_URL: `mqtt://host[:port]` or `mqtts://host[:port]`, one or
    /// more (a cluster's nodes, tried round robin); never empty.
    pub url: Option<Vec<BrokerUrl>>,
    /// MQTT_VERSION 3.1.1: MQTT 3.1.1 instead of 5 (brokers without 5).
    pub v311: bool,
    pub user: Option<String>,
    pub password: Option<String>,
    /// MQTT_PASSWORD_FILE: read at start-up, a trailing line end dropped.
    pub password_file: Option<String>,
    /// MQTT_CLIENT_ID: the base of each section's client id.
    pub client_id: Option<String>,
    /// MQTT_PREFIX: the first topic level(s).
    pub prefix: String,
    /// MQTT_CA, MQTT_CERT, MQTT_KEY: PEM files for `mqtts://`.
    pub ca: Option<String>,
    pub cert: Option<String>,
    pub key: Option<String>,
    /// MQTT_BUFFER: bytes of unsent messages kept on disk, per section.
    pub buffer: u64,
    /// MQTT_SPOOL: the folder of the on-disk queues.
    pub spool: String,
    /// SPARKPLUG_GROUP, SPARKPLUG_NODE (default: the host name),
    /// SPARKPLUG_HOST: the Sparkplug B edge node (apps/mqtt/src/sparkplug).
    pub sparkplug_group: String,
    pub sparkplug_node: Option<String>,
    pub sparkplug_host: Option<String>,
}

/// How a value is written on its topic.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MqttFormat {
    /// The value as the line protocol prints it.
    #[default]
    Plain,
    /// `{"value": .., "ts": "..", "quality": ".."}`.
    Json,
}

/// The MQTT keys of a PLC section.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MqttSection {
    /// MQTT_PUBLISH: masks of the variables published (none by default).
    pub publish: Vec<String>,
    /// MQTT_WRITE: masks of the variables that `/set` may write (none by
    /// default).
    pub write: Vec<String>,
    pub qos: u8,
    pub retain: bool,
    pub format: MqttFormat,
    /// MQTT_DELTA: the deadband, as written (checked by [`check_section`]).
    pub delta: Option<String>,
    pub ha_discovery: bool,
    /// SPARKPLUG (or MQTT_FORMAT = sparkplug): the section is a device of
    /// the Sparkplug B edge node instead of having topics of its own.
    pub sparkplug: bool,
}

impl Default for MqttSection {
    fn default() -> Self {
        MqttSection {
            publish: Vec::new(),
            write: Vec::new(),
            qos: 1,
            retain: true,
            format: MqttFormat::Plain,
            delta: None,
            ha_discovery: false,
            sparkplug: false,
        }
    }
}

/// The format names MQTT_FORMAT accepts.
pub const MQTT_FORMATS: [&str; 3] = ["plain", "json", "sparkplug"];

/// `A*, B , C*` -> `["A*", "B", "C*"]`: a comma-separated list of masks.
pub fn split_masks(text: &str) -> Vec<String> {
    text.split(',')
        .map(str::trim)
        .filter(|m| !m.is_empty())
        .map(str::to_string)
        .collect()
}

/// Whether `prefix` can start every topic: not empty, no wildcard, no empty
/// first or last level, not a `$` (broker) topic.
pub fn check_prefix(prefix: &str) -> Result<(), String> {
    if prefix.is_empty() {
        return Err("is empty".into());
    }
    if prefix.contains(['+', '#', '\0']) {
        return Err("holds a wildcard (+ or #) or a NUL".into());
    }
    if prefix.starts_with('/') || prefix.ends_with('/') {
        return Err("starts or ends with '/' (an empty topic level)".into());
    }
    if prefix.starts_with('$') {
        return Err("starts with '$' (topics the broker reserves)".into());
    }
    Ok(())
}

/// The checks of `[*]`'s MQTT keys beyond their kinds.
pub(super) fn check_global(
    mqtt: &MqttGlobal,
    map: &HashMap<&str, &Entry>,
    diags: &Diags<'_>,
    errors: &mut Vec<Diagnostic>,
) {
    let mut bad = |key: &str, problem: String| {
        if let Some(entry) = map.get(key) {
            if !errors.iter().any(|d| d.line == entry.line) {
                errors.push(diags.make(
                    Severity::Error,
                    entry.line,
                    format!("{} = {} {problem}", entry.key, entry.value),
                ));
            }
        }
    };
    // The key's setter keeps only a good URL; a bad one is reported here,
    // with the parser's words.
    if mqtt.url.is_none() {
        if let Some(Err(problem)) = map.get("MQTT_URL").map(|e| BrokerUrl::parse_list(&e.value)) {
            bad("MQTT_URL", problem);
        }
    }
    if let Err(problem) = check_prefix(&mqtt.prefix) {
        bad("MQTT_PREFIX", problem);
    }
    if mqtt.password.is_some() && mqtt.password_file.is_some() {
        bad(
            "MQTT_PASSWORD_FILE",
            "is given with MQTT_PASSWORD (give one of the two)".into(),
        );
    }
    if let Some(id) = &mqtt.client_id {
        if id.contains(['+', '#', '/', '\0']) {
            bad("MQTT_CLIENT_ID", "holds '+', '#', '/' or a NUL".into());
        }
    }
}

/// The checks of a section's MQTT keys beyond their kinds.
pub(super) fn check_section(
    mqtt: &MqttSection,
    map: &HashMap<&str, &Entry>,
    diags: &Diags<'_>,
    errors: &mut Vec<Diagnostic>,
) {
    if let (Some(delta), Some(entry)) = (&mqtt.delta, map.get("MQTT_DELTA")) {
        if let Err(problem) = Delta::parse(delta.as_bytes()) {
            errors.push(diags.make(
                Severity::Error,
                entry.line,
                format!("{} = {} {}", entry.key, entry.value, problem.message()),
            ));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn masks_and_prefixes() {
        assert_eq!(split_masks(" A*, B ,,c"), ["A*", "B", "c"]);
        assert!(split_masks(" , ").is_empty());
        assert!(check_prefix("plccoms").is_ok());
        assert!(check_prefix("site/1/plccoms").is_ok());
        for bad in ["", "a/+", "#", "/a", "a/", "$SYS"] {
            assert!(check_prefix(bad).is_err(), "{bad}");
        }
    }
}
