//! Sparkplug B (Eclipse, spec 3.0): the gateway as an edge node, each
//! section with `SPARKPLUG = Yes` (or `MQTT_FORMAT = sparkplug`) a device
//! of it. It shares the broker settings, the masks (MQTT_PUBLISH,
//! MQTT_WRITE) and the write path with the other MQTT formats, but has one
//! connection for the node (one will, the NDEATH), not one per section.
//!
//! - `proto.rs`: the payload (Eclipse Tahu's schema, EPL-2.0, by hand in
//!   prost);
//! - `topic.rs`: the namespace;
//! - `metric.rs`: datatypes, values, properties, command values;
//! - `command.rs`: NCMD/DCMD decoding (fuzzed);
//! - `node.rs`: the node's task.

pub mod command;
pub mod metric;
mod node;
pub mod proto;
pub mod topic;

use std::path::Path;
use std::sync::Arc;

use plccoms_core::config::MqttGlobal;
use plccoms_core::section::Section;
use plccoms_protocol::cp1250;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::settings::{id_safe, SectionRules, Settings};
use crate::spool::Spool;
use crate::{writes, Metrics};
pub use node::NodeSettings;
use node::{Device, Node};

/// The node's ids from the `[*]` keys, checked.
pub fn node_settings(mqtt: &MqttGlobal, spool: &Path) -> Result<NodeSettings, String> {
    let node = match &mqtt.sparkplug_node {
        Some(node) => node.clone(),
        None => topic::device_id(
            &nix::unistd::gethostname()
                .ok()
                .and_then(|h| h.into_string().ok())
                .unwrap_or_else(|| "plccoms".into()),
        ),
    };
    topic::check_id(&mqtt.sparkplug_group)
        .map_err(|p| format!("SPARKPLUG_GROUP = {} {p}", mqtt.sparkplug_group))?;
    topic::check_id(&node).map_err(|p| format!("SPARKPLUG_NODE = {node} {p}"))?;
    if let Some(host) = &mqtt.sparkplug_host {
        topic::check_id(host).map_err(|p| format!("SPARKPLUG_HOST = {host} {p}"))?;
    }
    Ok(NodeSettings {
        bdseq_file: spool
            .join(format!("sparkplug-{}", id_safe(&node)))
            .join("bdseq"),
        group: mqtt.sparkplug_group.clone(),
        node,
        host: mqtt.sparkplug_host.clone(),
    })
}

/// Starts the edge node with `sections` as its devices; their counters
/// are `metrics[i]`. Fails when the held changes' folder cannot be used.
pub(crate) fn start(
    settings: Arc<Settings>,
    sections: Vec<(Arc<Section>, SectionRules, Arc<Metrics>)>,
    stop: CancellationToken,
) -> Result<(JoinHandle<()>, Vec<JoinHandle<()>>), String> {
    let node = settings.sparkplug.clone();
    let dir = node.bdseq_file.with_file_name("held");
    let (held, recovered) = Spool::open(&dir, settings.buffer).map_err(|e| {
        format!(
            "Sparkplug: MQTT_SPOOL {}: {e}; make the folder writable by the server's user",
            dir.display()
        )
    })?;
    for cut in &recovered.cut {
        warn!("Sparkplug: held changes: {cut}");
    }
    if recovered.messages > 0 {
        info!(
            "Sparkplug: {} held changes from before are sent to the host after its birth",
            recovered.messages
        );
    }
    let (batch_tx, batches) = mpsc::channel(64);
    let (outcome_tx, outcomes) = mpsc::channel(writes::QUEUE);
    let mut helpers = Vec::new();
    let mut devices = Vec::new();
    let names: Vec<&str> = sections.iter().map(|(s, _, _)| s.name()).collect();
    check_device_ids(&names)?;
    for (index, (section, rules, metrics)) in sections.into_iter().enumerate() {
        // Every change, in order, as the JSON format's QoS 1 promises.
        // HISTORY_STAMP's pairs too: a metric's time is the PLC's where
        // one is paired.
        let mut masks = rules.publish.clone();
        for pair in &section.state().config.history.stamps {
            masks.push(cp1250::encode(&pair.value).into_owned());
            masks.push(cp1250::encode(&pair.stamp).into_owned());
        }
        let mut changes = section.subscribe_names(&masks).every_change();
        let table = changes.table().clone();
        let wanted = changes.wanted().to_vec();
        let tx = batch_tx.clone();
        helpers.push(tokio::spawn(async move {
            while let Some(batch) = changes.next().await {
                let wanted = batch.table_changed.then(|| changes.wanted().to_vec());
                if tx.send((index, batch, wanted)).await.is_err() {
                    break;
                }
            }
        }));
        let (write_tx, write_rx) = mpsc::channel(writes::QUEUE);
        let (done_tx, mut done_rx) = mpsc::channel(writes::QUEUE);
        helpers.push(tokio::spawn(writes::worker(
            section.clone(),
            write_rx,
            done_tx,
        )));
        let tx = outcome_tx.clone();
        helpers.push(tokio::spawn(async move {
            while let Some(outcome) = done_rx.recv().await {
                if tx.send((index, outcome)).await.is_err() {
                    break;
                }
            }
        }));
        let id = topic::device_id(section.name());
        info!(section = %section.name(), "Sparkplug: device {}/{}/{id}, metrics [{}]", node.group, node.node, section.state().config.mqtt.publish.join(", "));
        devices.push(Device::new(
            section, rules, id, metrics, write_tx, table, wanted,
        ));
    }
    let client_id = format!("{}-sparkplug", settings.client_id);
    let task = Node::new(
        settings, node, client_id, devices, stop, batches, outcomes, held,
    );
    Ok((tokio::spawn(task.run()), helpers))
}

/// Refuses two sections that would be one device (their names differ
/// only where a device id has `_`).
fn check_device_ids(sections: &[&str]) -> Result<(), String> {
    let mut seen: Vec<(&str, String)> = Vec::new();
    for &name in sections {
        let id = topic::device_id(name);
        if let Some((other, _)) = seen.iter().find(|(_, known)| *known == id) {
            return Err(format!(
                "[{name}] and [{other}] are both the Sparkplug device {id} (/, + and # become _): rename one"
            ));
        }
        seen.push((name, id));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn two_sections_are_never_one_device() {
        assert!(super::check_device_ids(&["Hala 1", "Hala 2"]).is_ok());
        assert_eq!(
            super::check_device_ids(&["a/b", "x", "a_b"]),
            Err("[a_b] and [a/b] are both the Sparkplug device a_b (/, + and # become _): rename one".into())
        );
    }
}
