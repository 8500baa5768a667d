//! `/api/...` JSON: sections (PLC state, identification, cycle time),
//! clients, variables, values, writes and the log. Names and values are the
//! protocol's (upper-case names; values printed as `DIFF:` lines print
//! them), decoded from cp1250; every value comes with its quality.

use std::sync::Arc;

use axum::extract::{Path, Query};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use plccoms_protocol::answer::ErrorCode;
use plccoms_protocol::cp1250;
use serde::{Deserialize, Serialize};

use super::State;
use plccoms_core::changes::Snapshot;
use plccoms_core::section::write::WriteRefusal;
use plccoms_core::section::Section;
use plccoms_core::vars::VarId;

/// Variables one request lists at most unless it asks for fewer.
const DEFAULT_LIMIT: usize = 1000;
/// The most any request lists.
const MAX_LIMIT: usize = 100_000;

/// `{"error": message}` with `status`.
pub fn error(status: StatusCode, message: impl Into<String>) -> Response {
    #[derive(Serialize)]
    struct Body {
        error: String,
    }
    (
        status,
        Json(Body {
            error: message.into(),
        }),
    )
        .into_response()
}

pub async fn not_found() -> Response {
    error(StatusCode::NOT_FOUND, "no such page or API")
}

/// A refusal, answered as [`error`].
pub struct ApiError {
    status: StatusCode,
    message: String,
}

impl ApiError {
    pub fn new(status: StatusCode, message: impl Into<String>) -> ApiError {
        ApiError {
            status,
            message: message.into(),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        error(self.status, self.message)
    }
}

/// The section named in the path, or 404.
pub fn find(state: &State, name: &str) -> Result<Arc<Section>, ApiError> {
    state
        .0
        .section(name)
        .cloned()
        .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, format!("no section named '{name}'")))
}

#[derive(Serialize)]
pub struct SectionView {
    pub name: String,
    /// The clients' TCP port.
    pub port: u16,
    pub read_only: bool,
    pub link: LinkView,
    pub poll: PollView,
    pub clients: usize,
    pub variables: usize,
    pub pubfile_fixed: String,
    pub pubfile_user: Option<String>,
}

#[derive(Serialize)]
pub struct LinkView {
    /// `no_plc`, `connecting`, `online` or `lost`.
    pub state: &'static str,
    /// Where the PLC is.
    pub plc: String,
    /// The PLC's identification, once connected.
    pub ident: Option<String>,
    pub source_address: Option<u8>,
    /// UTC milliseconds of the last change of `state`.
    pub since_ms: i64,
}

#[derive(Serialize)]
pub struct PollView {
    /// COMM_LOOP_DELAY.
    pub period_ms: u64,
    /// Poll cycles so far, and their total duration: the page takes the
    /// recent cycle time from two readings.
    pub cycles: u64,
    pub cycle_seconds_sum: f64,
    pub overruns: u64,
    /// UTC milliseconds of the last completed poll, if any.
    pub last_poll_ms: Option<i64>,
}

fn section_view(section: &Section) -> SectionView {
    let state = section.state();
    let snapshot = section.latest();
    let metrics = section.metrics();
    SectionView {
        name: section.name().to_string(),
        port: state.config.server_port,
        read_only: state.config.read_only,
        link: LinkView {
            state: state.link.state.as_str(),
            plc: state.link.describe.clone(),
            ident: state.link.ident.clone(),
            source_address: state.link.source_address,
            since_ms: state.link.since_ms,
        },
        poll: PollView {
            period_ms: section.global().comm_loop_delay.as_millis() as u64,
            cycles: metrics.poll_cycle.count(),
            cycle_seconds_sum: metrics.poll_cycle.sum().as_secs_f64(),
            overruns: metrics.overruns.get(),
            last_poll_ms: snapshot.polled.map(|p| p.unix_ms),
        },
        clients: section.clients().len(),
        variables: snapshot.table.len(),
        pubfile_fixed: snapshot.table.fixed_file.clone(),
        pubfile_user: snapshot.table.user_file.clone(),
    }
}

