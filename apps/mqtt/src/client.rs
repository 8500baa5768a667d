//! The broker side every connection shares: which broker of MQTT_URL is
//! next ([`Brokers`], round robin), and one connection attempt ([`Link`])
//! in MQTT 5 or, MQTT_VERSION = 3.1.1, in 3.1.1 for brokers without 5
//! (NATS, RabbitMQ before 3.13). A 3.1.1 link hands its events over in
//! rumqttc's MQTT 5 types, so the tasks handle one kind of event.
//!
//! Failover speed: a broker process that dies resets its connections at
//! once (an error at the next read); a frozen one or a lost network is
//! found by the keep-alive, [`KEEP_ALIVE`] (a PINGREQ after that long
//! without traffic, the connection given up when its answer is not in by
//! the next one: at most twice that). A connection attempt to a node that
//! does not answer gives up after [`CONNECT_TIMEOUT`] and moves on.

use std::time::Duration;

use rumqttc::v5::mqttbytes::v5::{
    ConnAck, ConnectReturnCode, Filter, LastWill, Packet, PubAck, PubAckReason, Publish, SubAck,
    SubscribeReasonCode,
};
use rumqttc::v5::mqttbytes::QoS;
use rumqttc::v5::{ConnectionError, Event};
use rumqttc::{TlsConfiguration, Transport};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use super::settings::Settings;
use plccoms_core::config::BrokerUrl;

/// Idle time before a PINGREQ; a broker that does not answer one by the
/// next is given up (a frozen node: found within twice this).
pub(super) const KEEP_ALIVE: Duration = Duration::from_secs(5);
/// TCP connect and CONNACK, at most (then the next broker is tried).
pub(super) const CONNECT_TIMEOUT: u64 = 3;
/// The wait before trying the next broker of MQTT_URL after one was lost
/// or refused: short, a cluster's other nodes are meant to be up. Only a
/// whole round that failed backs off.
pub(super) const NEXT_BROKER: Duration = Duration::from_millis(50);

/// The brokers of MQTT_URL and the one in use (round robin).
#[derive(Debug, Clone)]
pub(super) struct Brokers {
    list: Vec<BrokerUrl>,
    current: usize,
    /// Brokers tried without a connection since the last one made.
    failed: usize,
}

impl Brokers {
    pub fn new(list: Vec<BrokerUrl>) -> Brokers {
        assert!(!list.is_empty(), "MQTT_URL lists a broker");
        Brokers {
            list,
            current: 0,
            failed: 0,
        }
    }

    pub fn current(&self) -> &BrokerUrl {
        &self.list[self.current]
    }

    /// The place of [`Brokers::current`] in MQTT_URL, from 0.
    pub fn index(&self) -> usize {
        self.current
    }

    pub fn len(&self) -> usize {
        self.list.len()
    }

    /// A connection was made to the current broker.
    pub fn connected(&mut self) {
        self.failed = 0;
    }

    /// The current broker was lost or could not be reached: the next one
    /// is current. `true` when every broker failed in turn since the last
    /// connection (a round: time to back off), `false` while others are
    /// left to try at once.
    pub fn advance(&mut self) -> bool {
        self.current = (self.current + 1) % self.list.len();
        self.failed += 1;
        if self.failed >= self.list.len() {
            self.failed = 0;
            return true;
        }
        false
    }
}

impl std::fmt::Display for Brokers {
    /// `host:port`, and its place when MQTT_URL lists several.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let b = self.current();
        write!(f, "{}:{}", b.host, b.port)?;
        if self.list.len() > 1 {
            write!(f, " (broker {} of {})", self.current + 1, self.list.len())?;
        }
        Ok(())
    }
}

/// What a connection is made with.
pub(super) struct Connect<'a> {
    pub settings: &'a Settings,
    pub broker: &'a BrokerUrl,
    pub client_id: &'a str,
    /// Publishes rumqttc may have unacknowledged, if not its default.
    pub inflight: Option<u16>,
    pub will_topic: String,
    pub will_payload: Vec<u8>,
    pub will_retain: bool,
    /// The largest message taken from the broker.
    pub max_incoming: usize,
}

/// The client of a connection attempt, of either version.
pub(super) enum Client {
    V5(rumqttc::v5::AsyncClient),
    V4(rumqttc::AsyncClient),
}

/// rumqttc's error for a request it cannot take.
pub(super) type ClientError = String;

impl Client {
    pub fn try_publish(
        &self,
        topic: String,
        qos: QoS,
        retain: bool,
        payload: Vec<u8>,
    ) -> Result<(), ClientError> {
        match self {
            Client::V5(c) => c
                .try_publish(topic, qos, retain, payload)
                .map_err(|e| e.to_string()),
            Client::V4(c) => c
                .try_publish(topic, v4_qos(qos), retain, payload)
                .map_err(|e| e.to_string()),
        }
    }

