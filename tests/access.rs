//! Access control (this server's own keys): ALLOW and READ_ONLY; TCP
//! keepalive on accepted sockets.

mod common;

use std::fs;
use std::net::SocketAddr;
use std::os::fd::{AsRawFd, RawFd};
use std::time::Duration;

use common::{start, TestServer};
use plccoms_protocol::Area;
use tokio::io::AsyncReadExt;
use tokio::net::{TcpSocket, TcpStream};

/// The harness serves the first section of its ini file: one placed right
/// after `[*]` takes these keys.
fn section(keys: &str) -> String {
    format!("[Acl]\nSERVER_PORT = 5011\n{keys}")
}

async fn connect_from(source: &str, server: &TestServer) -> TcpStream {
    let socket = TcpSocket::new_v4().unwrap();
    socket.bind(format!("{source}:0").parse().unwrap()).unwrap();
    socket.connect(server.addr).await.unwrap()
}

/// The server closes the connection without sending anything.
async fn refused(mut stream: TcpStream) {
    let mut got = Vec::new();
    let result = tokio::time::timeout(Duration::from_secs(10), stream.read_to_end(&mut got))
        .await
        .expect("a refused client is closed at once");
    // End of stream, or a reset if the request was still unread.
    assert!(got.is_empty(), "{:?}", String::from_utf8_lossy(&got));
    drop(result);
}

async fn served(mut stream: TcpStream) -> TcpStream {
    use tokio::io::AsyncWriteExt;
    stream.write_all(b"LIST:TEST_1\n").await.unwrap();
    let want = b"LIST:TEST_1,INT*\r\nLIST:\r\n";
    let mut got = vec![0u8; want.len()];
    tokio::time::timeout(Duration::from_secs(10), stream.read_exact(&mut got))
        .await
        .expect("answer")
        .unwrap();
    assert_eq!(got, want);
    stream
}

#[tokio::test]
async fn allow_admits_listed_addresses_and_networks_only() {
    let server = start(&section("ALLOW = 127.0.0.2, 127.0.1.0/24, ::1")).await;
    let listed = served(connect_from("127.0.0.2", &server).await).await;
    let _network = served(connect_from("127.0.1.77", &server).await).await;
    for source in ["127.0.0.1", "127.0.0.3", "127.0.2.1"] {
        let stream = connect_from(source, &server).await;
        refused(stream).await;
    }
    assert_eq!(server.section.section.clients().len(), 2);
    served(listed).await;

    // Open by default, as PLCComS.
    let open = start("").await;
    served(connect_from("127.0.0.3", &open).await).await;
}

#[tokio::test]
async fn read_only_refuses_every_change_and_serves_the_rest() {
    let server = start(&section("READ_ONLY = Yes")).await;
    server.poke(Area::R, 0, &7i16.to_le_bytes());
    let mut c = server.client().await;
    c.ask(
        "SET:TEST_1,5\n",
        "ERROR:30 Bad client request: 'SET:TEST_1,5'\r\n",
    )
    .await;
    // A continuation line of SET, and a SET by address.
    c.ask(
        "TEST_1,6\n",
        "ERROR:30 Bad client request: 'SET:TEST_1,6'\r\n",
    )
    .await;
    c.ask(
        "SET:%RW0,9\n",
        "ERROR:30 Bad client request: 'SET:%RW0,9'\r\n",
    )
    .await;
    for key in [
        "ipaddr,10.0.0.1",
        "epsaddr,5",
        "epsport,1000",
        "serial_device,/dev/ttyS0",
        "serial_speed,9600",
        "pubfile,//other.pub",
    ] {
        c.ask(
            &format!("SETCONF:{key}\n"),
            &format!("ERROR:30 Bad client request: 'SETCONF:{key}'\r\n"),
        )
        .await;
    }
    // Files: the blocks are dropped, the answer comes where it would.
    for name in ["./new.txt", "new.txt"] {
        c.send(format!("WRITEFILE:{name}[3]=abc\nWRITEFILE:{name}[0]=\n").as_bytes())
            .await;
        c.expect(format!("ERROR:30 Bad client request: 'WRITEFILE:{name}'\r\n").as_bytes())
            .await;
        c.send(format!("WRITEFILEINFO:{name}[7]=1 0 0 0\n").as_bytes())
            .await;
        c.expect(format!("ERROR:30 Bad client request: 'WRITEFILEINFO:{name}'\r\n").as_bytes())
            .await;
    }
    assert_eq!(fs::read_dir(server.root.path()).unwrap().count(), 0);
    assert_eq!(fs::read_dir(server.plc_files.path()).unwrap().count(), 0);
    // Nothing changed in the PLC.
    assert_eq!(server.peek(Area::R, 0, 2), 7i16.to_le_bytes());
    // Reading works.
    c.ask("GET:TEST_1\n", "GET:TEST_1,7\r\n").await;
    c.ask("GET:%RW0\n", "GET:%RW0,7\r\n").await;
    c.ask(
        "EN:TEST_1\n",
        "WARNING:252 Changed active variables in public file: '[3/26]'\r\n",
    )
    .await;
    c.expect(b"DIFF:TEST_1,7\r\n").await;
    c.ask("SETCONF:diff,no\n", "SETCONF:DIFF,NO\r\n").await;
    c.ask("LIST:TEST_1\n", "LIST:TEST_1,INT\r\nLIST:\r\n").await;
    c.ask(
        "GETFILE:./none.txt\n",
        "ERROR:41 Unable to get file: './none.txt'\r\n",
    )
    .await;
}