/// `GET /api/sections`
pub async fn sections(state: State) -> Json<Vec<SectionView>> {
    Json(state.0.sections.iter().map(|s| section_view(s)).collect())
}

/// `GET /api/sections/{section}`
pub async fn section(
    state: State,
    Path(name): Path<String>,
) -> Result<Json<SectionView>, ApiError> {
    Ok(Json(section_view(&*find(&state, &name)?)))
}

#[derive(Serialize)]
pub struct ClientView {
    pub id: u64,
    pub address: String,
    /// Local time of connection, `yyyy-mm-dd hh:mm:ss`.
    pub connected: String,
    pub connected_ms: i64,
    /// Variables enabled, the fixed ones included.
    pub enabled: u64,
    /// Output queued for the client, in bytes.
    pub queued_bytes: u64,
}

/// `GET /api/sections/{section}/clients`
pub async fn clients(
    state: State,
    Path(name): Path<String>,
) -> Result<Json<Vec<ClientView>>, ApiError> {
    let section = find(&state, &name)?;
    let list: Vec<ClientView> = section
        .clients()
        .into_iter()
        .map(|c| ClientView {
            id: c.id,
            address: c.peer.to_string(),
            connected: c.connected,
            connected_ms: c.connected_ms,
            enabled: c.stats.enabled.get(),
            queued_bytes: c.stats.queued.get(),
        })
        .collect();
    Ok(Json(list))
}

/// Masks as a comma-separated list (`SIN*,counter`); empty: every variable.
pub fn parse_masks(text: Option<&str>) -> Vec<Vec<u8>> {
    let masks: Vec<Vec<u8>> = text
        .unwrap_or("")
        .split(',')
        .map(str::trim)
        .filter(|m| !m.is_empty())
        .map(|m| cp1250::encode(m).into_owned())
        .collect();
    if masks.is_empty() {
        vec![b"*".to_vec()]
    } else {
        masks
    }
}

#[derive(Deserialize)]
pub struct VarsQuery {
    /// Comma-separated masks (`vars` is the same).
    mask: Option<String>,
    vars: Option<String>,
    limit: Option<usize>,
}

impl VarsQuery {
    fn masks(&self) -> Vec<Vec<u8>> {
        parse_masks(self.mask.as_deref().or(self.vars.as_deref()))
    }

    fn limit(&self) -> usize {
        self.limit.unwrap_or(DEFAULT_LIMIT).min(MAX_LIMIT)
    }

    /// The named section's latest snapshot and its variables the masks
    /// match.
    fn select(&self, state: &State, name: &str) -> Result<(Arc<Snapshot>, Vec<VarId>), ApiError> {
        let snapshot = find(state, name)?.latest();
        let ids = snapshot.table.matching(&self.masks());
        Ok((snapshot, ids))
    }
}

#[derive(Serialize)]
pub struct VarView {
    pub name: String,
    #[serde(rename = "type")]
    pub ty: String,
}

#[derive(Serialize)]
pub struct VarList {
    /// Variables matching, of which `vars` lists the first `limit`.
    pub total: usize,
    pub vars: Vec<VarView>,
}

/// `GET /api/sections/{section}/vars?mask=A*,B&limit=N`: names and types.
pub async fn vars(
    state: State,
    Path(name): Path<String>,
    Query(query): Query<VarsQuery>,
) -> Result<Json<VarList>, ApiError> {
    let (snapshot, ids) = query.select(&state, &name)?;
    let vars = ids
        .iter()
        .take(query.limit())
        .map(|&id| {
            let var = snapshot.table.var(id);
            VarView {
                name: cp1250::decode(&var.name).into_owned(),
                ty: var.ty.to_string(),
            }
        })
        .collect();
    Ok(Json(VarList {
        total: ids.len(),
        vars,
    }))
}

#[derive(Serialize)]
pub struct ValueView {
    pub name: String,
    #[serde(rename = "type")]
    pub ty: String,
    /// As the protocol prints it; `null` until first read.
    pub value: Option<String>,
    /// `good`, `stale` or `link_lost`.
    pub quality: &'static str,
    /// UTC milliseconds of the poll that read the value as it is.
    pub changed_ms: Option<i64>,
}

