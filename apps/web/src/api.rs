//! `/api/...` JSON: sections (PLC state, identification, cycle time),
//! clients, variables, values, writes and the log. Names are the
//! protocol's (upper case, decoded from cp1250); values are in the user's
//! terms (`Presented`: numbers, booleans, ISO 8601 times), each with its
//! quality, unit and description; writes are refused in the user's words.

use std::sync::Arc;

use axum::extract::{FromRequestParts, Path, Query};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use plccoms_protocol::address::parse_direct;
use plccoms_protocol::answer::ErrorCode;
use plccoms_protocol::{cp1250, IecType};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use super::State;
use plccoms_core::changes::{Quality, Snapshot};
use plccoms_core::present::{self, Presented};
use plccoms_core::section::write::WriteRefusal;
use plccoms_core::section::Section;
use plccoms_core::vars::VarId;

/// Variables one request lists at most unless it asks for fewer.
const DEFAULT_LIMIT: usize = 1000;
/// The most one request lists: a page, never a whole table of 100,000
/// variables (`offset` goes on from there).
pub const MAX_LIMIT: usize = 5000;
/// The most sections one request of `/api/sections` lists when it asks
/// for a page (`limit`); without one it lists them all.
pub const MAX_SECTIONS_LIMIT: usize = 1000;

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

/// One line of the API's index.
#[derive(Serialize)]
pub struct Endpoint {
    pub path: &'static str,
    pub methods: &'static [&'static str],
    pub description: &'static str,
}

/// What `/api` lists: every endpoint, its methods, one line each.
pub const ENDPOINTS: &[Endpoint] = &[
    Endpoint {
        path: "/api/session",
        methods: &["GET"],
        description: "version; whether reading needs the token, writing is possible, this request carries the token, a historian records",
    },
    Endpoint {
        path: "/api/login",
        methods: &["POST"],
        description: "{\"token\": T}: a session cookie for the page",
    },
    Endpoint {
        path: "/api/logout",
        methods: &["POST"],
        description: "ends the page's session",
    },
    Endpoint {
        path: "/api/sections?filter=T&state=S&offset=N&limit=N",
        methods: &["GET"],
        description: "the sections (all, or the page asked for; X-Total-Count: how many match): link state, identification, poll cycle, clients, variables",
    },
    Endpoint {
        path: "/api/sections/{section}",
        methods: &["GET"],
        description: "one section, as in /api/sections",
    },
    Endpoint {
        path: "/api/sections/{section}/clients",
        methods: &["GET"],
        description: "the line protocol's clients: address, since, variables enabled, output queued",
    },
    Endpoint {
        path: "/api/sections/{section}/vars?mask=A*,B&offset=N&limit=N",
        methods: &["GET"],
        description: "variables: name, type, unit and description where known, writable",
    },
    Endpoint {
        path: "/api/sections/{section}/values?vars=A*,B&offset=N&limit=N",
        methods: &["GET"],
        description: "last known values in the user's terms, with text, unit, quality (good, not_polled, stale, link_lost) and changed_ms",
    },
    Endpoint {
        path: "/api/sections/{section}/live?vars=A*,B",
        methods: &["GET"],
        description: "server-sent events: values as they change, polled while the stream is open (2,000 variables at most)",
    },
    Endpoint {
        path: "/api/sections/{section}/set",
        methods: &["POST"],
        description: "{\"name\": N, \"value\": V} with the token: V a number, true/false or text (ISO 8601 for times); the value read back, or why not",
    },
    Endpoint {
        path: "/api/history?section=S&vars=A*,B&from=T&to=T&format=json|csv",
        methods: &["GET"],
        description: "what the historian recorded (503 when none records)",
    },
    Endpoint {
        path: "/api/log",
        methods: &["GET"],
        description: "the last warnings and errors, oldest first",
    },
    Endpoint {
        path: "/metrics",
        methods: &["GET"],
        description: "Prometheus text of every section and the web server",
    },
];

#[derive(Serialize)]
pub struct Index {
    pub version: &'static str,
    pub endpoints: &'static [Endpoint],
}