fn sockopt(fd: RawFd, level: i32, name: i32) -> i32 {
    let mut value: libc::c_int = 0;
    let mut len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
    // SAFETY: a valid descriptor of this process and a buffer of the
    // option's size.
    let rc = unsafe {
        libc::getsockopt(
            fd,
            level,
            name,
            (&mut value as *mut libc::c_int).cast(),
            &mut len,
        )
    };
    assert_eq!(rc, 0, "getsockopt: {}", std::io::Error::last_os_error());
    value
}

fn sock_addr(fd: RawFd, peer: bool) -> Option<SocketAddr> {
    // SAFETY: the descriptor stays open while borrowed, and ManuallyDrop
    // keeps it from being closed here.
    let socket = std::mem::ManuallyDrop::new(unsafe {
        <std::net::TcpStream as std::os::fd::FromRawFd>::from_raw_fd(fd)
    });
    if peer {
        socket.peer_addr().ok()
    } else {
        socket.local_addr().ok()
    }
}

/// The server's accepted socket for `client`: found among this process's
/// descriptors (the server runs in it) by its two addresses.
fn accepted_fd(server: &TestServer, client: &TcpStream) -> RawFd {
    let client_addr = client.local_addr().unwrap();
    let client_fd = client.as_raw_fd();
    for entry in fs::read_dir("/proc/self/fd").unwrap() {
        let Ok(fd) = entry
            .unwrap()
            .file_name()
            .to_string_lossy()
            .parse::<RawFd>()
        else {
            continue;
        };
        if fd == client_fd {
            continue;
        }
        let is_socket = fs::read_link(format!("/proc/self/fd/{fd}"))
            .is_ok_and(|target| target.to_string_lossy().starts_with("socket:"));
        if is_socket
            && sock_addr(fd, false) == Some(server.addr)
            && sock_addr(fd, true) == Some(client_addr)
        {
            return fd;
        }
    }
    panic!("the server's socket for {client_addr} was not found");
}

#[tokio::test]
async fn accepted_sockets_have_tcp_keepalive() {
    let server = start("").await;
    let mut c = server.client().await;
    c.ask("LIST:TEST_1\n", "LIST:TEST_1,INT*\r\nLIST:\r\n")
        .await;
    let fd = accepted_fd(&server, &c.stream);
    assert_eq!(sockopt(fd, libc::SOL_SOCKET, libc::SO_KEEPALIVE), 1);
    assert_eq!(sockopt(fd, libc::IPPROTO_TCP, libc::TCP_KEEPIDLE), 60);
    assert_eq!(sockopt(fd, libc::IPPROTO_TCP, libc::TCP_KEEPINTVL), 10);
    assert_eq!(sockopt(fd, libc::IPPROTO_TCP, libc::TCP_KEEPCNT), 5);
    assert_eq!(
        plccoms_telnet::server::KEEPALIVE_IDLE,
        Duration::from_secs(60)
    );
}
