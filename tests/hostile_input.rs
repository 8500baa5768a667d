//! Hostile and broken input over TCP: over-long lines, NUL and 0xFF bytes,
//! broken telnet sequences, cp1250 bytes that map to nothing, connection
//! floods. Each gets an error line where the protocol has one, the session
//! goes on, and other clients are not affected.

mod common;

use std::time::{Duration, Instant};

use common::{start, Client, TestServer};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// A second client checks that it is served normally.
async fn others_unaffected(server: &TestServer) {
    let mut other = server.client().await;
    other
        .ask("LIST:TEST_1\n", "LIST:TEST_1,INT*\r\nLIST:\r\n")
        .await;
}

trait AskRaw {
    async fn ask_raw(&mut self, request: &[u8], answer: &[u8]);
}

impl AskRaw for Client {
    async fn ask_raw(&mut self, request: &[u8], answer: &[u8]) {
        self.send(request).await;
        self.expect(answer).await;
    }
}

async fn still_works(c: &mut Client) {
    c.ask("LIST:TEST_1\n", "LIST:TEST_1,INT*\r\nLIST:\r\n")
        .await;
}

#[tokio::test]
async fn an_over_long_line_gets_error_30_and_the_session_goes_on() {
    let server = start("").await;
    let mut c = server.client().await;
    let mut line = b"GET:".to_vec();
    line.extend(std::iter::repeat_n(b'A', 100_000));
    line.push(b'\n');
    c.send(&line).await;
    let mut want = b"ERROR:30 Bad client request: 'GET:".to_vec();
    want.extend(std::iter::repeat_n(b'A', 60));
    want.extend_from_slice(b"...'\r\n");
    c.expect(&want).await;
    still_works(&mut c).await;
    // Exactly at the limit is still a request (16 KiB): an unknown name.
    let mut line = b"GET:".to_vec();
    line.extend(std::iter::repeat_n(b'B', 16 * 1024 - 4));
    line.push(b'\n');
    c.send(&line).await;
    let answer = c.line().await;
    assert!(
        answer.starts_with(b"ERROR:33 "),
        "{:?}",
        String::from_utf8_lossy(&answer)
    );
    still_works(&mut c).await;
    others_unaffected(&server).await;
}

#[tokio::test]
async fn nul_and_ff_bytes() {
    let server = start("").await;
    let mut c = server.client().await;
    // NUL bytes are dropped from a line.
    c.ask("\0LIST:\0TEST_1\0\n", "LIST:TEST_1,INT*\r\nLIST:\r\n")
        .await;
    c.ask("\0\0\0\n", "").await;
    // IAC IAC is a literal 0xFF: after LIST a bare line is LIST's
    // continuation (a mask that matches nothing)...
    c.ask_raw(b"\xff\xff\xff\xff\n", b"LIST:\r\n").await;
    // ...and on a fresh session an unknown command.
    let mut fresh = server.client().await;
    fresh
        .ask_raw(
            b"\xff\xff\xff\xff\n",
            b"ERROR:32 Unknown command name in request: '\xff\xff'\r\n",
        )
        .await;
    c.send(b"GET:\xff\xff\n").await;
    c.expect(b"ERROR:33 Unknown variable name in request: 'GET:\xff'\r\n")
        .await;
    // Every other byte value (but the line end) in a name.
    let mut line = b"GET:".to_vec();
    line.extend((1..=254u8).filter(|&b| b != b'\n'));
    line.push(b'\n');
    // (it holds `*`: a mask that matches nothing)
    c.ask_raw(&line, b"GET:\r\n").await;
    still_works(&mut c).await;
    others_unaffected(&server).await;
}

