//! Who may read and who may write.
//!
//! - Writing (a SET from the page or the API) always needs HTTP_TOKEN; with
//!   no token configured the web server writes nothing.
//! - Reading needs the token too when HTTP_BIND is not a loopback address
//!   (configuration refuses such an address without a token); on loopback
//!   anyone on the machine may look.
//!
//! The token comes as `Authorization: Bearer <token>` (scripts, Prometheus;
//! the scheme in any case) or the page logs in with it and gets a session:
//! a random cookie (`SameSite=Strict`, `HttpOnly`, 12 h) that logout ends on
//! the server. Tokens are compared as SHA-256 hashes, in constant time and
//! without telling their length. Wrong tokens draw on a budget, per address
//! and in all, taken before the comparison: parallel guesses cannot outrun
//! it, and over it a token is not even compared (429).

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::extract::{ConnectInfo, Request};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::{Deserialize, Serialize};

use super::api::error;
use super::{Shared, State};

const COOKIE: &str = "plccoms_session";

/// A failed login waits this long: guessing stays slow.
const LOGIN_PENALTY: Duration = Duration::from_millis(300);
/// How long a session lasts; how many are kept (the oldest goes first).
const SESSION_LIFE: Duration = Duration::from_secs(12 * 3600);
const MAX_SESSIONS: usize = 64;
/// Wrong tokens: a burst, then one per interval, per address and in all.
const GUESSES_PER_ADDRESS: Bucket = Bucket::new(10.0, 0.5);
const GUESSES_IN_ALL: Bucket = Bucket::new(20.0, 2.0);
/// Addresses whose guesses are remembered at most.
const MAX_GUESSERS: usize = 4096;

type Digest = [u8; 32];

fn digest(bytes: &[u8]) -> Digest {
    let hash = ring::digest::digest(&ring::digest::SHA256, bytes);
    let mut out = [0u8; 32];
    out.copy_from_slice(hash.as_ref());
    out
}

/// A token bucket of wrong guesses.
#[derive(Clone, Copy)]
struct Bucket {
    burst: f64,
    per_second: f64,
    level: f64,
    at: Option<Instant>,
}

impl Bucket {
    const fn new(burst: f64, per_second: f64) -> Bucket {
        Bucket {
            burst,
            per_second,
            level: burst,
            at: None,
        }
    }

    fn refill(&mut self, now: Instant) {
        if let Some(at) = self.at {
            let gained = now.duration_since(at).as_secs_f64() * self.per_second;
            self.level = (self.level + gained).min(self.burst);
        }
        self.at = Some(now);
    }
}

#[derive(Default)]
struct Guesses {
    all: Option<Bucket>,
    by_address: HashMap<IpAddr, Bucket>,
}

pub struct Auth {
    token: Option<Digest>,
    reads_need_token: bool,
    /// Cookies get `Secure` over HTTPS.
    secure: bool,
    /// Hashes of the session ids, and when each ends.
    sessions: Mutex<HashMap<Digest, Instant>>,
    guesses: Mutex<Guesses>,
}

/// A token may not be compared now: too many wrong ones lately.
pub struct Throttled;

/// What a request proved.
#[derive(PartialEq, Eq)]
enum Proof {
    Token,
    None,
}

/// Why a write is refused.
pub enum WriteRefusal {
    /// No HTTP_TOKEN configured: nobody writes through the web server.
    NoToken,
    /// The request does not carry the token.
    Unauthorized,
    /// Too many wrong tokens lately.
    Throttled,
}

impl Auth {
    pub fn new(token: Option<String>, reads_need_token: bool, secure: bool) -> Auth {
        Auth {
            token: token.map(|t| digest(t.as_bytes())),
            reads_need_token,
            secure,
            sessions: Mutex::new(HashMap::new()),
            guesses: Mutex::new(Guesses::default()),
        }
    }

    /// Takes one guess from the budgets of `peer` and of all, before the
    /// comparison; [`Auth::refund`] gives it back when it was right.
    fn take_guess(&self, peer: IpAddr) -> Result<(), Throttled> {
        let now = Instant::now();
        let mut guesses = self.guesses.lock().unwrap_or_else(|p| p.into_inner());
        let all = guesses.all.get_or_insert(GUESSES_IN_ALL);
        all.refill(now);
        if all.level < 1.0 {
            return Err(Throttled);
        }
        if guesses.by_address.len() >= MAX_GUESSERS {
            guesses.by_address.retain(|_, b| {
                b.refill(now);
                b.level < b.burst
            });
        }
        if guesses.by_address.len() >= MAX_GUESSERS {
            return Err(Throttled);
        }
        let mine = guesses
            .by_address
            .entry(peer)
            .or_insert(GUESSES_PER_ADDRESS);
        mine.refill(now);
        if mine.level < 1.0 {
            return Err(Throttled);
        }
        mine.level -= 1.0;
        if let Some(all) = guesses.all.as_mut() {
            all.level -= 1.0;
        }
        Ok(())
    }

