//! The built-in web page, `/metrics` and the JSON API, against the built
//! `plccoms` binary running a simulated PLC: `/metrics` parsed by Python's
//! prometheus_client, the page driven in Debian's Chromium (playwright-core,
//! `tests/web/`), the token rules, writes through SET's validation, the
//! history API without a historian, and HTTPS.
//!
//! Needs `python3` with `prometheus_client`, `node` with `tests/web`'s
//! packages installed (`npm ci --prefix tests/web`) and `/usr/bin/chromium`;
//! `.ci/run` installs them.

mod common;

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::process::{free_port, ChildGuard, ServerProcess, PLCCOMS};
use serde_json::Value;

const TOKEN: &str = "s3cret token";

/// `[*]` with the web keys, and the demo PLC section on `port`.
fn ini(web: &str, port: u16, section_extra: &str) -> String {
    format!(
        "[*]\nCOMM_LOOP_DELAY = 100\n{web}\n\n\
         [Demo]\nSIMULATOR = Yes\nSIMULATOR_PROGRAM = demo\nSERVER_PORT = {port}\n\
         IPADDR_LOCAL = 127.0.0.1\nPUBFILE = //demo.pub\n{section_extra}\n"
    )
}

struct Web {
    server: ServerProcess,
    http: SocketAddr,
}

fn start(web_keys: &str, section_extra: &str) -> Web {
    let web = start_server(web_keys, section_extra);
    let http = web.http;
    wait_until("the web page answers", || {
        request(http, "GET", "/api/sections", &[], None).0 == 200
            || request(http, "GET", "/api/session", &[], None).0 == 200
    });
    // The demo's public file comes from the simulated PLC.
    wait_until("the demo table is loaded", || {
        let (_, body) = request(
            http,
            "GET",
            "/api/sections/Demo/vars?mask=SINUS",
            &bearer(),
            None,
        );
        serde_json::from_slice::<Value>(&body).is_ok_and(|v| v["total"] == 1)
    });
    web
}

/// The server, without waiting for its page.
fn start_server(web_keys: &str, section_extra: &str) -> Web {
    let http_port = free_port();
    let port = free_port();
    let web = format!("HTTP_PORT = {http_port}\n{web_keys}");
    let server = ServerProcess::with_config(&ini(&web, port, section_extra), port);
    let http = SocketAddr::from(([127, 0, 0, 1], http_port));
    Web { server, http }
}

/// Waits for `check`; a liveness bound, not a speed limit: with the whole
/// suite on two cores a server with three sections and a historian took
/// over 15 s to record its first seconds.
fn wait_until(what: &str, mut check: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while !check() {
        assert!(Instant::now() < deadline, "timed out waiting until {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn bearer() -> Vec<(&'static str, String)> {
    vec![("Authorization", format!("Bearer {TOKEN}"))]
}

/// One HTTP/1.1 request (`Connection: close`): status and body (chunked
/// bodies decoded).
fn request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, String)],
    json: Option<&str>,
) -> (u16, Vec<u8>) {
    let (status, _, body) = exchange(addr, method, path, headers, json);
    (status, body)
}

fn exchange(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, String)],
    json: Option<&str>,
) -> (u16, String, Vec<u8>) {
    let Ok(mut stream) = TcpStream::connect_timeout(&addr, Duration::from_secs(5)) else {
        return (0, String::new(), Vec::new());
    };
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut head = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (name, value) in headers {
        head.push_str(&format!("{name}: {value}\r\n"));
    }
    let body = json.unwrap_or("");
    if json.is_some() {
        head.push_str("Content-Type: application/json\r\n");
    }
    head.push_str(&format!("Content-Length: {}\r\n\r\n{body}", body.len()));
    stream.write_all(head.as_bytes()).unwrap();
    let mut raw = Vec::new();
    let _ = stream.read_to_end(&mut raw);
    let Some(split) = raw.windows(4).position(|w| w == b"\r\n\r\n") else {
        return (0, String::new(), raw);
    };
    let head = String::from_utf8_lossy(&raw[..split]).into_owned();
    let mut body = raw[split + 4..].to_vec();
    let status = head
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    if head
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        body = dechunk(&body);
    }
    (status, head, body)
}

fn dechunk(mut raw: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let Some(end) = raw.windows(2).position(|w| w == b"\r\n") else {
            return out;
        };
        let size = usize::from_str_radix(std::str::from_utf8(&raw[..end]).unwrap().trim(), 16)
            .unwrap_or(0);
        if size == 0 || raw.len() < end + 2 + size {
            return out;
        }
        out.extend_from_slice(&raw[end + 2..end + 2 + size]);
        raw = &raw[(end + 4 + size).min(raw.len())..];
    }
}

/// GET `path` with no token: its JSON body.
fn get_json(http: SocketAddr, path: &str) -> Value {
    json(&request(http, "GET", path, &[], None).1)
}

fn json(body: &[u8]) -> Value {
    serde_json::from_slice(body)
        .unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(body)))
}

/// A telnet-like client of the section with `EN:*`: a client to list, and
/// DIFF lines to count.
fn client_with_everything_enabled(port: u16) -> TcpStream {
    let mut client = TcpStream::connect(("127.0.0.1", port)).unwrap();
    client.write_all(b"EN:*\r\n").unwrap();
    client
}