    pub fn try_subscribe(&self, topic: String, qos: QoS) -> Result<(), ClientError> {
        self.try_subscribe_filter(Filter::new(topic, qos))
    }

    /// MQTT 5's filter options where the version has them (3.1.1: only the
    /// topic and QoS).
    pub fn try_subscribe_filter(&self, filter: Filter) -> Result<(), ClientError> {
        match self {
            Client::V5(c) => c.try_subscribe_many([filter]).map_err(|e| e.to_string()),
            Client::V4(c) => c
                .try_subscribe(filter.path, v4_qos(filter.qos))
                .map_err(|e| e.to_string()),
        }
    }

    pub fn try_disconnect(&self) -> Result<(), ClientError> {
        match self {
            Client::V5(c) => c.try_disconnect().map_err(|e| e.to_string()),
            Client::V4(c) => c.try_disconnect().map_err(|e| e.to_string()),
        }
    }
}

/// A connection attempt: the client, and the event loop's events.
pub(super) struct Link {
    pub client: Client,
    events: mpsc::Receiver<Result<Event, ConnectionError>>,
    task: JoinHandle<()>,
}

impl Link {
    /// A fresh client whose event loop runs in a task of its own,
    /// forwarding its events until one fails.
    pub fn spawn(connect: Connect<'_>, requests: usize, events: usize) -> Link {
        let (tx, rx) = mpsc::channel(events);
        let (client, task) = if connect.settings.v311 {
            let (client, mut eventloop) = rumqttc::AsyncClient::new(v4_options(&connect), requests);
            eventloop
                .network_options
                .set_connection_timeout(CONNECT_TIMEOUT);
            let task = tokio::spawn(async move {
                loop {
                    let event = match eventloop.poll().await {
                        Ok(event) => match v5_event(event) {
                            Some(event) => Ok(event),
                            None => continue,
                        },
                        Err(e) => Err(v5_error(e)),
                    };
                    let failed = event.is_err();
                    if tx.send(event).await.is_err() || failed {
                        break;
                    }
                }
            });
            (Client::V4(client), task)
        } else {
            let (client, mut eventloop) =
                rumqttc::v5::AsyncClient::new(v5_options(&connect), requests);
            let task = tokio::spawn(async move {
                loop {
                    let event = eventloop.poll().await;
                    let failed = event.is_err();
                    if tx.send(event).await.is_err() || failed {
                        break;
                    }
                }
            });
            (Client::V5(client), task)
        };
        Link {
            client,
            events: rx,
            task,
        }
    }

    pub async fn next_event(&mut self) -> Result<Event, ConnectionError> {
        self.events
            .recv()
            .await
            .unwrap_or(Err(ConnectionError::RequestsDone))
    }
}

impl Drop for Link {
    fn drop(&mut self) {
        self.task.abort();
    }
}

fn v5_options(c: &Connect<'_>) -> rumqttc::v5::MqttOptions {
    let mut options = rumqttc::v5::MqttOptions::new(c.client_id, &c.broker.host, c.broker.port);
    options
        .set_keep_alive(KEEP_ALIVE)
        .set_connection_timeout(CONNECT_TIMEOUT)
        .set_clean_start(true)
        // The broker sends nothing larger (MQTT 5's maximum packet size):
        // a huge retained message cannot break the connection.
        .set_max_packet_size(Some(c.max_incoming as u32))
        .set_last_will(LastWill::new(
            c.will_topic.clone(),
            c.will_payload.clone(),
            QoS::AtLeastOnce,
            c.will_retain,
            None,
        ));
    if let Some(inflight) = c.inflight {
        options.set_outgoing_inflight_upper_limit(inflight);
    }
    if let Some((user, password)) = &c.settings.credentials {
        options.set_credentials(user, password);
    }
    if let Some(transport) = transport(c) {
        options.set_transport(transport);
    }
    options
}

fn v4_options(c: &Connect<'_>) -> rumqttc::MqttOptions {
    let mut options = rumqttc::MqttOptions::new(c.client_id, &c.broker.host, c.broker.port);
    options
        .set_keep_alive(KEEP_ALIVE)
        .set_clean_session(true)
        // 3.1.1 cannot tell the broker: what comes larger ends the
        // connection instead (logged as such by `describe`).
        .set_max_packet_size(c.max_incoming, c.max_incoming)
        .set_last_will(rumqttc::LastWill::new(
            c.will_topic.clone(),
            c.will_payload.clone(),
            rumqttc::QoS::AtLeastOnce,
            c.will_retain,
        ));
    if let Some(inflight) = c.inflight {
        options.set_inflight(inflight);
    }
    if let Some((user, password)) = &c.settings.credentials {
        options.set_credentials(user, password);
    }
    if let Some(transport) = transport(c) {
        options.set_transport(transport);
    }
    options
}

