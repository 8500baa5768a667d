//! The Sparkplug B topic namespace (spec 3.0, 4.1):
//! `spBv1.0/<group_id>/<message_type>/<edge_node_id>[/<device_id>]` and the
//! host's `spBv1.0/STATE/<host_id>`.

/// The namespace element of Sparkplug B ([tck-id-topic-structure-namespace-a]).
pub const NAMESPACE: &str = "spBv1.0";

/// Why an id cannot be a Sparkplug id.
pub fn check_id(id: &str) -> Result<(), &'static str> {
    // [tck-id-topic-structure-namespace-valid-group-id] and the like for
    // the node and device ids: UTF-8 without '/', '+', '#'.
    if id.is_empty() {
        return Err("is empty");
    }
    if id.contains(['/', '+', '#', '\0']) {
        return Err("holds '/', '+', '#' or a NUL, which Sparkplug ids may not");
    }
    Ok(())
}

/// A section's name as a device id: the characters an id may not hold
/// made `_`.
pub fn device_id(section: &str) -> String {
    let id: String = section
        .chars()
        .map(|c| {
            if matches!(c, '/' | '+' | '#' | '\0') {
                '_'
            } else {
                c
            }
        })
        .collect();
    if id.is_empty() {
        "_".into()
    } else {
        id
    }
}

/// The node's topics.
#[derive(Debug, Clone)]
pub struct Topics {
    group: String,
    node: String,
}

/// What a subscribed topic is.
#[derive(Debug, PartialEq, Eq)]
pub enum Incoming<'t> {
    NodeCommand,
    DeviceCommand(&'t str),
    State,
}

impl Topics {
    pub fn new(group: &str, node: &str) -> Topics {
        Topics {
            group: group.to_string(),
            node: node.to_string(),
        }
    }

    pub fn node(&self, kind: &str) -> String {
        format!("{NAMESPACE}/{}/{kind}/{}", self.group, self.node)
    }

    pub fn device(&self, kind: &str, device: &str) -> String {
        format!("{NAMESPACE}/{}/{kind}/{}/{device}", self.group, self.node)
    }

    /// Every device's commands.
    pub fn device_commands(&self) -> String {
        self.device("DCMD", "+")
    }

    pub fn state(host: &str) -> String {
        format!("{NAMESPACE}/STATE/{host}")
    }

    /// What `topic` is, if it is one this node subscribes to.
    pub fn parse<'t>(&self, topic: &'t str, host: Option<&str>) -> Option<Incoming<'t>> {
        if host.is_some_and(|h| topic == Topics::state(h)) {
            return Some(Incoming::State);
        }
        let rest = topic.strip_prefix(NAMESPACE)?.strip_prefix('/')?;
        let rest = rest.strip_prefix(self.group.as_str())?.strip_prefix('/')?;
        let (kind, rest) = rest.split_once('/')?;
        let (node, device) = match rest.split_once('/') {
            Some((node, device)) => (node, Some(device)),
            None => (rest, None),
        };
        if node != self.node {
            return None;
        }
        match (kind, device) {
            ("NCMD", None) => Some(Incoming::NodeCommand),
            ("DCMD", Some(device)) if !device.contains('/') => {
                Some(Incoming::DeviceCommand(device))
            }
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn namespace_of_spec_3_0() {
        // [tck-id-topic-structure] spBv1.0/group_id/message_type/edge_node_id/[device_id]
        let t = Topics::new("Plant 1", "gw");
        assert_eq!(t.node("NBIRTH"), "spBv1.0/Plant 1/NBIRTH/gw");
        assert_eq!(t.device("DDATA", "Hala"), "spBv1.0/Plant 1/DDATA/gw/Hala");
        assert_eq!(Topics::state("scada"), "spBv1.0/STATE/scada");
        assert_eq!(
            t.parse("spBv1.0/Plant 1/NCMD/gw", None),
            Some(Incoming::NodeCommand)
        );
        assert_eq!(
            t.parse("spBv1.0/Plant 1/DCMD/gw/Hala", None),
            Some(Incoming::DeviceCommand("Hala"))
        );
        assert_eq!(
            t.parse("spBv1.0/STATE/scada", Some("scada")),
            Some(Incoming::State)
        );
        assert_eq!(t.parse("spBv1.0/STATE/scada", None), None);
        assert_eq!(t.parse("spBv1.0/Plant 1/NCMD/other", None), None);
        assert_eq!(t.parse("spBv1.0/Plant 1/DCMD/gw/a/b", None), None);
        assert_eq!(t.parse("spBv1.0/Plant 2/NCMD/gw", None), None);
        assert_eq!(device_id("a/b+c#"), "a_b_c_");
        assert!(check_id("ok id").is_ok());
        assert!(check_id("a/b").is_err());
        assert!(check_id("").is_err());
    }
}