#[test]
fn metrics_parse_with_prometheus_client_and_name_every_family() {
    let web = start("", "");
    let _client = client_with_everything_enabled(web.server.port());
    // Let DIFF lines flow and the poll cycle be observed.
    std::thread::sleep(Duration::from_millis(500));
    let url = format!("http://{}/metrics", web.http);
    let output = Command::new("python3")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/web/check_metrics.py"))
        .arg(&url)
        .output()
        .expect("python3 runs (tests/web/check_metrics.py)");
    assert!(
        output.status.success(),
        "prometheus_client could not parse /metrics: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    let parsed = json(&output.stdout);
    assert_eq!(
        parsed["content_type"],
        "text/plain; version=0.0.4; charset=utf-8"
    );
    let families = parsed["families"].as_object().unwrap();
    // prometheus_client names counter families without `_total`.
    let expected = [
        ("plccoms_poll_cycle_seconds", "histogram"),
        ("plccoms_poll_overruns", "counter"),
        ("plccoms_poll_start_late_seconds", "histogram"),
        ("plccoms_backend_requests", "counter"),
        ("plccoms_backend_retries", "counter"),
        ("plccoms_backend_timeouts", "counter"),
        ("plccoms_backend_errors", "counter"),
        ("plccoms_backend_round_trip_seconds", "histogram"),
        ("plccoms_link_up", "gauge"),
        ("plccoms_clients_connected", "gauge"),
        ("plccoms_diff_lines", "counter"),
        ("plccoms_diff_bytes", "counter"),
        ("plccoms_client_output_queue_max_bytes", "gauge"),
        ("plccoms_pubfile_reloads", "counter"),
        ("plccoms_web_live_streams", "gauge"),
        ("plccoms_web_live_events", "counter"),
        ("plccoms_web_live_event_bytes", "counter"),
    ];
    for (name, kind) in expected {
        let family = families
            .get(name)
            .unwrap_or_else(|| panic!("no family {name} in {:?}", families.keys()));
        assert_eq!(family["type"], kind, "{name}");
        assert!(!family["help"].as_str().unwrap().is_empty(), "{name}: HELP");
    }
    let sample = |family: &str, sample: &str| -> f64 {
        families[family]["samples"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| {
                s[0] == sample && (s[1]["section"] == "Demo" || s[1] == serde_json::json!({}))
            })
            .unwrap_or_else(|| panic!("no sample {sample}"))[2]
            .as_f64()
            .unwrap()
    };
    assert_eq!(sample("plccoms_link_up", "plccoms_link_up"), 1.0);
    assert_eq!(
        sample("plccoms_clients_connected", "plccoms_clients_connected"),
        1.0
    );
    assert!(
        sample(
            "plccoms_poll_cycle_seconds",
            "plccoms_poll_cycle_seconds_count"
        ) > 0.0
    );
    assert!(
        sample(
            "plccoms_poll_start_late_seconds",
            "plccoms_poll_start_late_seconds_count"
        ) > 0.0
    );
    assert!(sample("plccoms_backend_requests", "plccoms_backend_requests_total") > 0.0);
    assert!(sample("plccoms_diff_lines", "plccoms_diff_lines_total") > 0.0);
    assert!(sample("plccoms_diff_bytes", "plccoms_diff_bytes_total") > 0.0);
}

#[test]
fn page_in_chromium_shows_live_values_and_a_chart_and_writes_with_the_token() {
    let web = start(&format!("HTTP_TOKEN = {TOKEN}"), "");
    let mut client = client_with_everything_enabled(web.server.port());
    // A second client that has a little queued, for the clients table.
    let _other = TcpStream::connect(("127.0.0.1", web.server.port())).unwrap();
    let artifacts = artifacts();
    let screenshot = artifacts.join("web-page.png");
    let _ = std::fs::remove_file(&screenshot);
    let seen = run_page_script(
        "page.mjs",
        &[
            format!("http://{}", web.http),
            screenshot.display().to_string(),
            TOKEN.to_string(),
        ],
    );
    assert_eq!(seen["failure"], Value::Null, "{seen:#}");
    assert_eq!(seen["page_errors"], serde_json::json!([]), "{seen:#}");
    let console: Vec<&str> = seen["console_errors"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_str)
        .collect();
    // The only console error: the browser's note of the refused write's 400.
    assert!(
        console
            .iter()
            .all(|e| e.starts_with("refused write: ") && e.contains("400")),
        "console errors: {console:?}"
    );
    assert_eq!(seen["link_state"], "online");
    assert_eq!(seen["ident"], "CP1000    SIM 1.0 1.0");
    assert_eq!(seen["quality"], "good");
    let changed = seen["value_changed_ms"].as_f64().unwrap();
    assert!(changed <= 1000.0, "SINUS changed after {changed} ms");
    assert!(seen["chart_points"].as_u64().unwrap() >= 5, "{seen:#}");
    assert_eq!(seen["chart_series"], 2);
    assert!(
        seen["chart_pixels"].as_u64().unwrap() > 20,
        "the chart drew no line: {seen:#}"
    );
    // Values in the user's terms: 21.5, not 21.500000; a refusal says why.
    assert_eq!(seen["write_result"], "✓ 21.5");
    assert_eq!(
        seen["bad_write_result"],
        "not written: 'hot' is not a number (REAL)"
    );
    // Logging in reloads the page; the ticked trend stays.
    assert_eq!(
        seen["trend_after_login"],
        serde_json::json!(["SINUS", "SETPOINT"])
    );
    assert_eq!(seen["boxes_after_login"], 2);
    // Every variable the page shows is polled for it: none stays stale.
    assert_eq!(
        seen["qualities"],
        serde_json::json!({"good": 29}),
        "{seen:#}"
    );
    assert_eq!(seen["legend"], "quality: good not polled stale link lost");
    assert_eq!(
        seen["range_status"],
        "historian not enabled: no history is recorded by this server"
    );
    let png = std::fs::read(&screenshot).expect("the screenshot");
    assert!(png.starts_with(b"\x89PNG") && png.len() > 10_000);
    // The write reached the PLC: the telnet client got its DIFF.
    client
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let mut seen_diff = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(5);
    let mut chunk = [0u8; 65536];
    while !String::from_utf8_lossy(&seen_diff).contains("DIFF:SETPOINT,21.500000")
        && Instant::now() < deadline
    {
        match client.read(&mut chunk) {
            Ok(n) if n > 0 => seen_diff.extend_from_slice(&chunk[..n]),
            _ => break,
        }
    }
    assert!(String::from_utf8_lossy(&seen_diff).contains("DIFF:SETPOINT,21.500000"));
    eprintln!("screenshot: {}", screenshot.display());
}

/// `target/test-artifacts/`: what a test run leaves to look at.
fn artifacts() -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .unwrap()
        .join("test-artifacts");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn off_loopback_without_a_token_the_server_does_not_start_and_names_http_token() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let http = free_port();
    std::fs::write(
        dir.path().join("plccoms.ini"),
        ini(
            &format!("HTTP_PORT = {http}\nHTTP_BIND = 0.0.0.0"),
            port,
            "",
        ),
    )
    .unwrap();
    let log = refused_start(dir.path());
    assert!(
        log.contains(
            "plccoms.ini:4: HTTP_BIND = 0.0.0.0 is not a loopback address: HTTP_TOKEN must be set"
        ),
        "{log}"
    );
}

/// Runs `plccoms -c plccoms.ini` in `dir`, which must refuse to start:
/// what it logged.
fn refused_start(dir: &Path) -> String {
    let output = Command::new(PLCCOMS)
        .args(["-c", "plccoms.ini"])
        .current_dir(dir)
        .env_remove("RUST_LOG")
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&output.stderr).into_owned();
    assert_eq!(output.status.code(), Some(1), "{log}");
    log
}

/// A configured page that cannot listen stops the start, naming the port:
/// the server never says "running" with its web page dead.
#[test]
fn a_page_that_cannot_listen_stops_the_start() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let http_port = taken.local_addr().unwrap().port();
    let port = free_port();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("plccoms.ini"),
        ini(&format!("HTTP_PORT = {http_port}"), port, ""),
    )
    .unwrap();
    let log = refused_start(dir.path());
    assert!(
        log.contains(&format!(
            "web page not started: web page: cannot listen on 127.0.0.1:{http_port}"
        )),
        "{log}"
    );
    assert!(!log.contains("section(s)"), "said running: {log}");
}

