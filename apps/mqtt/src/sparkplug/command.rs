//! NCMD and DCMD payloads from the broker: decoded with a bound on their
//! size, and each metric's target (alias or name) picked out. What a host
//! may send is anything any client of the broker may send: nothing here
//! panics or trusts a length.

use prost::Message as _;

use super::proto::{Metric, MetricValue, Payload};

/// The node's metric that asks for a rebirth.
pub const REBIRTH: &str = "Node Control/Rebirth";

/// The largest command payload decoded; a command writes a few values.
pub const MAX_COMMAND: usize = 1 << 20;
/// The most metrics one command may carry.
pub const MAX_METRICS: usize = 1024;

#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum CommandError {
    #[error("a command payload of {0} bytes, over the {MAX_COMMAND} taken")]
    TooLarge(usize),
    #[error("not a Sparkplug B payload: {0}")]
    Protobuf(String),
    #[error("{0} metrics in one command, over the {MAX_METRICS} taken")]
    TooMany(usize),
}

/// A command's payload, decoded.
pub fn decode(bytes: &[u8]) -> Result<Payload, CommandError> {
    if bytes.len() > MAX_COMMAND {
        return Err(CommandError::TooLarge(bytes.len()));
    }
    let payload = Payload::decode(bytes).map_err(|e| CommandError::Protobuf(e.to_string()))?;
    if payload.metrics.len() > MAX_METRICS {
        return Err(CommandError::TooMany(payload.metrics.len()));
    }
    Ok(payload)
}

/// What a command's metric names: hosts send the alias, the name or both
/// (the alias wins, as it was given at birth).
#[derive(Debug, PartialEq, Eq)]
pub enum Target<'a> {
    Alias(u64),
    Name(&'a str),
    None,
}

pub fn target(metric: &Metric) -> Target<'_> {
    match (metric.alias, metric.name.as_deref()) {
        (Some(alias), _) => Target::Alias(alias),
        (None, Some(name)) => Target::Name(name),
        (None, None) => Target::None,
    }
}

/// The metric's value, `None` when it says it has none.
pub fn value(metric: &Metric) -> Option<&MetricValue> {
    if metric.is_null == Some(true) {
        return None;
    }
    metric.value.as_ref()
}

/// Whether an NCMD asks for a rebirth: `Node Control/Rebirth` = true, by
/// name or by its alias.
pub fn asks_rebirth(payload: &Payload, rebirth_alias: u64) -> bool {
    payload.metrics.iter().any(|m| {
        let named = match target(m) {
            Target::Alias(alias) => alias == rebirth_alias,
            Target::Name(name) => name == REBIRTH,
            Target::None => false,
        };
        named
            && matches!(
                value(m),
                Some(MetricValue::BooleanValue(true)) | Some(MetricValue::IntValue(1))
            )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_payloads_are_errors_not_panics() {
        assert!(matches!(
            decode(&[0xff, 0xff, 0xff]),
            Err(CommandError::Protobuf(_))
        ));
        assert!(matches!(
            decode(&vec![0; MAX_COMMAND + 1]),
            Err(CommandError::TooLarge(_))
        ));
        let many = Payload {
            metrics: vec![Metric::default(); MAX_METRICS + 1],
            ..Payload::default()
        };
        assert_eq!(
            decode(&many.encode_to_vec()),
            Err(CommandError::TooMany(MAX_METRICS + 1))
        );
        assert_eq!(decode(&[]).unwrap(), Payload::default());
    }

    #[test]
    fn rebirth_by_name_or_alias() {
        // [tck-id-operational-behavior-data-commands-rebirth-action-2]
        let by = |name: Option<&str>, alias: Option<u64>, v: bool| Payload {
            metrics: vec![Metric {
                name: name.map(str::to_string),
                alias,
                value: Some(MetricValue::BooleanValue(v)),
                ..Metric::default()
            }],
            ..Payload::default()
        };
        assert!(asks_rebirth(
            &by(Some("Node Control/Rebirth"), None, true),
            2
        ));
        assert!(asks_rebirth(&by(None, Some(2), true), 2));
        assert!(!asks_rebirth(&by(None, Some(3), true), 2));
        assert!(!asks_rebirth(
            &by(Some("Node Control/Rebirth"), None, false),
            2
        ));
    }
}
