//! bench-opcua-plc: an OPC UA server of N variables for `bench-opcua
//! --against ua`, standing in for a PLC's own server: async-opcua's
//! in-memory node manager, the folder `Bench` (`nsu=urn:bench-plc;s=Bench`)
//! holding `T0`..`T15` (Int16, writable, written in memory at once) and
//! `V16`.. (Int32, Float, Double, UInt16 in turn), every `V*` set to a
//! rising counter each `--delay` ms with that moment as SourceTimestamp.
//! No security, anonymous, Nagle off. Prints `ready` on stdout once it
//! listens.
//!
//! Run: `bench-opcua-plc --port 4840 --vars 100000 --delay 1000`.

use std::time::Duration;

use clap::Parser;
use opcua::crypto::SecurityPolicy;
use opcua::nodes::{NodeType, VariableBuilder};
use opcua::server::diagnostics::NamespaceMetadata;
use opcua::server::node_manager::memory::{simple_node_manager, SimpleNodeManager};
use opcua::server::{ServerBuilder, ServerEndpoint};
use opcua::types::{
    AttributeId, DataTypeId, DataValue, DateTime, MessageSecurityMode, NodeId, Variant,
};

#[derive(Debug, Parser)]
#[command(name = "bench-opcua-plc")]
struct Args {
    /// The port to listen on (127.0.0.1).
    #[arg(long)]
    port: u16,
    /// Variables in all, the 16 SET targets included.
    #[arg(long, default_value_t = 100_000)]
    vars: usize,
    /// How often every `V*` changes (ms).
    #[arg(long, default_value_t = 1000)]
    delay: u64,
}

const NAMESPACE: &str = "urn:bench-plc";
const SET_TAGS: usize = 16;
/// Values set under one hold of the address space's lock.
const SLICE: usize = 2_000;

/// The name and type of variable `i`.
fn variable(i: usize) -> (String, DataTypeId) {
    if i < SET_TAGS {
        return (format!("T{i}"), DataTypeId::Int16);
    }
    let ty = match i % 4 {
        0 => DataTypeId::Int32,
        1 => DataTypeId::Float,
        2 => DataTypeId::Double,
        _ => DataTypeId::UInt16,
    };
    (format!("V{i}"), ty)
}

/// The value of variable `i` at counter `n` (each cycle: no name made).
fn value(i: usize, n: u32) -> Variant {
    if i < SET_TAGS {
        return Variant::Int16(0);
    }
    match i % 4 {
        0 => Variant::Int32(n as i32),
        1 => Variant::Float(n as f32),
        2 => Variant::Double(n as f64),
        _ => Variant::UInt16(n as u16),
    }
}

