//! `GET /metrics`: the Prometheus text of every section and source, and the
//! web server's own figures (a [`Source`] like the historian's).

use std::sync::Arc;

use axum::extract::Query;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};

use super::api::error;
use super::State;
use plccoms_core::metrics::{header as family, Counter, Gauge, Source};

/// The text format's content type (version 0.0.4).
const CONTENT_TYPE: &str = "text/plain; version=0.0.4; charset=utf-8";

/// `GET /metrics`: everything; `?section=A&section=B` (or `section=A,B`):
/// only those sections' families, for scraping 1,000 devices in parts. A
/// name no section has answers 404 (a removed section's scrape fails
/// rather than silently reporting nothing); another parameter answers 400.
pub async fn metrics(state: State, Query(params): Query<Vec<(String, String)>>) -> Response {
    let registry = &state.0.metrics;
    let mut wanted: Vec<&str> = Vec::new();
    for (key, value) in &params {
        if key != "section" {
            return error(
                StatusCode::BAD_REQUEST,
                format!("unknown parameter '{key}': /metrics takes section=NAME"),
            );
        }
        wanted.extend(value.split(',').map(str::trim).filter(|n| !n.is_empty()));
    }
    let text = if params.is_empty() {
        registry.render()
    } else {
        if let Some(unknown) = wanted.iter().find(|n| !registry.has_section(n)) {
            return error(
                StatusCode::NOT_FOUND,
                format!("no section named '{unknown}'"),
            );
        }
        if wanted.is_empty() {
            return error(StatusCode::BAD_REQUEST, "section= names no section");
        }
        registry.render_sections(&|name| wanted.contains(&name))
    };
    ([(header::CONTENT_TYPE, CONTENT_TYPE)], text).into_response()
}

/// The web server's figures.
#[derive(Debug, Default)]
pub struct WebMetrics {
    /// Live-value streams open now.
    pub streams: Gauge,
    pub events: Counter,
    pub event_bytes: Counter,
}

impl Source for WebMetrics {
    fn render(&self, out: &mut String) {
        use std::fmt::Write as _;
        family(
            out,
            "plccoms_web_live_streams",
            "gauge",
            "Live-value streams (browsers) open on the web page.",
        );
        let _ = writeln!(out, "plccoms_web_live_streams {}", self.streams.get());
        family(
            out,
            "plccoms_web_live_events_total",
            "counter",
            "Live-value events sent to browsers.",
        );
        let _ = writeln!(out, "plccoms_web_live_events_total {}", self.events.get());
        family(
            out,
            "plccoms_web_live_event_bytes_total",
            "counter",
            "Bytes of live-value event data sent to browsers.",
        );
        let _ = writeln!(
            out,
            "plccoms_web_live_event_bytes_total {}",
            self.event_bytes.get()
        );
    }
}

/// Counts a stream as open for as long as it lives.
pub struct StreamGuard(Arc<WebMetrics>);

impl StreamGuard {
    pub fn new(metrics: Arc<WebMetrics>) -> StreamGuard {
        metrics.streams.add(1);
        StreamGuard(metrics)
    }
}

impl Drop for StreamGuard {
    fn drop(&mut self) {
        self.0.streams.sub(1);
    }
}
