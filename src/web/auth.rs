//! Who may read and who may write.
//!
//! - Writing (a SET from the page or the API) always needs HTTP_TOKEN; with
//!   no token configured the web server writes nothing.
//! - Reading needs the token too when HTTP_BIND is not a loopback address
//!   (configuration refuses such an address without a token); on loopback
//!   anyone on the machine may look.
//!
//! The token comes as `Authorization: Bearer <token>` (scripts, Prometheus)
//! or as the cookie the page's login sets (`SameSite=Strict`, so another
//! site's page cannot write through a logged-in browser; `HttpOnly`, so no
//! script reads it). Comparisons take the same time whatever matches.

use std::sync::Arc;
use std::time::Duration;

use axum::extract::Request;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::{Deserialize, Serialize};

use super::api::error;
use super::{Shared, State};

const COOKIE: &str = "plccoms_token";

/// A failed login waits this long: guessing stays slow.
const LOGIN_PENALTY: Duration = Duration::from_millis(300);

pub struct Auth {
    token: Option<String>,
    reads_need_token: bool,
    /// Cookies get `Secure` over HTTPS.
    secure: bool,
}

/// Why a write is refused.
pub enum WriteRefusal {
    /// No HTTP_TOKEN configured: nobody writes through the web server.
    NoToken,
    /// The request does not carry the token.
    Unauthorized,
}

impl Auth {
    pub fn new(token: Option<String>, reads_need_token: bool, secure: bool) -> Auth {
        Auth {
            token,
            reads_need_token,
            secure,
        }
    }

    /// Whether the request carries the configured token.
    fn presented(&self, headers: &HeaderMap) -> bool {
        let Some(token) = &self.token else {
            return false;
        };
        let bearer = headers
            .get_all(header::AUTHORIZATION)
            .iter()
            .filter_map(|v| v.to_str().ok())
            .filter_map(|v| v.strip_prefix("Bearer "))
            .any(|given| same(given.trim().as_bytes(), token.as_bytes()));
        bearer || cookie(headers).is_some_and(|given| same(given.as_bytes(), hex(token).as_bytes()))
    }

    pub fn may_read(&self, headers: &HeaderMap) -> bool {
        !self.reads_need_token || self.presented(headers)
    }

    pub fn may_write(&self, headers: &HeaderMap) -> Result<(), WriteRefusal> {
        match &self.token {
            None => Err(WriteRefusal::NoToken),
            Some(_) if self.presented(headers) => Ok(()),
            Some(_) => Err(WriteRefusal::Unauthorized),
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

/// Middleware: the request may read, or gets 401.
pub async fn require_read(
    axum::extract::State(shared): axum::extract::State<Arc<Shared>>,
    request: Request,
    next: Next,
) -> Response {
    if shared.auth.may_read(request.headers()) {
        next.run(request).await
    } else {
        unauthorized()
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
pub async fn session(state: State, headers: HeaderMap) -> Json<SessionInfo> {
    let auth = &state.0.auth;
    Json(SessionInfo {
        version: env!("CARGO_PKG_VERSION"),
        reads_need_token: auth.reads_need_token,
        writes_possible: auth.token.is_some(),
        authenticated: auth.presented(&headers),
        historian: state.0.history.is_some(),
    })
}

#[derive(Deserialize)]
pub struct Login {
    token: String,
}

/// `POST /api/login {"token": "..."}`: sets the page's cookie.
pub async fn login(state: State, Json(login): Json<Login>) -> Response {
    let auth = &state.0.auth;
    let Some(token) = &auth.token else {
        return error(
            StatusCode::BAD_REQUEST,
            "no HTTP_TOKEN is configured: there is nothing to log in to",
        );
    };
    if !same(login.token.as_bytes(), token.as_bytes()) {
        tokio::time::sleep(LOGIN_PENALTY).await;
        return error(StatusCode::UNAUTHORIZED, "wrong token");
    }
    let secure = if auth.secure { "; Secure" } else { "" };
    set_cookie(format!(
        "{COOKIE}={}; Path=/; HttpOnly; SameSite=Strict{secure}",
        hex(token)
    ))
}

/// `POST /api/logout`: forgets the cookie.
pub async fn logout() -> Response {
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

/// The token as the cookie holds it: any byte of it survives a cookie.
fn hex(token: &str) -> String {
    token.bytes().map(|b| format!("{b:02x}")).collect()
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

    #[test]
    fn token_by_bearer_or_cookie() {
        let auth = Auth::new(Some("s3 cr;et".into()), true, false);
        assert!(!auth.may_read(&HeaderMap::new()));
        assert!(auth.may_read(&headers(&[(header::AUTHORIZATION, "Bearer s3 cr;et")])));
        assert!(!auth.may_read(&headers(&[(header::AUTHORIZATION, "Bearer s3 cr;eT")])));
        let cookie = format!("a=b; {COOKIE}={}", hex("s3 cr;et"));
        assert!(auth.may_read(&headers(&[(header::COOKIE, &cookie)])));
        assert!(auth
            .may_write(&headers(&[(header::COOKIE, &cookie)]))
            .is_ok());
        assert!(matches!(
            auth.may_write(&HeaderMap::new()),
            Err(WriteRefusal::Unauthorized)
        ));
    }

    #[test]
    fn loopback_reads_freely_and_nobody_writes_without_a_token() {
        let auth = Auth::new(None, false, false);
        assert!(auth.may_read(&HeaderMap::new()));
        assert!(matches!(
            auth.may_write(&headers(&[(header::AUTHORIZATION, "Bearer ")])),
            Err(WriteRefusal::NoToken)
        ));
    }
}
