//! Which names the page answers to, and which pages may post to it.
//!
//! A page of another site whose name is made to resolve to this server
//! (DNS rebinding) reaches it with its own name in `Host`: refused, so it
//! reads nothing, token or not. Answered: the address the page listens on
//! (any address when it listens on all), `localhost` on loopback, and the
//! names of HTTP_HOSTS. Requests that change something (POST) must come
//! from the page's own origin: a browser sends `Origin` and
//! `Sec-Fetch-Site` with them, scripts usually neither.

use std::net::IpAddr;
use std::sync::Arc;

use axum::extract::Request;
use axum::http::{header, HeaderMap, Method, StatusCode};
use axum::middleware::Next;
use axum::response::Response;

use super::api::error;
use super::Shared;

pub struct Hosts {
    bind: IpAddr,
    /// HTTP_HOSTS, lower case: `name` or `name:port`.
    names: Vec<String>,
}

impl Hosts {
    pub fn new(bind: IpAddr, names: Vec<String>) -> Hosts {
        Hosts { bind, names }
    }

    /// Whether `authority` (`Host` as sent: `name`, `name:port`,
    /// `[v6]:port`) names this server.
    pub fn allows(&self, authority: &str) -> bool {
        let authority = authority.trim().to_ascii_lowercase();
        if self.names.iter().any(|n| n == "*" || *n == authority) {
            return true;
        }
        let host = host_part(&authority);
        if self.names.iter().any(|n| n == host) {
            return true;
        }
        let ip_text = host.trim_start_matches('[').trim_end_matches(']');
        if let Ok(ip) = ip_text.parse::<IpAddr>() {
            // A browser reaches an address literal only at that address.
            return self.bind.is_unspecified() || ip == self.bind;
        }
        host == "localhost" && (self.bind.is_loopback() || self.bind.is_unspecified())
    }
}

/// `name` of `name:port`, `[v6]` of `[v6]:port`.
fn host_part(authority: &str) -> &str {
    if authority.starts_with('[') {
        return authority.split_inclusive(']').next().unwrap_or(authority);
    }
    match authority.rsplit_once(':') {
        Some((host, port)) if port.bytes().all(|b| b.is_ascii_digit()) => host,
        _ => authority,
    }
}

/// The authority the request was sent to: HTTP/2's `:authority`, else
/// `Host`.
fn authority(request: &Request) -> Option<String> {
    if let Some(authority) = request.uri().authority() {
        return Some(authority.as_str().to_string());
    }
    let mut hosts = request.headers().get_all(header::HOST).iter();
    let host = hosts.next()?.to_str().ok()?.to_string();
    // Two Host headers: which one a proxy used is anybody's guess.
    hosts.next().is_none().then_some(host)
}

/// Why a state-changing request is not the page's own, if it is not.
fn foreign_origin(headers: &HeaderMap, authority: &str) -> Option<String> {
    if let Some(site) = headers.get("sec-fetch-site") {
        let site = site.to_str().unwrap_or("");
        if site != "same-origin" && site != "none" {
            return Some(format!("Sec-Fetch-Site: {site}"));
        }
    }
    let origin = headers.get(header::ORIGIN)?;
    let text = origin.to_str().unwrap_or("");
    let origin_authority = text.split_once("://").map(|(_, rest)| rest);
    match origin_authority {
        Some(rest) if rest.eq_ignore_ascii_case(authority) => None,
        _ => Some(format!("Origin: {text}")),
    }
}

/// Middleware: the Host check for every request, the origin check for
/// those that change something.
pub async fn check(
    axum::extract::State(shared): axum::extract::State<Arc<Shared>>,
    request: Request,
    next: Next,
) -> Response {
    let Some(authority) = authority(&request) else {
        return error(
            StatusCode::BAD_REQUEST,
            "the request needs one Host header naming this server",
        );
    };
    if !shared.hosts.allows(&authority) {
        return error(
            StatusCode::MISDIRECTED_REQUEST,
            format!(
                "Host '{authority}' is not a name of this web page: \
                 add it to HTTP_HOSTS in the configuration's [*] section"
            ),
        );
    }
    let safe = matches!(
        *request.method(),
        Method::GET | Method::HEAD | Method::OPTIONS
    );
    if !safe {
        if let Some(why) = foreign_origin(request.headers(), &authority) {
            return error(
                StatusCode::FORBIDDEN,
                format!("only the page itself may post here, not another site's page ({why})"),
            );
        }
    }
    next.run(request).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_of_this_server_and_no_other() {
        let loopback = Hosts::new("127.0.0.1".parse().unwrap(), vec!["plc.example".into()]);
        for ok in [
            "127.0.0.1",
            "127.0.0.1:80",
            "LOCALHOST:5080",
            "plc.example:1",
        ] {
            assert!(loopback.allows(ok), "{ok}");
        }
        for refused in [
            "evil.example",
            "127.0.0.2:5080",
            "[::1]:5080",
            "localhost.evil",
            "",
        ] {
            assert!(!loopback.allows(refused), "{refused}");
        }
        let all = Hosts::new("::".parse().unwrap(), vec!["plc:8080".into()]);
        assert!(all.allows("[2001:db8::1]:5080") && all.allows("10.0.0.1"));
        assert!(all.allows("plc:8080") && !all.allows("plc:8081"));
        let lan = Hosts::new("10.0.0.1".parse().unwrap(), vec![]);
        assert!(lan.allows("10.0.0.1:5080") && !lan.allows("localhost"));
        assert!(Hosts::new("10.0.0.1".parse().unwrap(), vec!["*".into()]).allows("x"));
    }
}
