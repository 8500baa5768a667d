//! Starting a section: its change stream, its link (on the links' pool or
//! a thread of its own), and the [`Section`] every app serves. Which apps
//! serve it (a telnet port, MQTT, the web page) is the binary's choice.

use std::io;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use tokio_util::sync::CancellationToken;
use tracing::warn;

use super::Section;
use crate::changes::Publisher;
use crate::config::{Global, Section as SectionConfig};
use crate::driver::{Drivers, PlcBackend};
use crate::link::files::FileSettings;
use crate::link::{self, Link, LinkSetup, Tables};
use crate::metrics::SectionMetrics;
use crate::vars::VarTable;

/// What a section needs to run.
pub struct Setup {
    pub global: Arc<Global>,
    pub config: SectionConfig,
    pub table: VarTable,
    /// The section's backend; `None`: no PLC yet.
    pub backend: Option<Box<dyn PlcBackend>>,
    /// Where a new backend comes from when SETCONF changes the link.
    pub drivers: Drivers,
    /// The configuration file's folder, the root of the section's local
    /// files.
    pub config_dir: PathBuf,
    /// How to (re)load the section's public files (`None`: `table` stays).
    pub tables: Option<Tables>,
}

/// A section whose link is running. Dropping it stops the link.
pub struct Running {
    pub section: Arc<Section>,
    stop: CancellationToken,
    link: link::Running,
}

/// Starts the section's link at once, whatever the PLC does.
pub fn start(setup: Setup) -> io::Result<Running> {
    let Setup {
        global,
        config,
        table,
        backend,
        drivers,
        config_dir,
        tables,
    } = setup;
    let format = super::format_options(&global);
    let fresh_for = link::fresh_for(global.comm_loop_delay, config.epstout);
    let metrics = Arc::new(SectionMetrics::default());
    let (publisher, changes) = Publisher::new(Arc::new(table), format, fresh_for);
    let eol: &'static [u8] = if global.end_line_crlf { b"\r\n" } else { b"\n" };
    let publisher = publisher.with_diff_block(eol);
    let trace = crate::trace::FrameTrace::new(&config.name, config.trace);
    let placement = link::Placement::of(&config, global.comm_sched_pri);
    let (link, handle, state) = Link::new(LinkSetup {
        name: config.name.clone(),
        trace,
        backend,
        drivers,
        publisher,
        config,
        loop_delay: global.comm_loop_delay,
        files: FileSettings {
            cache_recs: global.ffile_maxrecs,
            cache_timeout: global.ffile_timeout,
            sync_var_enabled: global.sync_var_enabled,
        },
        tables,
        metrics: metrics.clone(),
    });
    let stop = link.stop_token();
    let link = link::spawn(link, placement)?;
    let section = Arc::new(Section::new(
        global,
        handle,
        changes.woken_by_relay(),
        state,
        metrics,
        config_dir,
    ));
    Ok(Running {
        section,
        stop,
        link,
    })
}

impl Running {
    /// Stops polling; the link's thread ends once the request to the PLC in
    /// flight, if any, is done.
    pub fn stop(&self) {
        self.stop.cancel();
    }

    /// Waits, at most `grace`, for the link's thread to finish what it is
    /// doing with the PLC after [`Running::stop`], so that nothing it logs
    /// comes after the server says it stopped.
    pub async fn wait(&self, grace: Duration) {
        let start = tokio::time::Instant::now();
        while !self.link.is_finished() {
            if start.elapsed() >= grace {
                warn!(section = %self.section.name, "the link's thread is still waiting for the PLC at shutdown");
                return;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        self.stop();
    }
}