/// `GET /api`: the index of the API.
pub async fn index() -> Json<Index> {
    Json(Index {
        version: env!("CARGO_PKG_VERSION"),
        endpoints: ENDPOINTS,
    })
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

/// A query string deserialized as `T`, or a 400 saying which parameter
/// was wrong and why (axum's own rejection is plain text).
pub struct Params<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequestParts<S> for Params<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        match Query::<T>::from_request_parts(parts, state).await {
            Ok(Query(query)) => Ok(Params(query)),
            Err(rejection) => Err(ApiError::new(
                StatusCode::BAD_REQUEST,
                rejection.body_text(),
            )),
        }
    }
}

/// `limit` checked against `1..=max`: a clear 400 rather than a silent cap,
/// so a script learns it reads a page and goes on with `offset`.
pub fn checked_limit(limit: Option<usize>, default: usize, max: usize) -> Result<usize, ApiError> {
    match limit.unwrap_or(default) {
        0 => Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            format!("limit must be 1 to {max}"),
        )),
        n if n > max => Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            format!("limit {n} is over {max}, the most one page lists: read on with offset"),
        )),
        n => Ok(n),
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

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SectionsQuery {
    /// Part of the name or of the PLC's address, in any case.
    filter: Option<String>,
    /// Link state: `no_plc`, `connecting`, `online` or `lost`.
    state: Option<String>,
    offset: Option<usize>,
    limit: Option<usize>,
}

const LINK_STATES: [&str; 4] = ["no_plc", "connecting", "online", "lost"];

