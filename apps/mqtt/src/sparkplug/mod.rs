//! Sparkplug B (Eclipse, spec 3.0): the gateway as an edge node.
//!
//! - `proto.rs`: the payload (Eclipse Tahu's schema, EPL-2.0, by hand in
//!   prost);
//! - `topic.rs`: the namespace;
//! - `metric.rs`: datatypes, values, properties, command values;
//! - `command.rs`: NCMD/DCMD decoding (fuzzed).

pub mod command;
pub mod metric;
pub mod proto;
pub mod topic;