#[tokio::test]
async fn broken_telnet_sequences() {
    let server = start("").await;
    let mut c = server.client().await;
    // IAC WILL then a byte: that byte is the option, not data.
    c.send(b"\xff\xfbLIST:TEST_1\n").await;
    c.expect(b"ERROR:32 Unknown command name in request: 'IST:TEST_1'\r\n")
        .await;
    // A real negotiation in the middle of a request is skipped.
    c.ask("LIST:\u{0}TEST_1\n", "LIST:TEST_1,INT*\r\nLIST:\r\n")
        .await;
    c.send(b"LI\xff\xfd\x18ST:TE\xff\xf1ST_1\n").await;
    c.expect(b"LIST:TEST_1,INT*\r\nLIST:\r\n").await;
    // A subnegotiation that never ends: after a bounded skip the bytes are
    // data again, so the session is not swallowed.
    let mut junk = b"\xff\xfa\x18".to_vec();
    junk.extend(std::iter::repeat_n(b'x', 2000));
    junk.push(b'\n');
    c.send(&junk).await;
    // (here a continuation of LIST: a mask of x's that matches nothing)
    c.expect(b"LIST:\r\n").await;
    still_works(&mut c).await;
    // IAC before the line end, and IAC as the last byte of the connection.
    c.send(b"\xff\n").await;
    still_works(&mut c).await;
    c.send(b"LIST:TEST_1\n\xff").await;
    c.expect(b"LIST:TEST_1,INT*\r\nLIST:\r\n").await;
    c.stream.shutdown().await.unwrap();
    c.closed().await;
    others_unaffected(&server).await;
}

#[tokio::test]
async fn cp1250_bytes_that_map_to_nothing() {
    let server = start("").await;
    let mut c = server.client().await;
    let unmapped = b"\x81\x83\x88\x90\x98";
    let mut line = b"GET:".to_vec();
    line.extend_from_slice(unmapped);
    c.send(&[line.as_slice(), b"\n"].concat()).await;
    c.expect(
        &[
            b"ERROR:33 Unknown variable name in request: '".as_slice(),
            &line,
            b"'\r\n",
        ]
        .concat(),
    )
    .await;
    // As a STRING value: stored and read back byte for byte.
    c.send(&[b"SET:TEST_STRING,".as_slice(), unmapped, b"\n"].concat())
        .await;
    c.expect(&[b"DIFF:TEST_STRING,\"".as_slice(), unmapped, b"\"\r\n"].concat())
        .await;
    let stored = server.peek(plccoms_protocol::Area::R, 8, 6);
    assert_eq!(&stored[..5], unmapped);
    // After SET a bare line continues it: no comma, incomplete.
    c.ask_raw(b"\x81\x98:x\n", b"ERROR:31 Incomplete client request.\r\n")
        .await;
    // In a command name on a fresh session, and in LIST's mask.
    let mut fresh = server.client().await;
    fresh
        .ask_raw(
            b"\x81\x98:x\n",
            b"ERROR:32 Unknown command name in request: '\x81\x98:x'\r\n",
        )
        .await;
    c.ask_raw(b"LIST:\x81*\n", b"LIST:\r\n").await;
    still_works(&mut c).await;
    others_unaffected(&server).await;
}

/// NET_CONNECT_MAX + many at once: every extra one gets ERROR:11 and is
/// closed; those admitted keep working; a place freed is taken again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_connection_flood_over_net_connect_max() {
    const MAX: usize = 16;
    const FLOOD: usize = 300;
    let server = start(&format!("NET_CONNECT_MAX = {MAX}")).await;
    let mut admitted = Vec::new();
    for _ in 0..MAX {
        let mut c = server.client().await;
        still_works(&mut c).await;
        admitted.push(c);
    }
    let addr = server.addr;
    let start = Instant::now();
    let flood: Vec<_> = (0..FLOOD)
        .map(|_| {
            tokio::spawn(async move {
                let mut stream = TcpStream::connect(addr).await.expect("connect");
                let _ = stream.write_all(b"LIST:\n").await;
                let mut got = Vec::new();
                tokio::time::timeout(Duration::from_secs(30), stream.read_to_end(&mut got))
                    .await
                    .expect("refused connection not closed")
                    .ok();
                got
            })
        })
        .collect();
    for task in flood {
        let got = task.await.unwrap();
        assert_eq!(
            String::from_utf8_lossy(&got),
            "ERROR:11 Maximum connections reached.\r\n"
        );
    }
    eprintln!("{FLOOD} refused in {:?}", start.elapsed());
    for c in &mut admitted {
        still_works(c).await;
    }
    assert_eq!(server.section.section.clients().len(), MAX);
    drop(admitted.pop());
    let started = Instant::now();
    loop {
        let mut c = server.client().await;
        c.send(b"LIST:TEST_1\n").await;
        let line = c.line().await;
        if line.starts_with(b"LIST:TEST_1") {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(10),
            "no place freed"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}