    fn refund(&self, peer: IpAddr) {
        let mut guesses = self.guesses.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(all) = guesses.all.as_mut() {
            all.level = (all.level + 1.0).min(all.burst);
        }
        if let Some(mine) = guesses.by_address.get_mut(&peer) {
            mine.level = (mine.level + 1.0).min(mine.burst);
        }
    }

    /// `given` against the token, drawing on the guess budget.
    fn check_token(&self, given: &[u8], peer: IpAddr) -> Result<bool, Throttled> {
        let Some(token) = &self.token else {
            return Ok(false);
        };
        self.take_guess(peer)?;
        let right = same(&digest(given), token);
        if right {
            self.refund(peer);
        }
        Ok(right)
    }

    /// Whether the request carries the token or a live session.
    fn presented(&self, headers: &HeaderMap, peer: IpAddr) -> Result<Proof, Throttled> {
        if self.token.is_none() {
            return Ok(Proof::None);
        }
        if let Some(id) = cookie(headers) {
            let key = digest(id.as_bytes());
            let sessions = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
            if sessions.get(&key).is_some_and(|end| *end > Instant::now()) {
                return Ok(Proof::Token);
            }
        }
        for value in headers.get_all(header::AUTHORIZATION) {
            let Ok(value) = value.to_str() else { continue };
            let Some((scheme, given)) = value.trim().split_once(' ') else {
                continue;
            };
            if scheme.eq_ignore_ascii_case("bearer")
                && self.check_token(given.trim().as_bytes(), peer)?
            {
                return Ok(Proof::Token);
            }
        }
        Ok(Proof::None)
    }

    pub fn may_read(&self, headers: &HeaderMap, peer: IpAddr) -> Result<bool, Throttled> {
        if !self.reads_need_token {
            return Ok(true);
        }
        Ok(self.presented(headers, peer)? == Proof::Token)
    }

    pub fn may_write(&self, headers: &HeaderMap, peer: IpAddr) -> Result<(), WriteRefusal> {
        if self.token.is_none() {
            return Err(WriteRefusal::NoToken);
        }
        match self.presented(headers, peer) {
            Ok(Proof::Token) => Ok(()),
            Ok(Proof::None) => Err(WriteRefusal::Unauthorized),
            Err(Throttled) => Err(WriteRefusal::Throttled),
        }
    }

    /// A new session: its id for the cookie.
    fn open_session(&self) -> String {
        let mut id = [0u8; 32];
        let _ = ring::rand::SecureRandom::fill(&ring::rand::SystemRandom::new(), &mut id);
        let id: String = id.iter().map(|b| format!("{b:02x}")).collect();
        let now = Instant::now();
        let mut sessions = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
        sessions.retain(|_, end| *end > now);
        if sessions.len() >= MAX_SESSIONS {
            if let Some(oldest) = sessions
                .iter()
                .min_by_key(|(_, end)| **end)
                .map(|(k, _)| *k)
            {
                sessions.remove(&oldest);
            }
        }
        sessions.insert(digest(id.as_bytes()), now + SESSION_LIFE);
        id
    }

    fn close_session(&self, headers: &HeaderMap) {
        if let Some(id) = cookie(headers) {
            let mut sessions = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
            sessions.remove(&digest(id.as_bytes()));
        }
    }
}

impl WriteRefusal {
    pub fn response(&self) -> Response {
        match self {
            WriteRefusal::NoToken => error(
                StatusCode::FORBIDDEN,
                "writing through the web page needs HTTP_TOKEN in the configuration's [*] section",
            ),
            WriteRefusal::Unauthorized => unauthorized(),
            WriteRefusal::Throttled => throttled(),
        }
    }
}

fn unauthorized() -> Response {
    let mut response = error(
        StatusCode::UNAUTHORIZED,
        "this needs the HTTP_TOKEN: log in on the page, or send Authorization: Bearer <token>",
    );
    response.headers_mut().insert(
        header::WWW_AUTHENTICATE,
        HeaderValue::from_static("Bearer realm=\"plccoms\""),
    );
    response
}

fn throttled() -> Response {
    let mut response = error(
        StatusCode::TOO_MANY_REQUESTS,
        "too many wrong tokens lately: try again in a few seconds",
    );
    response
        .headers_mut()
        .insert(header::RETRY_AFTER, HeaderValue::from_static("5"));
    response
}

/// The client's address (axum-server hands it to every request).
pub fn peer(request_extensions: &axum::http::Extensions) -> IpAddr {
    request_extensions
        .get::<ConnectInfo<SocketAddr>>()
        .map(|c| c.0.ip())
        .unwrap_or(IpAddr::V4(std::net::Ipv4Addr::UNSPECIFIED))
}

/// Middleware: the request may read, or gets 401.
pub async fn require_read(
    axum::extract::State(shared): axum::extract::State<Arc<Shared>>,
    request: Request,
    next: Next,
) -> Response {
    match shared
        .auth
        .may_read(request.headers(), peer(request.extensions()))
    {
        Ok(true) => next.run(request).await,
        Ok(false) => unauthorized(),
        Err(Throttled) => throttled(),
    }
}

