//! OPC UA over TCP with Nagle's algorithm off. async-opcua's own connector
//! leaves it on: a small request (a Write, a Publish) sent while an earlier
//! one is not yet acknowledged waits for the server's delayed ACK, 40 ms
//! on Linux, and the last chunk of a large request waits so too. A PLC
//! gateway's requests are small and latency-bound; this connector is
//! async-opcua's, with `TCP_NODELAY` set on the socket.

use std::sync::Arc;

use opcua::client::transport::{
    Connector, OutgoingMessage, SecureChannelState, StreamConnection, StreamConnector,
    TcpTransport, TransportConfiguration,
};
use opcua::client::ConnectionSource;
use opcua::core::comms::tcp_codec::TcpCodec;
use opcua::core::comms::url::hostname_port_from_url;
use opcua::types::{DecodingOptions, EndpointDescription, Error, StatusCode};
use tokio::io::{ReadHalf, WriteHalf};
use tokio::net::TcpStream;
use tokio_util::codec::FramedRead;

type Connection = StreamConnection<ReadHalf<TcpStream>, WriteHalf<TcpStream>>;

/// A session's connection source: a direct opc.tcp connection, Nagle off.
pub struct NoDelay;

impl ConnectionSource for NoDelay {
    type Builder = NoDelayConnector;

    fn get_connector(&self, endpoint: &EndpointDescription) -> Result<NoDelayConnector, Error> {
        Ok(NoDelayConnector {
            endpoint_url: endpoint.endpoint_url.as_ref().to_string(),
        })
    }
}

/// async-opcua's `TcpConnector`, but for the socket's option.
pub struct NoDelayConnector {
    endpoint_url: String,
}

impl Connector for NoDelayConnector {
    type Transport = TcpTransport;

    async fn connect(
        &self,
        channel: Arc<SecureChannelState>,
        outgoing_recv: tokio::sync::mpsc::Receiver<OutgoingMessage>,
        config: TransportConfiguration,
    ) -> Result<TcpTransport, Error> {
        StreamConnector::new(connect, self.endpoint_url.clone())
            .connect(channel, outgoing_recv, config)
            .await
    }

    fn default_endpoint(&self) -> EndpointDescription {
        EndpointDescription::from(self.endpoint_url.as_str())
    }
}

async fn connect(url: String, options: DecodingOptions) -> Result<Connection, Error> {
    let (reader, writer) = tokio::io::split(stream(&url).await?);
    Ok(StreamConnection::new(
        FramedRead::new(reader, TcpCodec::new(options)),
        writer,
        url,
    ))
}

/// A TCP connection to the server of an opc.tcp `url`, Nagle off.
async fn stream(url: &str) -> Result<TcpStream, Error> {
    let (host, port) =
        hostname_port_from_url(url, opcua::core::constants::DEFAULT_OPC_UA_SERVER_PORT)
            .map_err(|status| Error::new(status, format!("{url}: not an opc.tcp URL")))?;
    let unreachable = |e: std::io::Error| {
        Error::new(
            StatusCode::BadCommunicationError,
            format!("{host}:{port}: {e}"),
        )
    };
    let socket = TcpStream::connect((host.as_str(), port))
        .await
        .map_err(unreachable)?;
    socket.set_nodelay(true).map_err(unreachable)?;
    Ok(socket)
}

/// [`opcua::client::Client::connect_to_matching_endpoint`], over a
/// [`NoDelay`] connection (GetEndpoints too).
pub async fn connect_to_matching_endpoint(
    client: &mut opcua::client::Client,
    endpoint: EndpointDescription,
    identity: opcua::client::IdentityToken,
) -> Result<
    (
        std::sync::Arc<opcua::client::Session>,
        opcua::client::SessionEventLoop<NoDelayConnector>,
    ),
    Error,
> {
    let connector = NoDelay.get_connector(&endpoint)?;
    let endpoints = client.get_server_endpoints_from_url(connector).await?;
    client
        .session_builder()
        .with_endpoints(endpoints)
        .connect_to_matching_endpoint(endpoint)?
        .user_identity_token(identity)
        .with_connector(NoDelay)
        .build(client.certificate_store().clone())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn connections_send_without_nagle() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let socket = stream(&format!("opc.tcp://127.0.0.1:{port}/"))
            .await
            .unwrap();
        assert!(socket.nodelay().unwrap());
        let refused = stream("http://127.0.0.1:1/").await.unwrap_err();
        assert!(
            refused.to_string().contains("not an opc.tcp URL"),
            "{refused}"
        );
    }
}
