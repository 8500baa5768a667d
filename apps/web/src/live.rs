//! `GET /api/sections/{section}/live?vars=<masks>`: live values as
//! server-sent events, one `values` event per poll of the section that
//! changed something shown: a value, or a quality (a variable the stream
//! made the link poll turns `good` when first read, even if its value is
//! the one already shown).
//!
//! Each stream is a [`Subscription`](plccoms_core::changes::Subscription): while it
//! is open the link polls what it shows, and when the browser goes the
//! interest goes with it. A browser that reads slowly is not queued for:
//! the next event is made only when the connection takes it, from the
//! latest snapshot (`missed` counts the publishes it skipped). Memory per
//! stream is bounded by the variables it shows, which are capped.
//!
//! Event data (JSON):
//! `{"seq":n,"polled_ms":t|null,"online":b,"missed":n,"table_changed":b,
//!   "link":"lost"|"restored"|null,
//!   "values":[[name,value,quality,changed_ms,text],..]}`, `value` in the
//! user's terms (`Presented`, as `/values` has it) and `text` the same as
//! text. The first event holds every shown variable that has a value.
//! After `table_changed` or a `link` event the page reads `/values` again
//! for every quality.

use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use std::net::SocketAddr;

use axum::extract::{ConnectInfo, Path};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use plccoms_protocol::cp1250;
use serde::{Deserialize, Serialize};
use tokio_util::sync::CancellationToken;

use super::api::{error, find, parse_masks, presented, quality_of, Params};
use super::limits::{Permit, MAX_LIVE_STREAMS};
use super::metrics::{StreamGuard, WebMetrics};
use super::State;
use plccoms_core::changes::{ChangeBatch, LinkEvent, Subscription};
use plccoms_core::present::Presented;
use plccoms_core::section::Section;
use plccoms_core::vars::{VarId, VarTable};

/// Most variables one stream shows: a mask matching more is refused (the
/// link would poll all of them for one browser).
pub const MAX_LIVE: usize = 2000;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LiveQuery {
    vars: Option<String>,
}

pub async fn live(
    state: State,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    Path(name): Path<String>,
    Params(query): Params<LiveQuery>,
) -> Response {
    let section = match find(&state, &name) {
        Ok(section) => section,
        Err(refused) => return refused.into_response(),
    };
    let masks = parse_masks(query.vars.as_deref());
    let count = section.latest().table.matching(&masks).len();
    if count > MAX_LIVE {
        return error(
            StatusCode::BAD_REQUEST,
            format!(
                "the masks match {count} variables; at most {MAX_LIVE} are shown live: narrow them"
            ),
        );
    }
    let permit = match state.0.live_streams.acquire(peer.ip(), MAX_LIVE_STREAMS) {
        Ok(permit) => permit,
        Err(refused) => {
            let mut response = error(
                StatusCode::SERVICE_UNAVAILABLE,
                format!(
                    "{}: close another page or try later",
                    refused.describe(state.0.live_streams.what())
                ),
            );
            response
                .headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from_static("10"));
            return response;
        }
    };
    let stream = Stream {
        _permit: permit,
        // A batch per poll, so qualities that change without their values
        // are told too.
        subscription: section.subscribe(&masks).every_poll(),
        shown: Shown::default(),
        section,
        stop: state.0.stop.clone(),
        _guard: StreamGuard::new(state.0.web_metrics.clone()),
        metrics: state.0.web_metrics.clone(),
    };
    let events = futures::stream::unfold(stream, |mut stream| async move {
        let data = loop {
            let batch = tokio::select! {
                _ = stream.stop.cancelled() => return None,
                batch = stream.subscription.next() => batch?,
            };
            let wanted = stream.subscription.wanted().to_vec();
            if let Some(data) = encode(&batch, &stream.section, &wanted, &mut stream.shown) {
                break data;
            }
        };
        stream.metrics.events.inc();
        stream.metrics.event_bytes.add(data.len() as u64);
        Some((
            Ok::<_, Infallible>(Event::default().event("values").data(data)),
            stream,
        ))
    });
    Sse::new(events)
        .keep_alive(KeepAlive::new().interval(Duration::from_secs(15)))
        .into_response()
}

struct Stream {
    _permit: Permit,
    subscription: Subscription,
    section: Arc<Section>,
    shown: Shown,
    stop: CancellationToken,
    metrics: Arc<WebMetrics>,
    _guard: StreamGuard,
}

/// The quality last sent per variable (by id), for the table it was sent
/// of: looked up for every shown variable at every poll, so a plain slice.
#[derive(Default)]
pub struct Shown {
    table: Option<Arc<VarTable>>,
    quality: Vec<Option<&'static str>>,
}

#[derive(Serialize)]
struct Batch<'a> {
    seq: u64,
    polled_ms: Option<i64>,
    online: bool,
    missed: u64,
    table_changed: bool,
    link: Option<&'static str>,
    values: Vec<(
        std::borrow::Cow<'a, str>,
        Presented,
        &'static str,
        i64,
        String,
    )>,
}

/// The event data of a batch: the values that changed and those whose
/// quality did (`wanted`: the stream's variables); `None` when it has
/// nothing to tell.
pub fn encode(
    batch: &ChangeBatch,
    section: &Section,
    wanted: &[VarId],
    shown: &mut Shown,
) -> Option<String> {
    let snapshot = &batch.snapshot;
    if !shown
        .table
        .as_ref()
        .is_some_and(|t| Arc::ptr_eq(t, &snapshot.table))
    {
        shown.table = Some(snapshot.table.clone());
        shown.quality.clear();
        shown.quality.resize(snapshot.table.len(), None);
    }
    let now = tokio::time::Instant::now();
    let mut ids: Vec<VarId> = batch.changes.clone();
    for &id in wanted {
        if snapshot.slot(id).text().is_some()
            && shown.quality[id as usize] != Some(quality_of(snapshot, id, now))
        {
            ids.push(id);
        }
    }
    ids.sort_unstable();
    ids.dedup();
    let values: Vec<_> = ids
        .into_iter()
        .filter_map(|id| {
            let (value, text) = presented(section, snapshot, id)?;
            let quality = quality_of(snapshot, id, now);
            shown.quality[id as usize] = Some(quality);
            Some((
                cp1250::decode(&snapshot.table.var(id).name),
                value,
                quality,
                snapshot.slot(id).changed_ms,
                text,
            ))
        })
        .collect();
    if values.is_empty() && batch.link.is_none() && !batch.table_changed {
        return None;
    }
    let body = Batch {
        seq: snapshot.seq,
        polled_ms: snapshot.polled.map(|p| p.unix_ms),
        online: snapshot.online,
        missed: batch.missed,
        table_changed: batch.table_changed,
        link: batch.link.map(|event| match event {
            LinkEvent::Lost => "lost",
            LinkEvent::Restored => "restored",
        }),
        values,
    };
    serde_json::to_string(&body).ok()
}
