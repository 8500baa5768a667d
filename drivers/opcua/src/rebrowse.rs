//! Looking for the server's variables (`OPCUA_BROWSE` / `OPCUA_TAGS`) and
//! again every `OPCUA_REBROWSE`: the first list is built while connecting,
//! the later ones by a task of their own, so that the link's polls and SETs
//! never wait behind a browse of 100,000 nodes. The task browses on a
//! session of its own, opened for each rebrowse and closed after it:
//! servers (asyncua's, many PLCs') answer one session's requests one after
//! another, so a Browse on the link's session would still hold a Write up.
//! Where the server refuses a second session (its session limit), it
//! browses on the link's session. It hands a list that changed to the link
//! through a slot the link's next read takes. Its requests may take longer
//! than OPCUA_TIMEOUT ([`Limits::browse_timeout`]); a failed rebrowse
//! leaves the link's session and the list as they are.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use opcua::client::services::{Browse, BrowseNext, Read};
use opcua::client::{Session, UARequest};
use opcua::types::{
    BrowseDescription, BrowseResult, ByteString, DataValue, ReadValueId, TimestampsToReturn,
};
use tokio::task::JoinHandle;
use tracing::{info, warn};

use plccoms_core::driver::PlcError;
use plccoms_plc::opcua::nodeid::NodeRef;

use crate::browse::{self, Built, Known};
use crate::{connect_session, new_client, service_error, Carries, Limits, OpcuaConfig};

/// What to look for.
#[derive(Debug, Clone)]
pub(crate) struct Lister {
    pub section: String,
    /// OPCUA_TAGS, read again each time.
    pub tags: Option<PathBuf>,
    /// OPCUA_BROWSE's nodes (the Objects folder when none).
    pub starts: Vec<NodeRef>,
}

/// The list built by the task and not yet taken by the link.
pub(crate) type Slot = Arc<Mutex<Option<Built>>>;

/// Finds the variables and builds their list; `None` for the list where
/// the same nodes by the same names as `known` (its [`browse::Print`])
/// were found: their attributes are not read again (at 100,000 variables
/// that is 400,000 of them every OPCUA_REBROWSE), and the browse only
/// hashes what it finds. Unless `full`, such a look browses no variable
/// but those that had children (a structure's fields): at 100,000
/// variables, their folders, not 100,000 nodes. Where they differ, it
/// browses everything again keeping it (a change is rare; a list of
/// 100,000 held each OPCUA_REBROWSE was most of a rebrowse's memory).
pub(crate) async fn list(
    session: &Session,
    lister: &Lister,
    limits: &Limits,
    known: Option<&Known>,
    full: bool,
) -> Result<(Known, Option<Built>), PlcError> {
    let tags = || {
        lister
            .tags
            .as_ref()
            .map(|path| crate::read_tag_file(&lister.section, path))
    };
    let section = &lister.section;
    let starts = &lister.starts;
    let parents = known.filter(|_| !full).map(|k| &k.parents);
    let looked = browse::find(
        section,
        session,
        limits,
        tags(),
        starts,
        known.is_none(),
        parents,
    )
    .await?;
    if known.map(|k| k.print) == Some(looked.known.print) {
        return Ok((looked.known, None));
    }
    let looked = match looked.found {
        Some(_) => looked,
        None => browse::find(section, session, limits, tags(), starts, true, None).await?,
    };
    let found = looked.found.unwrap_or_default();
    let built = browse::build(section, session, limits, found).await?;
    Ok((looked.known, Some(built)))
}

/// A look takes at most one part in this many of the time: at 100,000
/// variables a full look browses every variable (for a structure's
/// fields) and costs seconds of both sides' CPU, more than a 10 s
/// OPCUA_REBROWSE should spend.
const REBROWSE_SHARE: u32 = 20;

/// Every this many looks, one browses every variable again, not only
/// those that had children: a variable that had none and has some now
/// (its type made a structure, its node id the same) is found by it. The
/// others cost a server its folders' Browse only (node-opcua's, at 10,000
/// variables and 50 SETs a second, stopped answering under the Browse of
/// every variable every 10 s).
const FULL_LOOK_EVERY: u32 = 10;