/// TLS for an `mqtts://` broker.
fn transport(c: &Connect<'_>) -> Option<Transport> {
    let tls = c.settings.tls.as_ref().filter(|_| c.broker.tls)?;
    Some(Transport::tls_with_config(TlsConfiguration::Rustls(
        tls.clone(),
    )))
}

fn v4_qos(qos: QoS) -> rumqttc::QoS {
    match qos {
        QoS::AtMostOnce => rumqttc::QoS::AtMostOnce,
        QoS::AtLeastOnce => rumqttc::QoS::AtLeastOnce,
        QoS::ExactlyOnce => rumqttc::QoS::ExactlyOnce,
    }
}

fn v5_qos(qos: rumqttc::QoS) -> QoS {
    match qos {
        rumqttc::QoS::AtMostOnce => QoS::AtMostOnce,
        rumqttc::QoS::AtLeastOnce => QoS::AtLeastOnce,
        rumqttc::QoS::ExactlyOnce => QoS::ExactlyOnce,
    }
}

/// A 3.1.1 event as the tasks handle it (`None`: one they ignore).
fn v5_event(event: rumqttc::Event) -> Option<Event> {
    use rumqttc::Packet as P;
    let packet = match event {
        rumqttc::Event::Outgoing(outgoing) => return Some(Event::Outgoing(outgoing)),
        rumqttc::Event::Incoming(packet) => packet,
    };
    Some(Event::Incoming(match packet {
        P::ConnAck(ack) => Packet::ConnAck(ConnAck {
            session_present: ack.session_present,
            code: ConnectReturnCode::Success,
            properties: None,
        }),
        P::PubAck(ack) => Packet::PubAck(PubAck {
            pkid: ack.pkid,
            reason: PubAckReason::Success,
            properties: None,
        }),
        P::Publish(p) => {
            let mut publish = Publish::new(p.topic, v5_qos(p.qos), p.payload, None);
            publish.retain = p.retain;
            publish.dup = p.dup;
            publish.pkid = p.pkid;
            Packet::Publish(publish)
        }
        P::SubAck(ack) => Packet::SubAck(SubAck {
            pkid: ack.pkid,
            return_codes: ack
                .return_codes
                .into_iter()
                .map(|code| match code {
                    rumqttc::SubscribeReasonCode::Success(qos) => {
                        SubscribeReasonCode::Success(v5_qos(qos))
                    }
                    rumqttc::SubscribeReasonCode::Failure => SubscribeReasonCode::Unspecified,
                })
                .collect(),
            properties: None,
        }),
        _ => return None,
    }))
}

/// A 3.1.1 connection error in MQTT 5's terms, for `describe`.
fn v5_error(e: rumqttc::ConnectionError) -> ConnectionError {
    use rumqttc::ConnectReturnCode as C;
    match e {
        rumqttc::ConnectionError::ConnectionRefused(code) => {
            ConnectionError::ConnectionRefused(match code {
                C::BadUserNamePassword => ConnectReturnCode::BadUserNamePassword,
                C::NotAuthorized => ConnectReturnCode::NotAuthorized,
                C::BadClientId => ConnectReturnCode::ClientIdentifierNotValid,
                C::RefusedProtocolVersion => ConnectReturnCode::UnsupportedProtocolVersion,
                C::ServiceUnavailable | C::Success => ConnectReturnCode::ServerUnavailable,
            })
        }
        rumqttc::ConnectionError::Tls(e) => ConnectionError::Tls(e),
        rumqttc::ConnectionError::Io(e) => ConnectionError::Io(e),
        other => ConnectionError::Io(std::io::Error::other(other.to_string())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_robin_backs_off_after_a_whole_round() {
        let url = |port| BrokerUrl {
            host: "h".into(),
            port,
            tls: false,
        };
        let mut brokers = Brokers::new(vec![url(1), url(2), url(3)]);
        assert_eq!(brokers.current().port, 1);
        assert_eq!(brokers.to_string(), "h:1 (broker 1 of 3)");
        // Lost 1, 2 refused: 3 next, at once.
        assert!(!brokers.advance());
        assert!(!brokers.advance());
        assert_eq!(brokers.index(), 2);
        // 3 refused too: a whole round, back off; 1 next.
        assert!(brokers.advance());
        assert_eq!(brokers.current().port, 1);
        // A connection starts the count again.
        brokers.connected();
        assert!(!brokers.advance());
        let mut one = Brokers::new(vec![url(1)]);
        assert_eq!(one.to_string(), "h:1");
        assert!(one.advance());
        assert_eq!(one.index(), 0);
    }
}