/// `GET /api/sections?filter=T&state=S&offset=N&limit=N`: the sections in
/// configuration order, those matching `filter` and `state`, from `offset`,
/// `limit` of them (all without one); `X-Total-Count` says how many match.
/// Only the page's sections are described, so a page of 1,000 sections
/// costs what its rows do.
pub async fn sections(
    state: State,
    Params(query): Params<SectionsQuery>,
) -> Result<Response, ApiError> {
    if let Some(wanted) = query.state.as_deref() {
        if !LINK_STATES.contains(&wanted) {
            return Err(ApiError::new(
                StatusCode::BAD_REQUEST,
                format!("state '{wanted}' is none of {}", LINK_STATES.join(", ")),
            ));
        }
    }
    let limit = match query.limit {
        Some(_) => checked_limit(query.limit, 0, MAX_SECTIONS_LIMIT)?,
        None => usize::MAX,
    };
    let filter = query.filter.as_deref().map(str::to_lowercase);
    let list = state.0.sections.current();
    let matching: Vec<&Arc<Section>> = list
        .iter()
        .filter(|s| {
            if filter.is_none() && query.state.is_none() {
                return true;
            }
            let st = s.state();
            query
                .state
                .as_deref()
                .is_none_or(|wanted| st.link.state.as_str() == wanted)
                && filter.as_deref().is_none_or(|f| {
                    s.name().to_lowercase().contains(f)
                        || st.link.describe.to_lowercase().contains(f)
                })
        })
        .collect();
    let page: Vec<SectionView> = matching
        .iter()
        .skip(query.offset.unwrap_or(0))
        .take(limit)
        .map(|s| section_view(s))
        .collect();
    let mut response = Json(page).into_response();
    response
        .headers_mut()
        .insert("x-total-count", HeaderValue::from(matching.len()));
    Ok(response)
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
#[serde(deny_unknown_fields)]
pub struct VarsQuery {
    /// Comma-separated masks (`vars` is the same).
    mask: Option<String>,
    vars: Option<String>,
    /// The first matching variable listed (0: from the start).
    offset: Option<usize>,
    limit: Option<usize>,
}

impl VarsQuery {
    fn masks(&self) -> Vec<Vec<u8>> {
        parse_masks(self.mask.as_deref().or(self.vars.as_deref()))
    }

    /// The named section's latest snapshot, its variables the masks match,
    /// and the page of them asked for.
    fn select(&self, state: &State, name: &str) -> Result<Selection, ApiError> {
        let limit = checked_limit(self.limit, DEFAULT_LIMIT, MAX_LIMIT)?;
        let snapshot = find(state, name)?.latest();
        let ids = snapshot.table.matching(&self.masks());
        let offset = self.offset.unwrap_or(0);
        let end = offset.saturating_add(limit).min(ids.len());
        Ok(Selection {
            snapshot,
            total: ids.len(),
            offset,
            next_offset: (end < ids.len()).then_some(end),
            page: ids.get(offset..end).unwrap_or_default().to_vec(),
        })
    }
}

/// A page of the variables a request's masks match.
struct Selection {
    snapshot: Arc<Snapshot>,
    total: usize,
    offset: usize,
    next_offset: Option<usize>,
    page: Vec<VarId>,
}

/// What the API tells of a variable besides its value: its type, unit and
/// description (from a tag file), and whether a write could succeed.
#[derive(Serialize)]
pub struct VarFacts {
    #[serde(rename = "type")]
    pub ty: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unit: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
    /// The page offers a Set box only where this is true.
    pub writable: bool,
}

/// A system variable (`__PLC_RUN`): the PLC's or the server's own state.
pub fn is_system(name: &[u8]) -> bool {
    name.starts_with(b"__")
}

/// Whether a write to `var` could succeed: the section is not READ_ONLY,
/// the tag file does not mark it read-only, and it is not a system
/// variable.
pub fn may_be_written(section: &Section, var: &plccoms_core::vars::Var) -> bool {
    !section.read_only() && var.writable && !is_system(&var.name)
}

pub fn var_facts(section: &Section, snapshot: &Snapshot, id: VarId) -> VarFacts {
    let var = snapshot.table.var(id);
    let said = |text: &str| (!text.is_empty()).then(|| text.to_string());
    VarFacts {
        ty: var.ty.to_string(),
        unit: var.info.as_ref().and_then(|i| said(&i.unit)),
        description: var.info.as_ref().and_then(|i| said(&i.description)),
        writable: may_be_written(section, var),
    }
}

#[derive(Serialize)]
pub struct VarView {
    pub name: String,
    #[serde(flatten)]
    pub facts: VarFacts,
}

#[derive(Serialize)]
pub struct VarList {
    /// Variables matching, of which `vars` lists `limit` from `offset`.
    pub total: usize,
    pub offset: usize,
    /// Where the next page starts; `null` on the last.
    pub next_offset: Option<usize>,
    pub vars: Vec<VarView>,
}

/// `GET /api/sections/{section}/vars?mask=A*,B&offset=N&limit=N`: names,
/// types, units, descriptions and whether they may be written, a page at a
/// time.
pub async fn vars(
    state: State,
    Path(name): Path<String>,
    Params(query): Params<VarsQuery>,
) -> Result<Json<VarList>, ApiError> {
    let section = find(&state, &name)?;
    let selected = query.select(&state, &name)?;
    let snapshot = &selected.snapshot;
    let vars = selected
        .page
        .iter()
        .map(|&id| VarView {
            name: cp1250::decode(&snapshot.table.var(id).name).into_owned(),
            facts: var_facts(&section, snapshot, id),
        })
        .collect();
    Ok(Json(VarList {
        total: selected.total,
        offset: selected.offset,
        next_offset: selected.next_offset,
        vars,
    }))
}

/// How far a shown value can be trusted, in four words: `good` (read by
/// the last poll), `not_polled` (no client or subscriber enabled it, so
/// nobody reads it: the value is whatever was read last, if ever),
/// `stale` (polled, but the last poll did not read it, or that poll is
/// older than a GET would serve, or the device marked it uncertain) and
/// `link_lost`.
pub fn quality_of(snapshot: &Snapshot, id: VarId, now: tokio::time::Instant) -> &'static str {
    if !snapshot.online {
        return Quality::LinkLost.as_str();
    }
    if !snapshot.table.is_fixed(id) && !snapshot.interest.is_wanted(id) {
        return "not_polled";
    }
    snapshot.quality_at(id, now).as_str()
}

/// The value of `id` in the user's terms (JSON: numbers, booleans, ISO 8601
/// times), and as text in the same form (exact where a JSON reader's
/// numbers are not: 64-bit integers).
pub fn presented(section: &Section, snapshot: &Snapshot, id: VarId) -> Option<(Presented, String)> {
    let text = snapshot.slot(id).text()?;
    let value = Presented::of(snapshot.table.var(id).ty, text, section.format());
    let text = value.text();
    Some((value, text))
}