#[tokio::main(flavor = "multi_thread")]
async fn main() {
    let args = Args::parse();
    let pki = tempfile::tempdir().expect("a PKI folder");
    let mut builder = ServerBuilder::new()
        .application_name("bench-opcua-plc")
        .application_uri("urn:bench-opcua-plc")
        .product_uri("urn:bench-opcua-plc")
        .host("127.0.0.1".to_string())
        .port(args.port)
        .discovery_urls(vec![format!("opc.tcp://127.0.0.1:{}/", args.port)])
        .pki_dir(pki.path())
        .create_sample_keypair(true)
        .trust_client_certs(true)
        .with_node_manager(simple_node_manager(
            NamespaceMetadata {
                namespace_uri: NAMESPACE.to_owned(),
                ..Default::default()
            },
            "bench",
        ))
        .add_endpoint(
            "none",
            ServerEndpoint::new(
                "/",
                SecurityPolicy::None,
                MessageSecurityMode::None,
                &[opcua::server::ANONYMOUS_USER_TOKEN_ID.to_string()],
            ),
        );
    {
        // Room for every variable in one subscription, in few calls.
        let limits = builder.limits_mut();
        let op = &mut limits.operational;
        op.max_nodes_per_read = 10_000;
        op.max_nodes_per_write = 10_000;
        op.max_nodes_per_browse = 10_000;
        op.max_monitored_items_per_call = 10_000;
        op.max_references_per_browse_node = 10_000;
        let subs = &mut limits.subscriptions;
        subs.max_monitored_items_per_sub = args.vars + 1000;
        subs.max_queued_notifications = (args.vars + 1000) * 4;
        subs.max_notifications_per_publish = 50_000;
        subs.min_sampling_interval_ms = 0.0;
        limits.max_message_size = 64 << 20;
        limits.max_chunk_count = 8192;
        limits.max_array_length = 1 << 20;
    }
    let (server, handle) = builder.build().expect("the server");
    let manager = handle
        .node_managers()
        .get_of_type::<SimpleNodeManager>()
        .expect("the simple node manager");
    let ns = handle
        .get_namespace_index(NAMESPACE)
        .expect("its namespace");
    let folder = NodeId::new(ns, "Bench");
    let ids: Vec<NodeId> = (0..args.vars)
        .map(|i| NodeId::new(ns, format!("Bench.{}", variable(i).0)))
        .collect();
    {
        let mut space = manager.address_space().write();
        space.add_folder(&folder, "Bench", "Bench", &NodeId::objects_folder_id());
        for (i, id) in ids.iter().enumerate() {
            let (name, ty) = variable(i);
            let mut var = VariableBuilder::new(id, name.as_str(), name.as_str())
                .data_type(ty)
                .value(value(i, 0))
                .organized_by(folder.clone());
            if i < SET_TAGS {
                var = var.writable();
            }
            var.insert(&mut *space);
        }
    }
    let subscriptions = handle.subscriptions().clone();
    let every = Duration::from_millis(args.delay);
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(every);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut n = 0u32;
        loop {
            tick.tick().await;
            n = n.wrapping_add(1);
            let now = DateTime::now();
            // In slices, stored under the address space's lock and then
            // notified without it, as a PLC's runtime hands its values to
            // its server: `set_values` notifies holding that lock, and the
            // notification waits for the subscriptions' lock, which the
            // server holds while it builds a session's publish; a Read or
            // a Write waited for both (100,000 at once: 300 ms).
            for (at, slice) in ids.chunks(SLICE).enumerate() {
                let samples: Vec<(&NodeId, DataValue)> = slice
                    .iter()
                    .enumerate()
                    .filter_map(|(k, id)| {
                        let i = at * SLICE + k;
                        (i >= SET_TAGS).then(|| {
                            let mut sample = DataValue::new_at(value(i, n), now);
                            sample.server_timestamp = Some(now);
                            (id, sample)
                        })
                    })
                    .collect();
                {
                    let mut space = manager.address_space().write();
                    for (id, sample) in &samples {
                        if let Some(NodeType::Variable(v)) = space.find_mut(*id) {
                            v.set_data_value(sample.clone());
                        }
                    }
                }
                subscriptions.notify_data_change(
                    samples
                        .into_iter()
                        .map(|(id, sample)| (sample, id, AttributeId::Value)),
                );
                tokio::task::yield_now().await;
            }
        }
    });
    // Bound here, not by `run`, for Nagle's algorithm: async-opcua leaves
    // it on, and a Write's or a Read's answer could then wait for the
    // client's delayed ACK (40 ms on Linux). The stacks PLCs' servers are
    // built on turn it off (open62541, the OPC Foundation's), as plccoms's
    // server does, with this listener. Bound, it accepts: ready.
    let addr = std::net::SocketAddr::from(([127, 0, 0, 1], args.port));
    let listener = plccoms_opcua::listen(addr).expect("the port");
    let listener = tokio::net::TcpListener::from_std(listener).expect("the listener");
    let serving = tokio::spawn(server.run_with(listener));
    println!("ready");
    if let Ok(Err(e)) = serving.await {
        eprintln!("bench-opcua-plc: {e}");
        std::process::exit(1);
    }
}