#[derive(Serialize)]
pub struct ValueList {
    pub total: usize,
    /// The link answered the last poll.
    pub online: bool,
    pub polled_ms: Option<i64>,
    pub values: Vec<ValueView>,
}

/// `now`: the quality is the one GET would act on at that instant.
pub fn value_view(snapshot: &Snapshot, id: VarId, now: tokio::time::Instant) -> ValueView {
    let var = snapshot.table.var(id);
    let slot = snapshot.slot(id);
    ValueView {
        name: cp1250::decode(&var.name).into_owned(),
        ty: var.ty.to_string(),
        value: slot.text().map(|t| cp1250::decode(t).into_owned()),
        quality: snapshot.quality_at(id, now).as_str(),
        changed_ms: slot.text().map(|_| slot.changed_ms),
    }
}

/// `GET /api/sections/{section}/values?vars=A*,B&limit=N`: the last known
/// values with their quality. Variables nobody polls are `stale` (or have
/// no value yet): the live stream polls what it shows.
pub async fn values(
    state: State,
    Path(name): Path<String>,
    Query(query): Query<VarsQuery>,
) -> Result<Json<ValueList>, ApiError> {
    let (snapshot, ids) = query.select(&state, &name)?;
    let now = tokio::time::Instant::now();
    let values = ids
        .iter()
        .take(query.limit())
        .map(|&id| value_view(&snapshot, id, now))
        .collect();
    Ok(Json(ValueList {
        total: ids.len(),
        online: snapshot.online,
        polled_ms: snapshot.polled.map(|p| p.unix_ms),
        values,
    }))
}

#[derive(Deserialize)]
pub struct Write {
    name: String,
    value: String,
}

#[derive(Serialize)]
pub struct Written {
    pub name: String,
    /// The value read back from the PLC, as the protocol prints it.
    pub value: String,
}

#[derive(Serialize)]
struct WriteFailed {
    /// The error line a client's SET would have got.
    error: String,
    code: u16,
}

/// `POST /api/sections/{section}/set {"name": "...", "value": "..."}`: a
/// SET, with its validation and errors (READ_ONLY included), confirmed with
/// the value read back. Needs the token.
pub async fn set(
    state: State,
    axum::extract::ConnectInfo(peer): axum::extract::ConnectInfo<std::net::SocketAddr>,
    Path(name): Path<String>,
    headers: HeaderMap,
    Json(write): Json<Write>,
) -> Response {
    if let Err(refusal) = state.0.auth.may_write(&headers, peer.ip()) {
        return refusal.response();
    }
    let section = match find(&state, &name) {
        Ok(section) => section,
        Err(refused) => return refused.into_response(),
    };
    let var = cp1250::encode(&write.name);
    let value = cp1250::encode(&write.value);
    match section.write(&var, &value).await {
        Ok(written) => Json(Written {
            name: cp1250::decode(&written.name).into_owned(),
            value: cp1250::decode(&written.text).into_owned(),
        })
        .into_response(),
        Err(refusal) => {
            let status = match refusal {
                WriteRefusal::ReadOnly => StatusCode::FORBIDDEN,
                WriteRefusal::UnknownVariable
                | WriteRefusal::BadValue(_)
                | WriteRefusal::BadAddress => StatusCode::BAD_REQUEST,
                // The device refusing a value or an address is the
                // request's fault, as the code it answers says.
                WriteRefusal::Refused { .. } => match refusal.code() {
                    ErrorCode::WrongValue | ErrorCode::MemSet => StatusCode::BAD_REQUEST,
                    _ => StatusCode::BAD_GATEWAY,
                },
                WriteRefusal::Unreachable | WriteRefusal::Failed | WriteRefusal::TimedOut => {
                    StatusCode::BAD_GATEWAY
                }
            };
            (
                status,
                Json(WriteFailed {
                    code: refusal.code().code(),
                    error: refusal.line(&var, &value),
                }),
            )
                .into_response()
        }
    }
}

/// `GET /api/log`: the last warnings and errors, oldest first.
pub async fn log() -> Json<Vec<plccoms_core::logring::LogEntry>> {
    Json(plccoms_core::logring::global().entries())
}