#[derive(Serialize)]
pub struct ValueView {
    pub name: String,
    #[serde(flatten)]
    pub facts: VarFacts,
    /// In the user's terms (`Presented`); `null` until first read.
    pub value: Option<Presented>,
    /// The value as text, in the same form.
    pub text: Option<String>,
    /// `good`, `not_polled`, `stale` or `link_lost` ([`quality_of`]).
    pub quality: &'static str,
    /// UTC milliseconds of the poll that read the value as it is.
    pub changed_ms: Option<i64>,
}

#[derive(Serialize)]
pub struct ValueList {
    pub total: usize,
    pub offset: usize,
    pub next_offset: Option<usize>,
    /// The link answered the last poll.
    pub online: bool,
    pub polled_ms: Option<i64>,
    pub values: Vec<ValueView>,
}

/// `now`: the quality is the one GET would act on at that instant.
pub fn value_view(
    section: &Section,
    snapshot: &Snapshot,
    id: VarId,
    now: tokio::time::Instant,
) -> ValueView {
    let slot = snapshot.slot(id);
    let (value, text) = presented(section, snapshot, id).unzip();
    ValueView {
        name: cp1250::decode(&snapshot.table.var(id).name).into_owned(),
        facts: var_facts(section, snapshot, id),
        value,
        text,
        quality: quality_of(snapshot, id, now),
        changed_ms: slot.text().map(|_| slot.changed_ms),
    }
}

/// `GET /api/sections/{section}/values?vars=A*,B&offset=N&limit=N`: the
/// last known values with their quality, a page at a time. This request
/// does not poll anything: variables nobody polls are `not_polled`; the
/// live stream polls what it shows.
pub async fn values(
    state: State,
    Path(name): Path<String>,
    Params(query): Params<VarsQuery>,
) -> Result<Json<ValueList>, ApiError> {
    let section = find(&state, &name)?;
    let selected = query.select(&state, &name)?;
    let snapshot = &selected.snapshot;
    let now = tokio::time::Instant::now();
    let values = selected
        .page
        .iter()
        .map(|&id| value_view(&section, snapshot, id, now))
        .collect();
    Ok(Json(ValueList {
        total: selected.total,
        offset: selected.offset,
        next_offset: selected.next_offset,
        online: snapshot.online,
        polled_ms: snapshot.polled.map(|p| p.unix_ms),
        values,
    }))
}

#[derive(Deserialize)]
pub struct Write {
    name: String,
    /// A number, true/false, or text (ISO 8601 for the time types).
    value: serde_json::Value,
}

#[derive(Serialize)]
pub struct Written {
    pub name: String,
    /// The value read back from the PLC, in the user's terms.
    pub value: Presented,
    pub text: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unit: Option<String>,
}

/// A write refused: why, in the user's words, and as a word for scripts.
#[derive(Serialize)]
struct WriteFailed {
    error: String,
    /// `read_only`, `system_variable`, `unknown_variable`, `bad_address`,
    /// `bad_value`, `unreachable`, `failed`, `timed_out`, `refused`.
    reason: &'static str,
}

fn write_failed(status: StatusCode, reason: &'static str, error: String) -> Response {
    (status, Json(WriteFailed { error, reason })).into_response()
}

/// The protocol text of a write of `value` to a variable of type `ty`
/// (`None`: no such variable; the write path says so).
fn write_text(
    ty: Option<IecType>,
    value: &serde_json::Value,
    section: &Section,
) -> Result<Vec<u8>, String> {
    use serde_json::Value as Json;
    match (value, ty) {
        (Json::String(text), Some(ty)) => {
            present::protocol_text(ty, text.as_bytes(), section.format())
                .map(std::borrow::Cow::into_owned)
                .map_err(|expected| format!("'{text}': {expected}"))
        }
        (Json::String(text), None) => Ok(cp1250::encode(text).into_owned()),
        (Json::Number(_), Some(ty @ (IecType::Date | IecType::Dt))) => Err(format!(
            "a {ty} is written as ISO 8601 text (2026-11-25T10:15:00Z), not as a number"
        )),
        (Json::Number(n), _) => Ok(n.to_string().into_bytes()),
        (Json::Bool(b), Some(IecType::String(_))) => Ok(b.to_string().into_bytes()),
        (Json::Bool(b), _) => Ok(if *b { b"1".to_vec() } else { b"0".to_vec() }),
        _ => Err("the value is a number, true or false, or text".into()),
    }
}