/// Every `every` (or [`REBROWSE_SHARE`] times the last look's time, if
/// longer): the list again, put in `slot` where it differs from the last
/// one built (`known`). Ends when aborted (with its session).
pub(crate) fn spawn(
    link: Arc<Session>,
    config: OpcuaConfig,
    lister: Lister,
    limits: Limits,
    every: Duration,
    known: Known,
    slot: Slot,
) -> JoinHandle<()> {
    tokio::spawn(async move {
        let mut known = known;
        let mut looks = 0u32;
        let mut failing = false;
        let mut client = None;
        let mut shared = false;
        let mut took = Duration::ZERO;
        loop {
            tokio::time::sleep(every.max(took.saturating_mul(REBROWSE_SHARE))).await;
            let started = std::time::Instant::now();
            looks = looks.wrapping_add(1);
            let full = looks.is_multiple_of(FULL_LOOK_EVERY);
            // The link's client settings (accepted already), but patient:
            // a keep-alive the server answers after a slow Browse must not
            // close this session.
            if client.is_none() {
                client = new_client(&config, limits.browse_timeout).ok();
            }
            let own = match client.as_mut() {
                Some(client) => connect_session(client, &config, Carries::Values).await,
                None => Err(PlcError::Protocol("no client".into())),
            };
            let listed = match own {
                Ok((session, event_loop)) => {
                    let event_loop = Aborted(event_loop);
                    shared = false;
                    let listed = list(&session, &lister, &limits, Some(&known), full).await;
                    let _ = tokio::time::timeout(config.timeout, session.disconnect()).await;
                    drop(event_loop);
                    listed
                }
                Err(e) => {
                    if !std::mem::replace(&mut shared, true) {
                        info!(section = %lister.section, "no session of its own to look for the server's variables again ({e}): on the link's session");
                    }
                    list(&link, &lister, &limits, Some(&known), full).await
                }
            };
            took = started.elapsed();
            crate::trim_heap();
            match listed {
                Ok((found, built)) => {
                    known = found;
                    if let Some(built) = built {
                        *slot.lock().unwrap_or_else(|e| e.into_inner()) = Some(built);
                    }
                    if std::mem::take(&mut failing) {
                        info!(section = %lister.section, "looking for the server's variables again works again");
                    }
                }
                // A Browse refused or slow: the list stays as it is and is
                // looked for again later; a lost session is the link's to
                // find (its own requests, the keep-alive). Logged once.
                Err(e) => {
                    if !std::mem::replace(&mut failing, true) {
                        warn!(section = %lister.section, "looking for the server's variables again failed: {e}; the variables stay as they are");
                    }
                }
            }
        }
    })
}

/// A Browse of the list's, waiting up to [`Limits::browse_timeout`].
pub(crate) async fn browse_nodes(
    session: &Session,
    limits: &Limits,
    nodes: Vec<BrowseDescription>,
    per_node: u32,
) -> Result<Vec<BrowseResult>, PlcError> {
    Browse::new(session)
        .nodes_to_browse(nodes)
        .max_references_per_node(per_node)
        .timeout(limits.browse_timeout)
        .send(session.channel())
        .await
        .map(|r| r.results.unwrap_or_default())
        .map_err(|e| service_error("Browse", e))
}

/// A BrowseNext of the list's, waiting up to [`Limits::browse_timeout`].
pub(crate) async fn browse_next(
    session: &Session,
    limits: &Limits,
    point: ByteString,
) -> Result<Vec<BrowseResult>, PlcError> {
    BrowseNext::new(session)
        .continuation_point(point)
        .timeout(limits.browse_timeout)
        .send(session.channel())
        .await
        .map(|r| r.results.unwrap_or_default())
        .map_err(|e| service_error("BrowseNext", e))
}

/// Gives continuation points back unused (BrowseNext releasing them):
/// servers keep only a few per session.
pub(crate) async fn release_points(
    session: &Session,
    limits: &Limits,
    points: Vec<ByteString>,
) -> Result<(), PlcError> {
    BrowseNext::new(session)
        .continuation_points(points)
        .release_continuation_points(true)
        .timeout(limits.browse_timeout)
        .send(session.channel())
        .await
        .map(|_| ())
        .map_err(|e| service_error("BrowseNext", e))
}

/// A Read of attributes for the list, waiting up to
/// [`Limits::browse_timeout`].
pub(crate) async fn read_attributes(
    session: &Session,
    limits: &Limits,
    ids: &[ReadValueId],
) -> Result<Vec<DataValue>, PlcError> {
    Read::new(session)
        .nodes_to_read(ids.to_vec())
        .timestamps_to_return(TimestampsToReturn::Neither)
        .timeout(limits.browse_timeout)
        .send(session.channel())
        .await
        .map(|r| r.results.unwrap_or_default())
        .map_err(|e| service_error("Read", e))
}

/// A session's event loop, ended when dropped (the task aborted too).
struct Aborted(JoinHandle<opcua::types::StatusCode>);

impl Drop for Aborted {
    fn drop(&mut self) {
        self.0.abort();
    }
}