#[test]
fn off_loopback_every_request_needs_the_token_and_writes_always_do() {
    let web = start(&format!("HTTP_BIND = 0.0.0.0\nHTTP_TOKEN = {TOKEN}"), "");
    let http = web.http;
    for path in [
        "/api/sections",
        "/api/sections/Demo/values",
        "/metrics",
        "/api/log",
    ] {
        let (status, head, _) = exchange(http, "GET", path, &[], None);
        assert_eq!(status, 401, "{path}");
        assert!(head.contains("www-authenticate: Bearer"), "{head}");
        let wrong = [("Authorization", "Bearer nope".to_string())];
        assert_eq!(request(http, "GET", path, &wrong, None).0, 401, "{path}");
        assert_eq!(request(http, "GET", path, &bearer(), None).0, 200, "{path}");
    }
    // The page and what it asks first load without the token.
    assert_eq!(request(http, "GET", "/", &[], None).0, 200);
    let session = get_json(http, "/api/session");
    assert_eq!(session["reads_need_token"], true);
    assert_eq!(session["authenticated"], false);
    // Logging in sets a cookie that then serves as the token.
    let (status, _, _) = exchange(
        http,
        "POST",
        "/api/login",
        &[],
        Some(r#"{"token":"guess"}"#),
    );
    assert_eq!(status, 401);
    let login = serde_json::json!({ "token": TOKEN }).to_string();
    let (status, head, _) = exchange(http, "POST", "/api/login", &[], Some(&login));
    assert_eq!(status, 204);
    let cookie_line = head
        .lines()
        .find(|l| l.to_ascii_lowercase().starts_with("set-cookie:"))
        .expect("a cookie");
    assert!(cookie_line.contains("HttpOnly") && cookie_line.contains("SameSite=Strict"));
    let cookie = cookie_line
        .split_once(':')
        .unwrap()
        .1
        .split(';')
        .next()
        .unwrap()
        .trim();
    let with_cookie = [("Cookie", cookie.to_string())];
    assert_eq!(
        request(http, "GET", "/api/sections", &with_cookie, None).0,
        200
    );
    let set = |headers: &[(&str, String)], body: &str| {
        let (status, body) = request(http, "POST", "/api/sections/Demo/set", headers, Some(body));
        (status, json(&body))
    };
    let (status, _) = set(&[], r#"{"name":"setpoint","value":"1"}"#);
    assert_eq!(status, 401);
    let (status, body) = set(&with_cookie, r#"{"name":"setpoint","value":"20.25"}"#);
    assert_eq!(
        (status, &body),
        (
            200,
            &serde_json::json!({"name": "SETPOINT", "value": 20.25, "text": "20.25"})
        )
    );
    // SET's own validation, refused in the user's words.
    let (status, body) = set(&bearer(), r#"{"name":"setpoint","value":"warm"}"#);
    assert_eq!(status, 400);
    assert_eq!(
        body,
        serde_json::json!({"error": "not written: 'warm' is not a number (REAL)", "reason": "bad_value"})
    );
    let (status, body) = set(&bearer(), r#"{"name":"nothing","value":"1"}"#);
    assert_eq!(status, 400);
    assert_eq!(
        body,
        serde_json::json!({"error": "no variable named NOTHING in Demo", "reason": "unknown_variable"})
    );
    // The value is there for everyone.
    let values = json(
        &request(
            http,
            "GET",
            "/api/sections/Demo/values?vars=SETPOINT",
            &bearer(),
            None,
        )
        .1,
    );
    assert_eq!(values["values"][0]["value"], 20.25);
}

#[test]
fn on_loopback_reading_is_open_and_writing_needs_a_configured_token() {
    let web = start("", "");
    let http = web.http;
    assert_eq!(request(http, "GET", "/api/sections", &[], None).0, 200);
    let (status, body) = request(
        http,
        "POST",
        "/api/sections/Demo/set",
        &bearer(),
        Some(r#"{"name":"SETPOINT","value":"1"}"#),
    );
    assert_eq!(status, 403);
    assert!(json(&body)["error"]
        .as_str()
        .unwrap()
        .contains("HTTP_TOKEN"));
    let session = get_json(http, "/api/session");
    assert_eq!(session["writes_possible"], false);
    assert_eq!(session["historian"], false);
}

#[test]
fn a_read_only_section_refuses_writes_from_the_page_as_set_does() {
    let web = start(&format!("HTTP_TOKEN = {TOKEN}"), "READ_ONLY = Yes");
    let (status, body) = request(
        web.http,
        "POST",
        "/api/sections/Demo/set",
        &bearer(),
        Some(r#"{"name":"SETPOINT","value":"1"}"#),
    );
    assert_eq!(status, 403);
    assert_eq!(
        json(&body),
        serde_json::json!({"error": "the section is READ_ONLY: nothing in Demo is written", "reason": "read_only"})
    );
    let sections = json(&request(web.http, "GET", "/api/sections", &[], None).1);
    assert_eq!(sections[0]["read_only"], true);
    // The API says so of every variable: the page offers no Set box.
    let vars = json(&request(web.http, "GET", "/api/sections/Demo/vars", &[], None).1);
    assert_eq!(vars["total"], 29);
    assert!(
        vars["vars"]
            .as_array()
            .unwrap()
            .iter()
            .all(|v| v["writable"] == false),
        "{vars}"
    );
}

#[test]
fn the_api_lists_sections_clients_variables_and_values_and_streams_live_values() {
    let web = start("", "");
    let http = web.http;
    let _client = client_with_everything_enabled(web.server.port());
    let sections = get_json(http, "/api/sections");
    let demo = &sections[0];
    assert_eq!(demo["name"], "Demo");
    assert_eq!(demo["port"], web.server.port());
    assert_eq!(demo["link"]["state"], "online");
    assert_eq!(demo["link"]["ident"], "CP1000    SIM 1.0 1.0");
    assert_eq!(demo["poll"]["period_ms"], 100);
    assert_eq!(demo["variables"], 29);
    wait_until("the client is listed", || {
        let clients = get_json(http, "/api/sections/Demo/clients");
        clients[0]["enabled"].as_u64().unwrap_or(0) > 2
    });
    let vars = get_json(http, "/api/sections/Demo/vars?mask=s*,counter");
    assert_eq!(
        vars,
        serde_json::json!({"total": 4, "offset": 0, "next_offset": null, "vars": [
            {"name": "SINUS", "type": "LREAL", "writable": true},
            {"name": "SETPOINT", "type": "REAL", "writable": true},
            {"name": "SWITCH", "type": "BOOL", "writable": true},
            {"name": "COUNTER", "type": "INT", "writable": true}]})
    );
    wait_until("TEXT is polled for the client", || {
        let values = get_json(http, "/api/sections/Demo/values?vars=TEXT");
        values["values"][0]["quality"] == "good"
    });
    let values = get_json(http, "/api/sections/Demo/values?vars=TEXT");
    assert_eq!(values["values"][0]["value"], "Have a nice day");
    // Live: SINUS changes every poll.
    let mut stream = TcpStream::connect(http).unwrap();
    stream
        .write_all(b"GET /api/sections/Demo/live?vars=sinus HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        .unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let mut got = Vec::new();
    let mut chunk = [0u8; 4096];
    while got.windows(13).filter(|w| w == b"event: values").count() < 3 {
        let n = stream.read(&mut chunk).expect("live events");
        assert!(n > 0, "the stream ended: {}", String::from_utf8_lossy(&got));
        got.extend_from_slice(&chunk[..n]);
    }
    let text = String::from_utf8_lossy(&got);
    assert!(text.contains("content-type: text/event-stream"), "{text}");
    let event = text
        .lines()
        .filter_map(|l| l.strip_prefix("data: "))
        .nth(1)
        .unwrap();
    let event = json(event.as_bytes());
    assert_eq!(event["values"][0][0], "SINUS");
    assert_eq!(event["values"][0][2], "good");
    // The value in the user's terms (a number), and as text.
    let sinus = event["values"][0][1].as_f64().expect("SINUS is a number");
    assert_eq!(event["values"][0][4], sinus.to_string().as_str());
    assert_eq!(event["online"], true);
    // A mask too wide for one browser is refused, saying why.
    let (status, body) = request(http, "GET", "/api/sections/Nope/values", &[], None);
    assert_eq!(
        (status, json(&body)["error"].clone()),
        (404, Value::from("no section named 'Nope'"))
    );
}

#[test]
fn the_history_api_says_when_no_historian_is_enabled() {
    let web = start("", "");
    let (status, body) = request(
        web.http,
        "GET",
        "/api/history?section=Demo&vars=SINUS&from=0&format=csv",
        &[],
        None,
    );
    assert_eq!(status, 503);
    assert_eq!(
        json(&body)["error"],
        "historian not enabled: no history is recorded by this server"
    );
}

#[test]
fn the_history_api_reads_what_the_historian_recorded() {
    let web = start("HISTORY_SYNC = 1", "HISTORY = SINUS, TEXT");
    // The demo program changes SINUS every cycle: samples within a commit.
    let mut csv = String::new();
    wait_until("recorded samples in the history API", || {
        let (status, body) = request(
            web.http,
            "GET",
            "/api/history?section=Demo&vars=sin*&from=-1h&to=now&format=csv",
            &[],
            None,
        );
        csv = String::from_utf8_lossy(&body).into_owned();
        status == 200 && csv.lines().filter(|l| l.contains("SINUS")).count() >= 3
    });
    // The rows of `plccoms history` (README, "Reading it back").
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("time,name,value,text,quality"));
    assert_eq!(
        lines.next().map(|l| &l[24..]),
        Some(",__SERVER,,start,stopped")
    );
    // The first sample (a `__LINK` row may come first: the link's return
    // at start, when the PLC answered after recording began).
    let sample: Vec<&str> = lines
        .map(|line| line.split(',').collect::<Vec<&str>>())
        .find(|fields| !fields[1].starts_with("__"))
        .unwrap();
    assert_eq!(sample[1], "SINUS");
    assert!(sample[2].parse::<f64>().is_ok(), "{sample:?}");
    assert_eq!((sample[3], sample[4]), ("", "good"));
    assert!(!csv.contains("TEXT"), "only the masks asked for");
    let (status, body) = request(
        web.http,
        "GET",
        "/api/history?section=Nope&vars=*&from=-1h&format=json",
        &[],
        None,
    );
    assert_eq!(status, 404, "{}", String::from_utf8_lossy(&body));
}

#[test]
fn https_with_the_configured_certificate() {
    let dir = tempfile::tempdir().unwrap();
    let key = rcgen::generate_simple_self_signed(vec!["127.0.0.1".to_string()]).unwrap();
    let cert_path = dir.path().join("cert.pem");
    std::fs::write(&cert_path, key.cert.pem()).unwrap();
    std::fs::write(dir.path().join("key.pem"), key.signing_key.serialize_pem()).unwrap();
    let web = start_server(
        &format!(
            "HTTP_CERT = {}\nHTTP_KEY = {}",
            cert_path.display(),
            dir.path().join("key.pem").display()
        ),
        "",
    );
    // Python's TLS client, trusting only that certificate; the page starts
    // right after the section's port.
    let script = format!(
        "import ssl, time, urllib.request\n\
         ctx = ssl.create_default_context(cafile={cert:?})\n\
         for attempt in range(100):\n\
         \x20   try:\n\
         \x20       body = urllib.request.urlopen('https://{addr}/api/sections', context=ctx, timeout=10).read()\n\
         \x20       break\n\
         \x20   except ConnectionRefusedError:\n\
         \x20       time.sleep(0.1)\n\
         print(body.decode())\n",
        cert = cert_path.display().to_string(),
        addr = web.http
    );
    let output = Command::new("python3")
        .args(["-c", &script])
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert_eq!(json(&output.stdout)[0]["name"], "Demo");
    // Plain HTTP on the TLS port gets no page.
    assert_ne!(request(web.http, "GET", "/api/sections", &[], None).0, 200);
}

/// A TCP connection to `to` from the loopback address `from` (any of
/// 127.0.0.0/8 is this machine): the server sees as many clients as the
/// test has source addresses.
fn connect_from(from: [u8; 4], to: SocketAddr) -> std::io::Result<TcpStream> {
    let socket = socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None)?;
    socket.bind(&SocketAddr::from((from, 0)).into())?;
    socket.connect_timeout(&to.into(), Duration::from_secs(5))?;
    Ok(socket.into())
}

/// Descriptors the server process holds open.
fn server_fds(server: &mut ServerProcess) -> usize {
    let pid = server.child.child().id();
    std::fs::read_dir(format!("/proc/{pid}/fd"))
        .unwrap()
        .count()
}

/// The line protocol answers a GET on `port`.
fn line_client_is_served(port: u16) -> Result<(), String> {
    let mut client = TcpStream::connect(("127.0.0.1", port)).map_err(|e| e.to_string())?;
    client
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    client
        .write_all(b"GET:__PLC_RUN\r\n")
        .map_err(|e| e.to_string())?;
    let mut answer = [0u8; 64];
    let n = client.read(&mut answer).map_err(|e| e.to_string())?;
    if answer[..n].starts_with(b"GET:__PLC_RUN,") {
        Ok(())
    } else {
        Err(String::from_utf8_lossy(&answer[..n]).into_owned())
    }
}

#[test]
fn half_sent_requests_cannot_take_the_descriptors_the_line_protocol_needs() {
    let mut web = start("", "");
    // A server under a small descriptor limit, as a service manager may set.
    let pid = web.server.child.child().id();
    let limited = Command::new("prlimit")
        .args([&format!("--pid={pid}"), "--nofile=384:384"])
        .status()
        .expect("prlimit runs");
    assert!(limited.success());
    // 400 requests from 10 addresses, each stopping in its headers.
    let mut flood = Vec::new();
    for host in 2..12u8 {
        for _ in 0..40 {
            if let Ok(mut stream) = connect_from([127, 0, 0, host], web.http) {
                let _ = stream.write_all(b"GET /api/sections HTTP/1.1\r\nHost: 127.0.0.1\r\n");
                flood.push(stream);
            }
        }
    }
    std::thread::sleep(Duration::from_millis(500));
    let fds = server_fds(&mut web.server);
    assert!(
        fds < 384 - 64,
        "the web side holds {fds} of 384 descriptors"
    );
    line_client_is_served(web.server.port()).expect("a line client is served during the flood");
    let log = web.server.log();
    assert!(!log.contains("Too many open files"), "{log}");
    // The page still answers an address that is not flooding.
    wait_until("the page answers", || {
        let (status, _) = request(web.http, "GET", "/api/session", &[], None);
        status == 200
    });
    drop(flood);
}

#[test]
fn a_connection_that_stops_in_its_headers_or_sends_nothing_is_closed() {
    let web = start("", "");
    let mut silent = TcpStream::connect(web.http).unwrap();
    let mut half = TcpStream::connect(web.http).unwrap();
    half.write_all(b"GET /api/sections HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        .unwrap();
    for stream in [&mut silent, &mut half] {
        stream
            .set_read_timeout(Some(Duration::from_secs(40)))
            .unwrap();
        let mut buf = [0u8; 256];
        let closed = loop {
            match stream.read(&mut buf) {
                Ok(0) => break true,
                Ok(_) => continue,
                Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => break true,
                Err(_) => break false,
            }
        };
        assert!(closed, "the server kept an idle connection open for 40 s");
    }
}

/// Opens a live stream from `from`: the status line's code, and the stream.
fn open_live(from: [u8; 4], http: SocketAddr) -> (u16, TcpStream) {
    let mut stream = connect_from(from, http).expect("connect");
    stream
        .write_all(
            format!("GET /api/sections/Demo/live?vars=sinus HTTP/1.1\r\nHost: {http}\r\n\r\n")
                .as_bytes(),
        )
        .unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") && stream.read(&mut byte).unwrap_or(0) == 1 {
        head.push(byte[0]);
    }
    let status = String::from_utf8_lossy(&head)
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    (status, stream)
}

fn live_streams_gauge(http: SocketAddr) -> u64 {
    let (_, body) = request(http, "GET", "/metrics", &[], None);
    String::from_utf8_lossy(&body)
        .lines()
        .find_map(|l| l.strip_prefix("plccoms_web_live_streams "))
        .and_then(|v| v.trim().parse().ok())
        .expect("plccoms_web_live_streams")
}

#[test]
fn live_streams_are_capped_per_address_and_in_all_and_freed_when_closed() {
    let web = start("", "");
    let mut open = Vec::new();
    let mut refused = 0;
    for _ in 0..24 {
        match open_live([127, 0, 0, 1], web.http) {
            (200, stream) => open.push(stream),
            (503, _) => refused += 1,
            (other, _) => panic!("live stream answered {other}"),
        }
    }
    assert!(
        open.len() <= 16 && refused > 0,
        "one address opened {} live streams",
        open.len()
    );
    // Many addresses together meet the global cap.
    for host in 2..20u8 {
        for _ in 0..8 {
            match open_live([127, 0, 0, host], web.http) {
                (200, stream) => open.push(stream),
                (503, _) => refused += 1,
                (other, _) => panic!("live stream answered {other}"),
            }
        }
    }
    assert!(
        open.len() <= 64 && refused >= 24 + 18 * 8 - 64,
        "{} live streams open",
        open.len()
    );
    assert_eq!(live_streams_gauge(web.http), open.len() as u64);
    drop(open);
    wait_until("closed streams are freed", || {
        live_streams_gauge(web.http) == 0
    });
    // And their places are free again.
    assert_eq!(open_live([127, 0, 0, 1], web.http).0, 200);
}

/// The first SETTINGS frame the server sends on an HTTP/2 connection (h2c
/// with prior knowledge): its (identifier, value) pairs.
fn http2_server_settings(http: SocketAddr) -> Vec<(u16, u32)> {
    let mut stream = TcpStream::connect(http).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    stream
        .write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n\x00\x00\x00\x04\x00\x00\x00\x00\x00")
        .unwrap();
    loop {
        let mut head = [0u8; 9];
        stream.read_exact(&mut head).expect("an HTTP/2 frame");
        let len = u32::from_be_bytes([0, head[0], head[1], head[2]]) as usize;
        let mut payload = vec![0u8; len];
        stream.read_exact(&mut payload).unwrap();
        if head[3] == 4 && head[4] & 1 == 0 {
            return payload
                .chunks(6)
                .map(|c| {
                    (
                        u16::from_be_bytes([c[0], c[1]]),
                        u32::from_be_bytes([c[2], c[3], c[4], c[5]]),
                    )
                })
                .collect();
        }
    }
}

#[test]
fn http2_connections_allow_few_streams_at_once() {
    let web = start("", "");
    let settings = http2_server_settings(web.http);
    const MAX_CONCURRENT_STREAMS: u16 = 3;
    let max = settings
        .iter()
        .find(|(id, _)| *id == MAX_CONCURRENT_STREAMS)
        .map(|(_, v)| *v);
    assert!(
        max.is_some_and(|m| m <= 16),
        "SETTINGS_MAX_CONCURRENT_STREAMS {max:?}"
    );
}

#[test]
fn a_rebound_name_reads_nothing_and_other_sites_cannot_post() {
    let web = start(
        &format!("HTTP_TOKEN = {TOKEN}\nHTTP_HOSTS = plc.example, Other.Example:8080"),
        "",
    );
    let http = web.http;
    // `exchange` sends Host itself; a second Host header is refused too, so
    // these requests are written by hand.
    let get_with_host = |name: &str, path: &str| -> (u16, Vec<u8>) {
        let mut stream = TcpStream::connect(http).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        write!(
            stream,
            "GET {path} HTTP/1.1\r\nHost: {name}\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut raw = Vec::new();
        let _ = stream.read_to_end(&mut raw);
        let text = String::from_utf8_lossy(&raw).into_owned();
        let status = text
            .split(' ')
            .nth(1)
            .and_then(|s| s.parse().ok())
            .unwrap_or(0);
        let body = text
            .split_once("\r\n\r\n")
            .map(|(_, b)| b.as_bytes().to_vec())
            .unwrap_or_default();
        (status, body)
    };
    for path in ["/api/sections/Demo/values", "/api/log", "/metrics", "/"] {
        let (status, body) = get_with_host(&format!("attacker.example:{}", http.port()), path);
        assert_eq!(status, 421, "{path}: {}", String::from_utf8_lossy(&body));
        assert!(
            String::from_utf8_lossy(&body).contains("HTTP_HOSTS"),
            "{}",
            String::from_utf8_lossy(&body)
        );
    }
    for name in [
        format!("127.0.0.1:{}", http.port()),
        "127.0.0.1".to_string(),
        format!("localhost:{}", http.port()),
        "PLC.example".to_string(),
        "other.example:8080".to_string(),
    ] {
        assert_eq!(get_with_host(&name, "/api/sections").0, 200, "Host: {name}");
    }
    // A page of another site posts with its own Origin: refused, logged in
    // or not.
    let login = format!("{{\"token\": \"{TOKEN}\"}}");
    for path in ["/api/logout", "/api/login", "/api/sections/Demo/set"] {
        let (status, body) = request(
            http,
            "POST",
            path,
            &[("Origin", "http://attacker.example".to_string())],
            Some(&login),
        );
        assert_eq!(status, 403, "{path}: {}", String::from_utf8_lossy(&body));
        let (status, _) = request(
            http,
            "POST",
            path,
            &[("Sec-Fetch-Site", "cross-site".to_string())],
            Some(&login),
        );
        assert_eq!(status, 403, "{path} with Sec-Fetch-Site: cross-site");
    }
    // The page's own origin may.
    let (status, _) = request(
        http,
        "POST",
        "/api/login",
        &[("Origin", format!("http://{http}"))],
        Some(&login),
    );
    assert_eq!(status, 204);
}

#[test]
fn history_parameters_out_of_range_or_naming_no_section_are_refused() {
    let web = start("HISTORY_SYNC = 1", "HISTORY = SINUS");
    for (query, status_wanted, names) in [
        ("section=Demo&from=-9223372036854775808", 400, "from"),
        ("section=Demo&to=9223372036854775807", 400, "to"),
        ("section=..&from=0", 404, "section"),
        ("section=../../etc&from=0", 404, "section"),
        ("section=Nope", 404, "section"),
    ] {
        let (status, body) = request(web.http, "GET", &format!("/api/history?{query}"), &[], None);
        let error = json(&body)["error"].as_str().unwrap_or("").to_string();
        assert_eq!(status, status_wanted, "{query}: {error}");
        assert!(error.contains(names), "{query}: {error}");
    }
}

/// The cookie a login sets (`name=value`), and its Set-Cookie line.
fn login_cookie(http: SocketAddr) -> (String, String) {
    let login = serde_json::json!({ "token": TOKEN }).to_string();
    let (status, head, _) = exchange(http, "POST", "/api/login", &[], Some(&login));
    assert_eq!(status, 204, "{head}");
    let line = head
        .lines()
        .find(|l| l.to_ascii_lowercase().starts_with("set-cookie:"))
        .expect("a cookie")
        .to_string();
    let pair = line["set-cookie:".len()..]
        .split(';')
        .next()
        .unwrap()
        .trim()
        .to_string();
    (pair, line)
}

#[test]
fn sessions_expire_and_logout_ends_them_and_the_scheme_is_any_case() {
    let web = start_server(&format!("HTTP_BIND = 127.0.0.1\nHTTP_TOKEN = {TOKEN}"), "");
    let http = web.http;
    wait_until("the page answers", || {
        request(http, "GET", "/api/session", &[], None).0 == 200
    });
    let set = r#"{"name": "SETPOINT", "value": "1"}"#;
    let with = |name: &'static str, value: String| vec![(name, value)];
    // RFC 7235: the scheme is case-insensitive.
    let (status, _) = request(
        http,
        "POST",
        "/api/sections/Demo/set",
        &with("Authorization", format!("bearer {TOKEN}")),
        Some(set),
    );
    assert_ne!(status, 401, "lower-case bearer refused");
    let (cookie, line) = login_cookie(http);
    assert!(line.contains("Max-Age="), "{line}");
    assert!(
        !cookie.contains(&hex(TOKEN)),
        "the cookie is the token: {line}"
    );
    let (status, _) = request(
        http,
        "POST",
        "/api/sections/Demo/set",
        &with("Cookie", cookie.clone()),
        Some(set),
    );
    assert_ne!(status, 401);
    let (status, _) = request(
        http,
        "POST",
        "/api/logout",
        &with("Cookie", cookie.clone()),
        None,
    );
    assert_eq!(status, 204);
    let (status, _) = request(
        http,
        "POST",
        "/api/sections/Demo/set",
        &with("Cookie", cookie),
        Some(set),
    );
    assert_eq!(status, 401, "the session outlived its logout");
}

fn hex(text: &str) -> String {
    text.bytes().map(|b| format!("{b:02x}")).collect()
}

#[test]
fn token_guesses_are_throttled_even_in_parallel() {
    let web = start_server(&format!("HTTP_TOKEN = {TOKEN}"), "");
    let http = web.http;
    wait_until("the page answers", || {
        request(http, "GET", "/api/session", &[], None).0 == 200
    });
    let guesses: Vec<_> = (0..24)
        .map(|i| {
            std::thread::spawn(move || {
                let login = serde_json::json!({ "token": format!("guess {i}") }).to_string();
                request(http, "POST", "/api/login", &[], Some(&login)).0
            })
        })
        .collect();
    let statuses: Vec<u16> = guesses.into_iter().map(|g| g.join().unwrap()).collect();
    let compared = statuses.iter().filter(|s| **s == 401).count();
    assert!(
        compared <= 10 && statuses.iter().all(|s| *s == 401 || *s == 429),
        "{statuses:?}"
    );
    // Bearer guesses draw on the same budget.
    let (status, body) = request(
        http,
        "POST",
        "/api/sections/Demo/set",
        &[("Authorization", "Bearer guess".to_string())],
        Some(r#"{"name": "SETPOINT", "value": "1"}"#),
    );
    assert_eq!(status, 429, "{}", String::from_utf8_lossy(&body));
}

/// The server process's resident memory, in KiB.
fn server_rss_kib(web: &mut Web) -> u64 {
    let pid = web.server.child.child().id();
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS")
}

/// 5,000 live streams asked for took +105 MB, held after they closed. Now
/// at most 64 are open at once, the rest refused; what they held is given
/// back: rounds of opening and closing leave the server's memory where the
/// first round left it.
#[test]
fn thousands_of_live_streams_leave_memory_where_it_was() {
    let mut web = start("", "");
    let round = |web: &Web| {
        let mut open = Vec::new();
        for host in 1..=25u8 {
            for _ in 0..10 {
                if let (200, stream) = open_live([127, 0, 0, host], web.http) {
                    open.push(stream);
                }
            }
        }
        let held = open.len();
        drop(open);
        wait_until("closed streams are freed", || {
            live_streams_gauge(web.http) == 0
        });
        held
    };
    // The first round grows the allocator's pools to their working size.
    assert!(round(&web) <= 64);
    let before = server_rss_kib(&mut web);
    let mut asked = 250;
    while asked < 5_000 {
        assert!(round(&web) <= 64);
        asked += 250;
    }
    let after = server_rss_kib(&mut web);
    assert!(
        after < before + 16 * 1024,
        "VmRSS {before} kB after the first 250 live streams asked for, {after} kB after 5,000"
    );
    eprintln!("VmRSS {before} kB -> {after} kB over 5,000 live streams asked for");
}

/// A tag file for the simulated Modbus device of section M: units,
/// descriptions, a variable the file marks read-only, a DT.
const TAGS: &str = "name,type,table,address,access,unit,description\n\
    setpoint,REAL,holding,26,,°C,the heating setpoint\n\
    locked,INT,holding,30,ro,bar,set at the plant only\n\
    when,DT,holding,32,,,\n";

/// The demo section (its historian recording SINUS), section M (a
/// simulated Modbus device on [`TAGS`]) and section Gone (a Modbus device
/// nobody answers for), with the token.
fn start_three() -> (Web, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let tags = dir.path().join("tags.csv");
    std::fs::write(&tags, TAGS).unwrap();
    let closed = free_port();
    let extra = format!(
        "HISTORY = SINUS\n\n\
         [M]\nPROTOCOL = MODBUS_TCP\nSIMULATOR = Yes\nSERVER_PORT = {}\nMODBUS_TAGS = {tags}\n\n\
         [Gone]\nPROTOCOL = MODBUS_TCP\nIPADDR = 127.0.0.1\nMODBUS_PORT = {closed}\n\
         SERVER_PORT = {}\nMODBUS_TAGS = {tags}\n",
        free_port(),
        free_port(),
        tags = tags.display()
    );
    let web = start(&format!("HTTP_TOKEN = {TOKEN}\nHISTORY_SYNC = 1"), &extra);
    wait_until("section M's table is loaded", || {
        get_json(web.http, "/api/sections/M/vars")["total"].as_u64() > Some(0)
    });
    (web, dir)
}

/// A value of `/values` by name.
fn value_of(http: SocketAddr, section: &str, name: &str) -> Value {
    let list = get_json(http, &format!("/api/sections/{section}/values?vars={name}"));
    list["values"][0].clone()
}

#[test]
fn values_are_in_the_users_terms_with_units_quality_and_writability() {
    let (web, _dir) = start_three();
    let http = web.http;
    // Nobody polls the demo's variables yet: not_polled, not stale. The
    // system variables are always polled.
    let v = value_of(http, "Demo", "V_DT");
    assert_eq!(
        (&v["quality"], &v["value"]),
        (&"not_polled".into(), &Value::Null)
    );
    assert_eq!(value_of(http, "Demo", "__PLC_RUN")["quality"], "good");
    assert_eq!(value_of(http, "Demo", "__PLC_RUN")["writable"], false);
    // A device that never answers: link_lost.
    assert_eq!(value_of(http, "Gone", "SETPOINT")["quality"], "link_lost");
    let _client = client_with_everything_enabled(web.server.port());
    wait_until("the client's variables are polled", || {
        value_of(http, "Demo", "V_DT")["quality"] == "good"
    });
    let set = |section: &str, body: Value| {
        let (status, body) = request(
            http,
            "POST",
            &format!("/api/sections/{section}/set"),
            &bearer(),
            Some(&body.to_string()),
        );
        (status, json(&body))
    };
    // Numbers, booleans and ISO 8601 times are taken, and read back as such.
    for (name, given, shown) in [
        ("SETPOINT", serde_json::json!(22.3), serde_json::json!(22.3)),
        (
            "SETPOINT",
            serde_json::json!("20.5"),
            serde_json::json!(20.5),
        ),
        ("COUNTER", serde_json::json!(-12), serde_json::json!(-12)),
        ("SWITCH", serde_json::json!(true), serde_json::json!(true)),
        (
            "V_DT",
            serde_json::json!("2026-11-25T11:15:00.123+01:00"),
            serde_json::json!("2026-11-25T10:15:00.123Z"),
        ),
        (
            "V_TOD",
            serde_json::json!("10:15:00.5"),
            serde_json::json!("10:15:00.500"),
        ),
        (
            "V_ULINT",
            serde_json::json!(u64::MAX),
            serde_json::json!(u64::MAX),
        ),
    ] {
        let (status, body) = set("Demo", serde_json::json!({"name": name, "value": given}));
        assert_eq!(
            (status, &body["value"]),
            (200, &shown),
            "{name} {given}: {body}"
        );
        wait_until("the value is published", || {
            value_of(http, "Demo", name)["value"] == shown
        });
    }
    // TIME as an ISO duration. The demo program writes TIM (the time of
    // day) every PLC cycle, so a cycle between the write and its read-back
    // answers with the program's value: up to 3 tries for the written one.
    let mut answers = Vec::new();
    for _ in 0..3 {
        let (status, body) = set(
            "Demo",
            serde_json::json!({"name": "tim", "value": "PT1H2M3.456S"}),
        );
        assert_eq!(status, 200, "{body}");
        if body["value"] == "PT1H2M3.456S" {
            break;
        }
        answers.push(body["value"].clone());
    }
    assert!(
        answers.len() < 3,
        "TIME never read back as written: {answers:?}"
    );
    // Exact as text where a JSON reader's numbers are not.
    assert_eq!(
        value_of(http, "Demo", "V_ULINT")["text"],
        "18446744073709551615"
    );
    assert_eq!(value_of(http, "Demo", "TEXT")["value"], "Have a nice day");
    // DATE as a date. The demo program sets DAT to today every cycle, so
    // today is written: the read-back is today whether or not a cycle
    // ran between the write and it (another day was read back only then).
    let today = chrono::Utc::now().format("%Y-%m-%d").to_string();
    let (status, body) = set("Demo", serde_json::json!({"name": "dat", "value": today}));
    assert_eq!((status, &body["value"]), (200, &today.as_str().into()));
    // Refusals say why in the user's words, never as ERROR: lines.
    for (section, body, status_wanted, error, reason) in [
        (
            "M",
            serde_json::json!({"name": "locked", "value": 3}),
            403,
            "LOCKED is read-only: the tag file marks it ro",
            "read_only",
        ),
        (
            "Demo",
            serde_json::json!({"name": "__PLC_RUN", "value": false}),
            403,
            "__PLC_RUN is a system variable: the PLC's own state is not written from here",
            "system_variable",
        ),
        (
            "Demo",
            serde_json::json!({"name": "setpoint", "value": "hot"}),
            400,
            "not written: 'hot' is not a number (REAL)",
            "bad_value",
        ),
        (
            "Demo",
            serde_json::json!({"name": "v_dt", "value": "yesterday"}),
            400,
            "not written: 'yesterday': expected a date and time in ISO 8601 with its zone, as 2026-11-25T10:15:00.123Z",
            "bad_value",
        ),
        (
            "Demo",
            serde_json::json!({"name": "v_dt", "value": 1795601700}),
            400,
            "not written: a DT is written as ISO 8601 text (2026-11-25T10:15:00Z), not as a number",
            "bad_value",
        ),
        (
            "Demo",
            serde_json::json!({"name": "setpoint", "value": [1]}),
            400,
            "not written: the value is a number, true or false, or text",
            "bad_value",
        ),
        (
            "Gone",
            serde_json::json!({"name": "setpoint", "value": 1}),
            502,
            "not written: there is no link to the PLC",
            "unreachable",
        ),
    ] {
        let (status, body) = set(section, body.clone());
        assert_eq!(
            (status, body),
            (
                status_wanted,
                serde_json::json!({"error": error, "reason": reason})
            ),
            "{section}"
        );
    }
    // Units and descriptions from the tag file, and what may be written.
    let vars = get_json(http, "/api/sections/M/vars?mask=setpoint,locked,when");
    assert_eq!(
        vars["vars"],
        serde_json::json!([
            {"name": "SETPOINT", "type": "REAL", "unit": "°C",
             "description": "the heating setpoint", "writable": true},
            {"name": "LOCKED", "type": "INT", "unit": "bar",
             "description": "set at the plant only", "writable": false},
            {"name": "WHEN", "type": "DT", "writable": true}])
    );
    let (status, body) = set("M", serde_json::json!({"name": "setpoint", "value": 19.5}));
    assert_eq!(
        (status, body),
        (
            200,
            serde_json::json!({"name": "SETPOINT", "value": 19.5, "text": "19.5", "unit": "°C"})
        )
    );
    let m = value_of(http, "M", "SETPOINT");
    assert_eq!(
        (&m["unit"], &m["description"]),
        (&"°C".into(), &"the heating setpoint".into())
    );
}

#[test]
fn the_api_answers_an_index_of_itself() {
    let web = start("", "");
    for path in ["/api", "/api/"] {
        let (status, body) = request(web.http, "GET", path, &[], None);
        assert_eq!(status, 200, "{path}");
        let index = json(&body);
        let endpoints = index["endpoints"].as_array().unwrap();
        let set = endpoints
            .iter()
            .find(|e| e["path"] == "/api/sections/{section}/set")
            .expect("set is listed");
        assert_eq!(set["methods"], serde_json::json!(["POST"]));
        for e in endpoints {
            assert!(!e["description"].as_str().unwrap().is_empty(), "{e}");
        }
        assert!(endpoints.len() >= 12, "{index:#}");
    }
    assert_eq!(request(web.http, "GET", "/api/nothing", &[], None).0, 404);
}

/// Runs `node tests/web/<script> <args>`: the JSON line it prints.
fn run_page_script(script: &str, args: &[String]) -> Value {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/web")
        .join(script);
    let mut node = ChildGuard::spawn(
        "node tests/web script",
        Command::new("node")
            .arg(&path)
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped()),
    );
    let stdout = node.child().stdout.take().unwrap();
    let stderr = node.child().stderr.take().unwrap();
    let out = common::process::Capture::start(stdout);
    let err = common::process::Capture::start(stderr);
    let status = node
        .wait_timeout(Duration::from_secs(120))
        .expect("the browser run ends within 2 minutes");
    let (out, err) = (out.finish(), err.finish());
    assert!(
        status.success(),
        "node tests/web/{script} failed (is `npm ci --prefix tests/web` done and /usr/bin/chromium installed?): {}{}",
        String::from_utf8_lossy(&out),
        String::from_utf8_lossy(&err)
    );
    let line = String::from_utf8_lossy(&out);
    json(line.lines().last().unwrap_or("").as_bytes())
}

#[test]
fn page_in_chromium_shows_values_units_and_set_boxes_in_the_users_terms() {
    let (web, _dir) = start_three();
    let http = web.http;
    // Known values to show, and history recorded before the page opens.
    let _client = client_with_everything_enabled(web.server.port());
    for (name, value) in [("V_DT", "2026-11-25T10:15:00.123Z"), ("SETPOINT", "22.3")] {
        let body = serde_json::json!({"name": name, "value": value}).to_string();
        let (status, _) = request(
            http,
            "POST",
            "/api/sections/Demo/set",
            &bearer(),
            Some(&body),
        );
        assert_eq!(status, 200);
    }
    wait_until("the historian recorded SINUS", || {
        let (status, body) = request(
            http,
            "GET",
            "/api/history?section=Demo&vars=SINUS&from=-1h&format=csv",
            &[],
            None,
        );
        status == 200 && String::from_utf8_lossy(&body).lines().count() > 5
    });
    let seen = run_page_script("terms.mjs", &[format!("http://{http}"), TOKEN.to_string()]);
    assert_eq!(seen["failure"], Value::Null, "{seen:#}");
    assert_eq!(seen["page_errors"], serde_json::json!([]), "{seen:#}");
    assert_eq!(seen["console_errors"], serde_json::json!([]), "{seen:#}");
    let demo = &seen["demo"];
    assert_eq!(demo["V_DT"], "2026-11-25T10:15:00.123Z");
    assert_eq!(demo["SETPOINT"], "22.3");
    assert_eq!(demo["TEXT"], "Have a nice day");
    let iso = |text: &Value, pattern: &[&str]| {
        let text = text.as_str().unwrap();
        let shape: String = text
            .chars()
            .map(|c| if c.is_ascii_digit() { '9' } else { c })
            .collect();
        assert!(pattern.contains(&shape.as_str()), "{text}");
    };
    iso(&demo["DAT"], &["9999-99-99"]);
    iso(&demo["V_TOD"], &["99:99:99.999"]);
    assert!(demo["TIM"].as_str().unwrap().starts_with("PT"), "{demo}");
    // The trend of a recorded variable starts from its history.
    assert!(
        seen["seeded_before_tick"].as_u64().unwrap() >= 3,
        "{seen:#}"
    );
    let m = &seen["m"];
    assert!(
        m["setpoint_value"].as_str().unwrap().ends_with(" °C"),
        "{m}"
    );
    assert_eq!(m["setpoint_title"], "the heating setpoint");
    assert_eq!(m["setpoint_set_box"], 1);
    assert_eq!(m["locked_set_box"], 0);
    assert_eq!(m["locked_write_cell"], "read-only");
    assert_eq!(m["plc_run_set_box"], 0);
    assert_eq!(m["when_write"], "✓ 2026-11-25T10:15:00.123Z");
    assert_eq!(m["when_value"], "2026-11-25T10:15:00.123Z");
}

/// Tag names of the big section: `T00000` to `T19999`, one INT each.
const BIG_TAGS: usize = 20_000;
/// Sections that no PLC answers for, besides the big one.
const DEAD_SECTIONS: usize = 300;

/// Section `Big` (a simulated Modbus device with [`BIG_TAGS`] tags) first,
/// then `dev001` to `dev300`, Modbus devices on a port nobody listens on.
fn start_many() -> (Web, tempfile::TempDir) {
    use std::fmt::Write as _;
    let dir = tempfile::tempdir().unwrap();
    let big = dir.path().join("big.csv");
    let mut csv = String::from("name,type,table,address\n");
    for i in 0..BIG_TAGS {
        let _ = writeln!(csv, "T{i:05},INT,holding,{i}");
    }
    std::fs::write(&big, csv).unwrap();
    let small = dir.path().join("small.csv");
    std::fs::write(&small, "name,type,table,address\na,INT,holding,0\n").unwrap();
    // 300 ports picked free can be taken by another test's server before
    // this one binds them (the pick is a moment, the start seconds): that
    // section does not start, and the whole start is tried again with new
    // ports. Any other reason a section did not start fails the test.
    for attempt in 1.. {
        let web = start_many_on_new_ports(&big, &small);
        wait_until("the big table is loaded", || {
            let (status, body) = request(
                web.http,
                "GET",
                "/api/sections/Big/vars?mask=T*&limit=1",
                &[],
                None,
            );
            status == 200 && json(&body)["total"] == BIG_TAGS
        });
        // The web app starts after every section has started or failed.
        let running = get_paged(web.http, "/api/sections?limit=1").1;
        if running == Some(DEAD_SECTIONS + 1) {
            return (web, dir);
        }
        let log = web.server.log();
        let port_taken = log
            .lines()
            .filter(|l| l.contains("section not started"))
            .all(|l| l.contains("in use"));
        assert!(
            attempt < 3 && port_taken && log.contains("section not started"),
            "{running:?} of {} sections run (try {attempt}); the log:\n{log}",
            DEAD_SECTIONS + 1
        );
        eprintln!("try {attempt}: a section's port was taken meanwhile; starting again");
    }
    unreachable!()
}

fn start_many_on_new_ports(big: &std::path::Path, small: &std::path::Path) -> Web {
    use std::fmt::Write as _;
    // Ports picked apart: 300 random picks may repeat one.
    let mut taken = std::collections::HashSet::new();
    let mut port = || loop {
        let port = free_port();
        if taken.insert(port) {
            return port;
        }
    };
    let (http_port, big_port, closed) = (port(), port(), port());
    let mut ini = format!(
        "[*]\nCOMM_LOOP_DELAY = 100\nHTTP_PORT = {http_port}\n\n\
         [Big]\nPROTOCOL = MODBUS_TCP\nSIMULATOR = Yes\nSERVER_PORT = {big_port}\n\
         MODBUS_TAGS = {}\n",
        big.display()
    );
    for i in 1..=DEAD_SECTIONS {
        let _ = write!(
            ini,
            "\n[dev{i:03}]\nPROTOCOL = MODBUS_TCP\nIPADDR = 127.0.0.1\nMODBUS_PORT = {closed}\n\
             SERVER_PORT = {}\nMODBUS_TAGS = {}\n",
            port(),
            small.display()
        );
    }
    Web {
        server: ServerProcess::with_config(&ini, big_port),
        http: SocketAddr::from(([127, 0, 0, 1], http_port)),
    }
}

/// GET `path`: status, `X-Total-Count` if any, JSON body.
fn get_paged(http: SocketAddr, path: &str) -> (u16, Option<usize>, Value) {
    let (status, head, body) = exchange(http, "GET", path, &[], None);
    let total = head.lines().find_map(|line| {
        let (name, value) = line.split_once(':')?;
        name.eq_ignore_ascii_case("x-total-count")
            .then(|| value.trim().parse().ok())?
    });
    (status, total, json(&body))
}

/// A 400 whose `error` says `what`.
fn refused_with(http: SocketAddr, path: &str, what: &str) {
    let (status, _, body) = get_paged(http, path);
    assert_eq!(status, 400, "{path}: {body}");
    let error = body["error"].as_str().unwrap_or_default();
    assert!(
        error.contains(what),
        "{path}: {error:?} does not say {what:?}"
    );
}

fn names(list: &Value, key: &str) -> Vec<String> {
    list[key]
        .as_array()
        .unwrap_or_else(|| panic!("no {key} in {list}"))
        .iter()
        .map(|v| v["name"].as_str().unwrap().to_string())
        .collect()
}

#[test]
fn many_sections_and_a_table_of_20000_variables_are_read_a_page_at_a_time() {
    let (web, _dir) = start_many();
    let http = web.http;
    let all = DEAD_SECTIONS + 1;

    // Sections: all without a limit (as before), else a page; the header
    // counts those matching.
    let (status, total, list) = get_paged(http, "/api/sections");
    assert_eq!(status, 200);
    assert_eq!(total, Some(all));
    assert_eq!(list.as_array().unwrap().len(), all);
    let (_, total, list) = get_paged(http, "/api/sections?offset=20&limit=20");
    assert_eq!(total, Some(all));
    let page: Vec<&str> = list
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    assert_eq!(page.len(), 20);
    assert_eq!((page[0], page[19]), ("dev020", "dev039"));
    // The filter: part of the name, any case; or of the PLC's address.
    let (_, total, list) = get_paged(http, "/api/sections?filter=DEV29&limit=5");
    assert_eq!(total, Some(10));
    assert_eq!(list[0]["name"], "dev290");
    assert_eq!(list.as_array().unwrap().len(), 5);
    // Every device here is on 127.0.0.1, Big's simulator too.
    let (_, total, _) = get_paged(http, "/api/sections?filter=127.0.0.1");
    assert_eq!(total, Some(all));
    let (_, total, list) = get_paged(http, "/api/sections?offset=400&limit=20");
    assert_eq!((total, list), (Some(all), serde_json::json!([])));
    wait_until("Big is online", || {
        let (_, _, list) = get_paged(http, "/api/sections?state=online");
        list.as_array()
            .is_some_and(|l| l.len() == 1 && l[0]["name"] == "Big")
    });
    for (path, what) in [
        ("/api/sections?limit=0", "limit must be 1 to 1000"),
        ("/api/sections?limit=1001", "over 1000"),
        ("/api/sections?limit=ten", "limit"),
        ("/api/sections?offset=-1", "offset"),
        (
            "/api/sections?state=up",
            "none of no_plc, connecting, online, lost",
        ),
        ("/api/sections?page=2", "unknown field `page`"),
        ("/api/sections/Big/vars?limit=5001", "over 5000"),
        (
            "/api/sections/Big/values?limit=0",
            "limit must be 1 to 5000",
        ),
        ("/api/sections/Big/values?offset=x", "offset"),
        (
            "/api/sections/Big/values?vars=T*&sort=name",
            "unknown field `sort`",
        ),
        (
            "/api/sections/Big/live?vars=T*",
            "at most 2000 are shown live",
        ),
    ] {
        refused_with(http, path, what);
    }

    // Variables: a page from `offset`, `next_offset` to go on, the last
    // page short, past the end empty.
    let list = get_json(http, "/api/sections/Big/vars?mask=T*&limit=5000");
    assert_eq!(list["total"], BIG_TAGS);
    assert_eq!(
        (list["offset"].as_u64(), list["next_offset"].as_u64()),
        (Some(0), Some(5000))
    );
    assert_eq!(names(&list, "vars").len(), 5000);
    let list = get_json(
        http,
        "/api/sections/Big/values?vars=T*&offset=19950&limit=100",
    );
    let shown = names(&list, "values");
    assert_eq!(shown.len(), 50);
    assert_eq!(
        (shown[0].as_str(), shown[49].as_str()),
        ("T19950", "T19999")
    );
    assert_eq!(list["next_offset"], Value::Null);
    let list = get_json(http, "/api/sections/Big/values?vars=T*&offset=20000");
    assert_eq!(
        (list["total"].as_u64(), names(&list, "values").len()),
        (Some(20_000), 0)
    );
    // Without a limit a page of 1,000, never the whole table.
    let list = get_json(http, "/api/sections/Big/values");
    assert_eq!(names(&list, "values").len(), 1000);
    assert!(
        list["total"].as_u64().unwrap() > BIG_TAGS as u64,
        "{}",
        list["total"]
    );
    let list = get_json(http, "/api/sections/Big/vars?mask=t1999*");
    assert_eq!(names(&list, "vars").len(), 10);

    // What a page costs beside everything (printed for the notes).
    for path in [
        "/api/sections",
        "/api/sections?limit=20",
        "/api/sections/Big/values?vars=T*&limit=100",
        "/api/sections/Big/values?vars=T*&limit=5000",
    ] {
        let started = Instant::now();
        let (status, body) = request(http, "GET", path, &[], None);
        assert_eq!(status, 200);
        eprintln!("{path}: {} bytes in {:?}", body.len(), started.elapsed());
    }

    // /metrics: every section's families, or those asked for.
    let (status, text) = request(http, "GET", "/metrics", &[], None);
    assert_eq!(status, 200);
    let text = String::from_utf8(text).unwrap();
    let link_up = text
        .lines()
        .filter(|l| l.starts_with("plccoms_link_up{"))
        .count();
    assert_eq!(link_up, all);
    eprintln!(
        "/metrics of {all} sections: {} bytes, {} lines",
        text.len(),
        text.lines().count()
    );
    let (status, one) = request(http, "GET", "/metrics?section=dev007,Big", &[], None);
    assert_eq!(status, 200);
    let one = String::from_utf8(one).unwrap();
    let samples: Vec<&str> = one
        .lines()
        .filter(|l| l.starts_with("plccoms_link_up{"))
        .collect();
    assert_eq!(
        samples,
        [
            "plccoms_link_up{section=\"Big\"} 1",
            "plccoms_link_up{section=\"dev007\"} 0"
        ]
    );
    assert!(
        !one.contains("plccoms_web_"),
        "sources are not in a section's scrape"
    );
    let (status, body) = request(http, "GET", "/metrics?section=dev999", &[], None);
    assert_eq!(
        (status, json(&body)["error"].as_str()),
        (404, Some("no section named 'dev999'"))
    );
    let (status, _) = request(http, "GET", "/metrics?sections=dev007", &[], None);
    assert_eq!(status, 400);
}

#[test]
fn page_in_chromium_pages_and_filters_300_sections_and_20000_variables() {
    let (web, _dir) = start_many();
    let screenshot = artifacts().join("web-many-sections.png");
    let _ = std::fs::remove_file(&screenshot);
    let seen = run_page_script(
        "scale.mjs",
        &[
            format!("http://{}", web.http),
            screenshot.display().to_string(),
        ],
    );
    assert_eq!(seen["failure"], Value::Null, "{seen:#}");
    assert_eq!(seen["page_errors"], serde_json::json!([]), "{seen:#}");
    assert_eq!(seen["console_errors"], serde_json::json!([]), "{seen:#}");
    // The first section and the first page of its variables.
    assert_eq!(seen["section"], "Big");
    assert_eq!(seen["tabs"], 20);
    assert_eq!(seen["section_count"], "1–20 of 301 sections");
    assert_eq!(seen["rows"], 100);
    assert!(
        seen["var_count"]
            .as_str()
            .unwrap()
            .starts_with("1–100 of 200"),
        "{seen:#}"
    );
    // The next page of sections, then a filter.
    assert_eq!(
        seen["next_sections"],
        serde_json::json!(["dev020", "dev039"])
    );
    assert_eq!(seen["next_count"], "21–40 of 301 sections");
    assert_eq!(seen["filtered_tabs"], 10);
    assert_eq!(seen["filtered_count"], "1–10 of 10 matching");
    assert_eq!(seen["picked"], "dev295");
    assert!(
        ["connecting", "lost"].contains(&seen["picked_link"].as_str().unwrap_or_default()),
        "{seen:#}"
    );
    assert_eq!(seen["online_tabs"], serde_json::json!(["Big"]));
    // The next page of variables, then a mask; live values for what is on
    // screen only.
    assert_eq!(seen["next_first"], "T00100");
    assert!(
        seen["next_var_count"]
            .as_str()
            .unwrap()
            .starts_with("101–200 of "),
        "{seen:#}"
    );
    assert_eq!(seen["masked_rows"], 10);
    assert_eq!(seen["masked_pager_hidden"], true);
    assert_eq!(seen["masked_qualities"], serde_json::json!({"good": 10}));
    assert_eq!(seen["live_names"], 10);
    // Never a request for more than a page.
    assert_eq!(seen["unpaged_requests"], serde_json::json!([]), "{seen:#}");
    assert!(seen["requests"].as_u64().unwrap() > 5, "{seen:#}");
    let png = std::fs::read(&screenshot).expect("the screenshot");
    assert!(png.starts_with(b"\x89PNG"));
    eprintln!("screenshot: {}", screenshot.display());
}