/// A refusal of the write path in the user's words.
fn refusal_response(refusal: &WriteRefusal, section: &Section, name: &str) -> Response {
    let (status, reason, message) = match refusal {
        WriteRefusal::ReadOnly if section.read_only() => (
            StatusCode::FORBIDDEN,
            "read_only",
            format!(
                "the section is READ_ONLY: nothing in {} is written",
                section.name()
            ),
        ),
        WriteRefusal::ReadOnly => (
            StatusCode::FORBIDDEN,
            "read_only",
            format!("{name} is read-only: the tag file marks it ro"),
        ),
        WriteRefusal::UnknownVariable => (
            StatusCode::BAD_REQUEST,
            "unknown_variable",
            format!("no variable named {name} in {}", section.name()),
        ),
        WriteRefusal::BadAddress => (
            StatusCode::BAD_REQUEST,
            "bad_address",
            format!("{name} is not an address this server understands"),
        ),
        WriteRefusal::BadValue(why) => (
            StatusCode::BAD_REQUEST,
            "bad_value",
            format!("not written: {why}"),
        ),
        WriteRefusal::Unreachable => (
            StatusCode::BAD_GATEWAY,
            "unreachable",
            "not written: there is no link to the PLC".to_string(),
        ),
        WriteRefusal::Failed => (
            StatusCode::BAD_GATEWAY,
            "failed",
            "the link to the PLC failed during the write: it may not have been applied".to_string(),
        ),
        WriteRefusal::TimedOut => (
            StatusCode::BAD_GATEWAY,
            "timed_out",
            "not written: the write waited too long to be sent (EPSTOUT)".to_string(),
        ),
        WriteRefusal::Refused { refusal: why, .. } => {
            // The device refusing a value or an address is the request's
            // fault, as the code it answers says.
            let status = match refusal.code() {
                ErrorCode::WrongValue | ErrorCode::MemSet => StatusCode::BAD_REQUEST,
                _ => StatusCode::BAD_GATEWAY,
            };
            (
                status,
                "refused",
                format!("the PLC refused the write of {name}: {why}"),
            )
        }
    };
    write_failed(status, reason, message)
}

/// `POST /api/sections/{section}/set {"name": "...", "value": V}`: a write
/// through the one write path (`Section::write`), V a number, true/false or
/// text (ISO 8601 for DATE, DT, TOD and TIME), confirmed with the value
/// read back, or refused saying why. Needs the token.
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
    let var = cp1250::encode(&write.name).into_owned();
    let shown = cp1250::decode(&cp1250::to_upper(&var)).into_owned();
    if is_system(&var) {
        return write_failed(
            StatusCode::FORBIDDEN,
            "system_variable",
            format!("{shown} is a system variable: the PLC's own state is not written from here"),
        );
    }
    let snapshot = section.latest();
    let ty = if var.first() == Some(&b'%') {
        parse_direct(&var).map(|a| a.ty)
    } else {
        snapshot
            .table
            .lookup(&var)
            .map(|id| snapshot.table.var(id).ty)
    };
    let text = match write_text(ty, &write.value, &section) {
        Ok(text) => text,
        Err(why) => {
            return write_failed(
                StatusCode::BAD_REQUEST,
                "bad_value",
                format!("not written: {why}"),
            )
        }
    };
    match section.write(&var, &text).await {
        Ok(written) => {
            let unit = written.var.as_ref().and_then(|(table, id)| {
                let info = table.var(*id).info.as_ref()?;
                (!info.unit.is_empty()).then(|| info.unit.clone())
            });
            let ty = written
                .var
                .as_ref()
                .map(|(table, id)| table.var(*id).ty)
                .or(ty)
                .unwrap_or(IecType::Lreal);
            let value = Presented::of(ty, &written.text, section.format());
            Json(Written {
                name: cp1250::decode(&written.name).into_owned(),
                text: value.text(),
                value,
                unit,
            })
            .into_response()
        }
        Err(refusal) => refusal_response(&refusal, &section, &shown),
    }
}

/// `GET /api/log`: the last warnings and errors, oldest first.
pub async fn log() -> Json<Vec<plccoms_core::logring::LogEntry>> {
    Json(plccoms_core::logring::global().entries())
}