#[derive(Serialize)]
pub struct SessionInfo {
    pub version: &'static str,
    /// Everything but this and the login needs the token.
    pub reads_need_token: bool,
    /// An HTTP_TOKEN is configured: writes are possible with it.
    pub writes_possible: bool,
    /// This request carried the token.
    pub authenticated: bool,
    /// `/api/history` has a historian to read.
    pub historian: bool,
}

/// `GET /api/session`: what the page may do, before it asks for more.
pub async fn session(
    state: State,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
) -> Json<SessionInfo> {
    let auth = &state.0.auth;
    Json(SessionInfo {
        version: env!("CARGO_PKG_VERSION"),
        reads_need_token: auth.reads_need_token,
        writes_possible: auth.token.is_some(),
        authenticated: auth
            .presented(&headers, peer.ip())
            .is_ok_and(|p| p == Proof::Token),
        historian: state.0.history.is_some(),
    })
}

#[derive(Deserialize)]
pub struct Login {
    token: String,
}

/// `POST /api/login {"token": "..."}`: sets the page's cookie.
pub async fn login(
    state: State,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    Json(login): Json<Login>,
) -> Response {
    let auth = &state.0.auth;
    if auth.token.is_none() {
        return error(
            StatusCode::BAD_REQUEST,
            "no HTTP_TOKEN is configured: there is nothing to log in to",
        );
    }
    match auth.check_token(login.token.as_bytes(), peer.ip()) {
        Err(Throttled) => return throttled(),
        Ok(false) => {
            tokio::time::sleep(LOGIN_PENALTY).await;
            return error(StatusCode::UNAUTHORIZED, "wrong token");
        }
        Ok(true) => {}
    }
    let secure = if auth.secure { "; Secure" } else { "" };
    set_cookie(format!(
        "{COOKIE}={}; Path=/; HttpOnly; SameSite=Strict; Max-Age={}{secure}",
        auth.open_session(),
        SESSION_LIFE.as_secs()
    ))
}

/// `POST /api/logout`: ends the session and forgets the cookie (the origin
/// check keeps other sites' pages from forcing it).
pub async fn logout(state: State, headers: HeaderMap) -> Response {
    state.0.auth.close_session(&headers);
    set_cookie(format!(
        "{COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0"
    ))
}

fn set_cookie(value: String) -> Response {
    let mut response = StatusCode::NO_CONTENT.into_response();
    if let Ok(value) = HeaderValue::from_str(&value) {
        response.headers_mut().insert(header::SET_COOKIE, value);
    }
    response
}

/// The value of our cookie, if the request has it.
fn cookie(headers: &HeaderMap) -> Option<String> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .filter_map(|pair| pair.trim().split_once('='))
        .find(|(name, _)| *name == COOKIE)
        .map(|(_, value)| value.to_string())
}

/// Equality in time that depends on the lengths only.
fn same(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(header::HeaderName, &str)]) -> HeaderMap {
        let mut map = HeaderMap::new();
        for (name, value) in pairs {
            map.append(name.clone(), HeaderValue::from_str(value).unwrap());
        }
        map
    }

    const PEER: IpAddr = IpAddr::V4(std::net::Ipv4Addr::LOCALHOST);

    #[test]
    fn token_by_bearer_in_any_case_or_session() {
        let auth = Auth::new(Some("s3 cr;et".into()), true, false);
        assert!(!auth.may_read(&HeaderMap::new(), PEER).unwrap_or(true));
        for scheme in ["Bearer", "bearer", "BEARER"] {
            let value = format!("{scheme} s3 cr;et");
            assert!(matches!(
                auth.may_read(&headers(&[(header::AUTHORIZATION, &value)]), PEER),
                Ok(true)
            ));
        }
        let id = auth.open_session();
        let cookie = format!("a=b; {COOKIE}={id}");
        assert!(auth
            .may_write(&headers(&[(header::COOKIE, &cookie)]), PEER)
            .is_ok());
        auth.close_session(&headers(&[(header::COOKIE, &cookie)]));
        assert!(matches!(
            auth.may_write(&headers(&[(header::COOKIE, &cookie)]), PEER),
            Err(WriteRefusal::Unauthorized)
        ));
    }

    #[test]
    fn wrong_tokens_run_out_and_right_ones_are_refunded() {
        let auth = Auth::new(Some("t".into()), true, false);
        for _ in 0..20 {
            assert!(matches!(auth.check_token(b"t", PEER), Ok(true)));
        }
        let wrong = (0..20)
            .filter(|_| matches!(auth.check_token(b"x", PEER), Ok(false)))
            .count();
        assert_eq!(wrong, 10);
        assert!(
            auth.check_token(b"t", PEER).is_err(),
            "compared while throttled"
        );
    }

    #[test]
    fn loopback_reads_freely_and_nobody_writes_without_a_token() {
        let auth = Auth::new(None, false, false);
        assert!(matches!(auth.may_read(&HeaderMap::new(), PEER), Ok(true)));
        assert!(matches!(
            auth.may_write(&headers(&[(header::AUTHORIZATION, "Bearer ")]), PEER),
            Err(WriteRefusal::NoToken)
        ));
    }
}
