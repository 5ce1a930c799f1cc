//! The run manager: many concurrent runs, each driven by at most one task
//! ([`task`]) around the core's [`RunSession`].
//!
//! Per iteration the task (1) commits the record and the checkpoint (session
//! and device state) to the [`Store`] in one transaction, (2) updates the run's
//! summary and its ring of recent summaries ([`RECENT_SUMMARIES`]), (3)
//! broadcasts the pre-serialized `ServerMessage::Iteration` frame
//! ([`frames`]: summary and full text, shared by all viewers) over a bounded
//! `tokio::sync::broadcast` channel ([`ManagerOptions::viewer_buffer`]
//! frames). A slow viewer never blocks the run: it lags, is told so, and is
//! sent the newest page of summaries (see [`crate::server`]).
//!
//! One run, one task (ARCHITECTURE.md, invariant 6): starting and resuming
//! a run go through the run's lifecycle lock, so concurrent `resume`s start
//! one task and hand the others to it; each task claims a new generation in
//! the store ([`Store::claim`]) and every write it makes is checked against
//! it, so a superseded task (also one in another process sharing the store)
//! cannot write and exits. A task whose control channel closes exits too.
//!
//! A run without a live task (interrupted by a restart, faulted and detached,
//! failed, paused after a restart) is restarted from its last stored
//! checkpoint on `Resume`/`Step`; the restored session reads every gate back
//! from the instrument before it moves one.

mod frames;
mod task;

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::extract::ws::Utf8Bytes;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use spintune::lifecycle::Acceptance;
use spintune::protocol::{ControlCommand, IterationRecord, RunStatus, RunSummary, ServerMessage};
use spintune::session::{RunSession, SessionConfig};
use spintune::tuner::Tuner;
use tokio::sync::{broadcast, mpsc, oneshot};

pub use frames::{history_frame_text, iteration_frame_text, Frame, FrameEvent};

use crate::config::{DriverKind, RunConfig};
use crate::devices::bridge::{BridgeLink, Links};
use crate::devices::{self, Device, SimulatorDevice};
use crate::store::{Store, StoreError};

/// Control commands queued for one run's task (bounded by construction).
pub const CONTROL_QUEUE: usize = 16;

/// Summaries of the newest iterations each run keeps in memory (one default
/// history page), so the page sent after `Hello`/`Lagged` needs no store read.
pub const RECENT_SUMMARIES: usize = spintune::protocol::DEFAULT_HISTORY_PAGE as usize;

/// Limits of a run's viewer WebSockets (see `crate::server` for the constants
/// and what happens when one is reached).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ViewerLimits {
    /// A send to a viewer that does not complete in this time disconnects it.
    pub send_timeout: Duration,
    /// The server pings every viewer this often.
    pub ping_interval: Duration,
    /// A viewer from which nothing (pong or any frame) arrived for this long
    /// is disconnected (checked at each ping).
    pub pong_timeout: Duration,
    /// Open viewer WebSockets per run; one more is refused with 503.
    pub max_viewers_per_run: usize,
}

impl Default for ViewerLimits {
    fn default() -> Self {
        Self {
            send_timeout: crate::server::VIEWER_SEND_TIMEOUT,
            ping_interval: crate::server::VIEWER_PING_INTERVAL,
            pong_timeout: crate::server::VIEWER_PONG_TIMEOUT,
            max_viewers_per_run: crate::server::MAX_VIEWERS_PER_RUN,
        }
    }
}

/// One open viewer socket of a run (counted until dropped; holds the count,
/// not the run, so deleting the run still closes its channel).
pub struct ViewerSlot(Arc<AtomicUsize>);

impl Drop for ViewerSlot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// A page of summaries served from memory ([`RunHandle::recent_page`]).
#[derive(Debug, Clone)]
pub struct RecentPage {
    /// Seq of the first record (`None`: empty page).
    pub first_seq: Option<u64>,
    /// Summary records as JSON, oldest first.
    pub records: Vec<Utf8Bytes>,
    /// Older iterations exist.
    pub more_before: bool,
    /// The seq after the page's range (the newest committed + 1 for a page
    /// of the newest).
    pub end: u64,
}

/// Waits before each attempt to store a run's `failed` status, ms.
const FAILED_STATUS_RETRY_MS: [u64; 3] = [0, 200, 1_000];

/// A `stopped` status the store refused is stored again every this many ms
/// (the run is stopped in memory at once: nothing reaches the device).
const STOPPED_STATUS_RETRY_MS: u64 = 2_000;

/// ... at most this many times (one hour); after that a restart lists the
/// run with its last stored status (never `running`: `interrupted`).
const STOPPED_STATUS_RETRIES: u32 = 1_800;

/// Schema version of [`Checkpoint`] written by this release. Checkpoints
/// without a version were written by older releases (read as version 1).
pub const CHECKPOINT_VERSION: u32 = 2;

fn legacy_checkpoint_version() -> u32 {
    1
}

/// Everything needed to continue a run: stored after every iteration.
#[derive(Debug, Serialize, Deserialize)]
pub struct Checkpoint {
    /// Schema version ([`CHECKPOINT_VERSION`]); checked on load.
    #[serde(default = "legacy_checkpoint_version")]
    pub version: u32,
    /// The session's complete state (tuner, mode, deferred targets).
    #[serde(default)]
    pub session: Option<RunSession>,
    /// A checkpoint written before run sessions existed holds the tuner only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tuner: Option<Tuner>,
    /// The device's state (`null` for devices without restorable state).
    pub device: Value,
}

impl Checkpoint {
    /// A checkpoint of this release.
    pub fn new(session: RunSession, device: Value) -> Self {
        Self {
            version: CHECKPOINT_VERSION,
            session: Some(session),
            tuner: None,
            device,
        }
    }

    /// Parse and check a stored checkpoint of run `id`: malformed JSON, an
    /// unknown schema version or a state that does not belong to the run's
    /// config (other gates or limits: invariant 5 rests on them) is an error
    /// naming the problem, never a panic.
    pub fn load(id: u64, json: &str, config: &RunConfig) -> Result<Self, RunError> {
        let unusable = |why: String| {
            RunError::Conflict(format!(
                "run {id} cannot continue: its stored checkpoint {why}"
            ))
        };
        let raw: Value =
            serde_json::from_str(json).map_err(|e| unusable(format!("is not JSON ({e})")))?;
        let version = match raw.get("version") {
            None => legacy_checkpoint_version(),
            Some(v) => v
                .as_u64()
                .and_then(|v| u32::try_from(v).ok())
                .ok_or_else(|| unusable(format!("has an invalid schema version {v}")))?,
        };
        if version == 0 || version > CHECKPOINT_VERSION {
            return Err(unusable(format!(
                "has schema version {version}; this server reads versions 1 to {CHECKPOINT_VERSION}"
            )));
        }
        let cp: Checkpoint = serde_path_to_error::deserialize(raw)
            .map_err(|e| unusable(format!("is malformed at `{}`: {}", e.path(), e.inner())))?;
        let tuner = match (&cp.session, &cp.tuner) {
            (Some(s), _) => s.tuner(),
            (None, Some(t)) => t,
            (None, None) => return Err(unusable("holds neither a session nor a tuner".into())),
        };
        let want = &config.simulation.tuner.gates;
        let have = &tuner.config().gates;
        let same = want.len() == have.len()
            && want.iter().zip(have).all(|(a, b)| {
                a.name == b.name
                    && a.min_mv == b.min_mv
                    && a.max_mv == b.max_mv
                    && a.max_step_mv == b.max_step_mv
            });
        if !same {
            return Err(unusable(
                "has other gates or gate limits than the run's config".into(),
            ));
        }
        if let Some((gate, v)) = tuner.voltages_mv().iter().find(|(_, v)| !v.is_finite()) {
            return Err(unusable(format!(
                "holds a non-finite voltage {v} for {gate}"
            )));
        }
        Ok(cp)
    }

    /// The session to continue from (an old tuner-only checkpoint gets a
    /// fresh session around its tuner).
    pub fn into_session(self, config: SessionConfig) -> Result<(RunSession, Value), RunError> {
        match (self.session, self.tuner) {
            (Some(s), _) => Ok((s, self.device)),
            (None, Some(t)) => Ok((RunSession::from_tuner(t, config), self.device)),
            (None, None) => Err(RunError::Internal(
                "checkpoint holds neither a session nor a tuner".into(),
            )),
        }
    }
}

/// Why a control action or lookup failed; maps to an HTTP status.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RunError {
    /// No such run (404).
    #[error("no run with id {0}")]
    NotFound(u64),
    /// The action does not apply in the run's present state (409).
    #[error("{0}")]
    Conflict(String),
    /// The command's content is invalid (400 / 422), e.g. an unknown parameter.
    #[error("{0}")]
    Invalid(String),
    /// The store failed (500; a stale task generation ends that task).
    #[error("{0}")]
    Store(StoreErrorKind),
    /// Internal failure (500).
    #[error("{0}")]
    Internal(String),
}

/// The store failures a caller distinguishes.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StoreErrorKind {
    /// Another task drives the run now.
    #[error("{0}")]
    Stale(String),
    /// Anything else.
    #[error("{0}")]
    Other(String),
}

impl From<StoreError> for RunError {
    fn from(e: StoreError) -> Self {
        match e {
            StoreError::NotFound(id) => RunError::NotFound(id),
            e @ StoreError::Stale { .. } => RunError::Store(StoreErrorKind::Stale(e.to_string())),
            e => RunError::Store(StoreErrorKind::Other(e.to_string())),
        }
    }
}

impl RunError {
    /// Whether this is a stale-generation refusal (another task drives the run).
    pub fn is_stale(&self) -> bool {
        matches!(self, RunError::Store(StoreErrorKind::Stale(_)))
    }
}

struct ControlMsg {
    command: ControlCommand,
    reply: oneshot::Sender<Result<RunSummary, RunError>>,
}

/// A run known to the manager (live task or not).
pub struct RunHandle {
    /// Run id.
    pub id: u64,
    /// The run's configuration.
    pub config: RunConfig,
    summary: Mutex<RunSummary>,
    tx: broadcast::Sender<Frame>,
    control: Mutex<Option<mpsc::Sender<ControlMsg>>>,
    /// Why the stored run is unreadable (`Some`: quarantined; listed, never driven).
    quarantine: Option<String>,
    /// Held while starting, resuming or controlling the run: at most one task.
    lifecycle: tokio::sync::Mutex<()>,
    /// (seq, summary JSON) of the newest committed iterations, at most
    /// [`RECENT_SUMMARIES`].
    recent: Mutex<VecDeque<(u64, Utf8Bytes)>>,
    /// Open viewer sockets ([`RunHandle::add_viewer`]).
    viewer_sockets: Arc<AtomicUsize>,
}

impl RunHandle {
    fn new(id: u64, config: RunConfig, summary: RunSummary, viewer_buffer: usize) -> Self {
        Self {
            id,
            config,
            summary: Mutex::new(summary),
            tx: broadcast::channel(viewer_buffer.max(1)).0,
            control: Mutex::new(None),
            quarantine: None,
            lifecycle: tokio::sync::Mutex::new(()),
            recent: Mutex::new(VecDeque::with_capacity(RECENT_SUMMARIES)),
            viewer_sockets: Arc::new(AtomicUsize::new(0)),
        }
    }

    /// Count one more open viewer socket, unless `max` are open already.
    pub fn add_viewer(&self, max: usize) -> Option<ViewerSlot> {
        self.viewer_sockets
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < max).then_some(n + 1)
            })
            .ok()
            .map(|_| ViewerSlot(self.viewer_sockets.clone()))
    }

    /// Open viewer sockets.
    pub fn viewer_sockets(&self) -> usize {
        self.viewer_sockets.load(Ordering::Acquire)
    }

    fn remember_summary(&self, seq: u64, summary: Utf8Bytes) {
        let mut recent = self.recent.lock().unwrap_or_else(|p| p.into_inner());
        if recent.back().is_some_and(|(s, _)| s + 1 != seq) {
            recent.clear();
        }
        if recent.len() == RECENT_SUMMARIES {
            recent.pop_front();
        }
        recent.push_back((seq, summary));
    }

    /// The page of summaries with seq in `[from.max(before - limit), before)`
    /// (`before` `None`: up to the newest committed iteration), if the ring of
    /// recent summaries holds all of it; `None`: ask the store.
    pub fn recent_page(&self, before: Option<u64>, limit: u64, from: u64) -> Option<RecentPage> {
        let recent = self.recent.lock().unwrap_or_else(|p| p.into_inner());
        let committed = self.summary().iterations;
        let end = before.map_or(committed, |b| b.min(committed));
        let start = end.saturating_sub(limit).max(from);
        if start >= end {
            // Seq is contiguous from 0: older iterations exist iff end > 0.
            return Some(RecentPage {
                first_seq: None,
                records: Vec::new(),
                more_before: end > 0,
                end,
            });
        }
        let (first, _) = *recent.front()?;
        let (last, _) = *recent.back()?;
        if start < first || end - 1 > last {
            return None;
        }
        let lo = (start - first) as usize;
        let hi = (end - first) as usize;
        Some(RecentPage {
            first_seq: Some(start),
            records: recent.range(lo..hi).map(|(_, t)| t.clone()).collect(),
            more_before: start > 0,
            end,
        })
    }

    /// A run whose stored row or config is unreadable: listed with the
    /// error, refused for control, config and bridges; deletable.
    fn quarantined(id: u64, summary: RunSummary, error: String, viewer_buffer: usize) -> Self {
        Self {
            quarantine: Some(error),
            ..Self::new(id, RunConfig::paper_default(), summary, viewer_buffer)
        }
    }

    /// `Conflict` naming the error if the run is quarantined.
    pub fn readable(&self) -> Result<(), RunError> {
        match &self.quarantine {
            None => Ok(()),
            Some(e) => Err(RunError::Conflict(format!(
                "run {} is quarantined: its stored data is unreadable ({e}); delete it or repair the store",
                self.id
            ))),
        }
    }

    /// Current summary.
    pub fn summary(&self) -> RunSummary {
        self.summary
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Subscribe to the run's live frames.
    pub fn subscribe(&self) -> broadcast::Receiver<Frame> {
        self.tx.subscribe()
    }

    /// Number of connected viewers.
    pub fn viewers(&self) -> usize {
        self.tx.receiver_count()
    }

    /// Whether a task drives the run in this process.
    pub fn is_live(&self) -> bool {
        self.control_sender().is_some()
    }

    fn set_summary(&self, f: impl FnOnce(&mut RunSummary)) -> RunSummary {
        let mut s = self.summary.lock().unwrap_or_else(|p| p.into_inner());
        f(&mut s);
        s.clone()
    }

    fn broadcast_status(&self, run: RunSummary) {
        let _ = self.tx.send(Frame::message(&ServerMessage::Status { run }));
    }

    fn control_sender(&self) -> Option<mpsc::Sender<ControlMsg>> {
        self.control
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .filter(|s| !s.is_closed())
            .cloned()
    }

    fn set_control(&self, sender: Option<mpsc::Sender<ControlMsg>>) {
        *self.control.lock().unwrap_or_else(|p| p.into_inner()) = sender;
    }
}

/// Manager settings.
#[derive(Debug, Clone)]
pub struct ManagerOptions {
    /// Default wall-clock pause after each iteration (a run config may override it).
    pub iteration_delay: Duration,
    /// Live frames buffered per viewer before it is told it lagged.
    pub viewer_buffer: usize,
    /// At open, mark runs left `running`/`paused` by a previous process as
    /// `interrupted` (the server does; a headless `run` sharing the store does not).
    pub recover: bool,
    /// Limits of viewer sockets (send timeout, pings, sockets per run).
    pub viewers: ViewerLimits,
}

impl Default for ManagerOptions {
    fn default() -> Self {
        Self {
            iteration_delay: Duration::from_millis(0),
            viewer_buffer: 256,
            recover: true,
            viewers: ViewerLimits::default(),
        }
    }
}

/// All runs of one server (or one headless `spintune run`).
pub struct Manager {
    store: Arc<Store>,
    runs: Mutex<BTreeMap<u64, Arc<RunHandle>>>,
    options: ManagerOptions,
    bridges: Links,
}

async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, StoreError> + Send + 'static,
) -> Result<T, RunError> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| RunError::Internal(format!("store task failed: {e}")))?
        .map_err(RunError::from)
}

/// The session settings a run's driver implies.
fn session_config(config: &RunConfig, default_delay: Duration) -> SessionConfig {
    let b = &config.backend;
    let readback_tolerance_mv = match b.driver {
        DriverKind::Simulator => SessionConfig::default().readback_tolerance_mv,
        DriverKind::Bridge => b.bridge.readback_tolerance_mv,
        DriverKind::Scpi => b
            .scpi
            .as_ref()
            .map_or(b.bridge.readback_tolerance_mv, |s| s.readback_tolerance_mv),
    };
    let delay_ms = b
        .iteration_delay_ms
        .unwrap_or(default_delay.as_millis() as u64)
        .min(SessionConfig::MAX_ITERATION_DELAY_MS);
    SessionConfig {
        readback_tolerance_mv,
        iteration_delay_ms: delay_ms,
        moved_tolerance_mv: b
            .moved_tolerance_mv
            .unwrap_or(SessionConfig::default().moved_tolerance_mv),
    }
}

impl Manager {
    /// Load all runs from the store. Runs left running by a previous process are
    /// marked `Interrupted`; no task is started for them until they are resumed.
    pub fn open(store: Arc<Store>, options: ManagerOptions) -> Result<Arc<Self>, RunError> {
        if options.recover {
            store.mark_interrupted()?;
        }
        let mut runs = BTreeMap::new();
        for stored in store.list_runs()? {
            let id = stored.summary.id;
            let config = match &stored.unreadable {
                Some(e) => Err(e.clone()),
                None => serde_json::from_str::<RunConfig>(&stored.config_json)
                    .map_err(|e| format!("unreadable config: {e}")),
            };
            let config = match config {
                Ok(c) => c,
                Err(e) => {
                    eprintln!("warning: run {id} is quarantined: {e}");
                    let mut summary = stored.summary;
                    summary.status = RunStatus::Failed {
                        message: format!("quarantined: the stored run is unreadable ({e})"),
                    };
                    runs.insert(
                        id,
                        Arc::new(RunHandle::quarantined(
                            id,
                            summary,
                            e,
                            options.viewer_buffer,
                        )),
                    );
                    continue;
                }
            };
            runs.insert(
                id,
                Arc::new(RunHandle::new(
                    id,
                    config,
                    stored.summary,
                    options.viewer_buffer,
                )),
            );
        }
        Ok(Arc::new(Self {
            store,
            runs: Mutex::new(runs),
            options,
            bridges: Links::default(),
        }))
    }

    /// The manager's settings.
    pub fn options(&self) -> &ManagerOptions {
        &self.options
    }

    /// The store.
    pub fn store(&self) -> &Arc<Store> {
        &self.store
    }

    fn runs(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, Arc<RunHandle>>> {
        self.runs.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A run's handle.
    pub fn get(&self, id: u64) -> Result<Arc<RunHandle>, RunError> {
        self.runs().get(&id).cloned().ok_or(RunError::NotFound(id))
    }

    /// The lab bridge link of run `id` (created on first use). `Conflict` if
    /// the run's device does not include the bridge.
    pub fn bridge_link(&self, id: u64) -> Result<Arc<BridgeLink>, RunError> {
        let handle = self.get(id)?;
        handle.readable()?;
        if !handle.config.backend.uses_bridge() {
            return Err(RunError::Conflict(format!(
                "run {id} does not use the lab bridge (its driver is {:?}); create it with driver = \"bridge\" or scpi.measure = \"bridge\"",
                handle.config.backend.driver
            )));
        }
        Ok(self.bridges.get(id))
    }

    /// Summaries of all runs, by id.
    pub fn list(&self) -> Vec<RunSummary> {
        self.runs().values().map(|h| h.summary()).collect()
    }

    /// Create a run from `config` and start it (or leave it paused).
    pub async fn create(
        self: &Arc<Self>,
        config: RunConfig,
        start_paused: bool,
    ) -> Result<RunSummary, RunError> {
        let sim = &config.simulation;
        sim.validate()
            .map_err(|e| RunError::Invalid(e.to_string()))?;
        let scfg = session_config(&config, self.options.iteration_delay);
        let mut session = RunSession::new(sim.tuner.clone(), scfg)
            .map_err(|e| RunError::Invalid(e.to_string()))?;
        if start_paused {
            session
                .control(&ControlCommand::Pause)
                .map_err(|e| RunError::Internal(e.to_string()))?;
        }
        let device = sim
            .simulated_device()
            .map_err(|e| RunError::Invalid(e.to_string()))?;
        let checkpoint = Checkpoint::new(
            session,
            SimulatorDevice::new(device)
                .checkpoint()
                .map_err(|e| RunError::Internal(e.to_string()))?,
        );
        let checkpoint_json =
            serde_json::to_string(&checkpoint).map_err(|e| RunError::Internal(e.to_string()))?;
        let config_json =
            serde_json::to_string(&config).map_err(|e| RunError::Internal(e.to_string()))?;
        let status = if start_paused {
            RunStatus::Paused
        } else {
            RunStatus::Running
        };
        let store = self.store.clone();
        let name = config.name().to_string();
        let st = status.clone();
        let id =
            blocking(move || store.create_run(&name, &config_json, &st, &checkpoint_json)).await?;
        let summary = RunSummary {
            id,
            name: config.name().to_string(),
            status,
            iterations: 0,
            lab_seconds: 0.0,
            tuned: false,
            driver: serde_json::to_value(config.backend.driver)
                .ok()
                .and_then(|v| v.as_str().map(str::to_string)),
        };
        let handle = Arc::new(RunHandle::new(
            id,
            config,
            summary,
            self.options.viewer_buffer,
        ));
        self.runs().insert(id, handle.clone());
        {
            let _lock = handle.lifecycle.lock().await;
            self.start_task(&handle, checkpoint).await?;
        }
        Ok(handle.summary())
    }

    /// Apply a control command to run `id`: handed to its live task, or
    /// applied to the stored run (resume and step start a task).
    pub async fn control(
        self: &Arc<Self>,
        id: u64,
        command: ControlCommand,
    ) -> Result<RunSummary, RunError> {
        let handle = self.get(id)?;
        handle.readable()?;
        let _lock = handle.lifecycle.lock().await;
        if let Some(sender) = handle.control_sender() {
            let (reply, rx) = oneshot::channel();
            if sender
                .send(ControlMsg {
                    command: command.clone(),
                    reply,
                })
                .await
                .is_ok()
            {
                if let Ok(result) = rx.await {
                    return result;
                }
            }
            // The task ended in between: its final status is stored; handle
            // the command offline.
        }
        self.control_offline(&handle, command).await
    }

    /// Under the lifecycle lock, with no live task.
    async fn control_offline(
        self: &Arc<Self>,
        handle: &Arc<RunHandle>,
        command: ControlCommand,
    ) -> Result<RunSummary, RunError> {
        let status = handle.summary().status;
        // The one lifecycle table (the core's), for a run without a task.
        let acceptance = status
            .accepts(&command)
            .map_err(|r| RunError::Conflict(format!("run {}: {r}", handle.id)))?;
        if acceptance == Acceptance::AlreadyThere {
            return Ok(handle.summary());
        }
        match &command {
            ControlCommand::Resume | ControlCommand::Step => {
                let checkpoint = self.load_checkpoint(handle).await?;
                let scfg = session_config(&handle.config, self.options.iteration_delay);
                let (mut session, device) = checkpoint.into_session(scfg)?;
                let new_status = session
                    .control(&command)
                    .map_err(|e| RunError::Conflict(e.to_string()))?;
                handle.set_summary(|s| s.status = new_status);
                if let Err(e) = self
                    .start_task(handle, Checkpoint::new(session, device))
                    .await
                {
                    // No task runs: the run is what it was (never a phantom
                    // `running` nobody drives).
                    let summary = handle.set_summary(|s| s.status = status.clone());
                    handle.broadcast_status(summary);
                    return Err(e);
                }
                Ok(handle.summary())
            }
            ControlCommand::Pause => self.set_status_offline(handle, RunStatus::Paused).await,
            ControlCommand::Stop => Ok(self.settle_stopped(handle, None).await),
            ControlCommand::SetTarget { .. } => {
                let checkpoint = self.load_checkpoint(handle).await?;
                let scfg = session_config(&handle.config, self.options.iteration_delay);
                let (mut session, device) = checkpoint.into_session(scfg)?;
                session.control(&command).map_err(|e| match e {
                    spintune::session::ControlError::Conflict { .. } => {
                        RunError::Conflict(e.to_string())
                    }
                    e => RunError::Invalid(e.to_string()),
                })?;
                // a new target revives a run that finished because it was tuned
                let revived =
                    status == RunStatus::Finished && session.status() == RunStatus::Paused;
                let json = serde_json::to_string(&Checkpoint::new(session, device))
                    .map_err(|e| RunError::Internal(e.to_string()))?;
                let store = self.store.clone();
                let id = handle.id;
                blocking(move || store.save_checkpoint(id, None, &json)).await?;
                if revived {
                    return self.set_status_offline(handle, RunStatus::Paused).await;
                }
                Ok(handle.summary())
            }
            ControlCommand::AcceptPositions => {
                // Only a faulted run has positions to accept; the session
                // decides (it refuses every other status).
                let checkpoint = self.load_checkpoint(handle).await?;
                let scfg = session_config(&handle.config, self.options.iteration_delay);
                let (mut session, device) = checkpoint.into_session(scfg)?;
                if let RunStatus::Faulted { fault } = &status {
                    session.restore_fault(fault.clone());
                }
                let new_status = session
                    .control(&command)
                    .map_err(|e| RunError::Conflict(format!("run {}: {e}", handle.id)))?;
                let json = serde_json::to_string(&Checkpoint::new(session, device))
                    .map_err(|e| RunError::Internal(e.to_string()))?;
                let store = self.store.clone();
                let id = handle.id;
                blocking(move || store.save_checkpoint(id, None, &json)).await?;
                self.set_status_offline(handle, new_status).await
            }
        }
    }

    async fn load_checkpoint(&self, handle: &RunHandle) -> Result<Checkpoint, RunError> {
        let store = self.store.clone();
        let id = handle.id;
        let json = blocking(move || store.checkpoint(id)).await?;
        Checkpoint::load(id, &json, &handle.config)
    }

    /// Run a task's future; if it panics (e.g. on a restored state the core
    /// cannot handle) the run is failed instead of being left `running`.
    async fn supervise(
        &self,
        handle: &RunHandle,
        generation: u64,
        task: impl std::future::Future<Output = ()> + Send + 'static,
    ) {
        if let Err(e) = tokio::spawn(task).await {
            let message = match e.try_into_panic() {
                Ok(p) => format!(
                    "internal error: the run task panicked: {}",
                    p.downcast_ref::<&str>()
                        .map(|s| s.to_string())
                        .or_else(|| p.downcast_ref::<String>().cloned())
                        .unwrap_or_default()
                ),
                Err(e) => format!("internal error: the run task ended: {e}"),
            };
            self.fail_run(handle, generation, message).await;
        }
    }

    /// A run task failed (the store refused a write, or the task panicked):
    /// the run is `failed` with `message`, in memory at once (nobody is told
    /// `running`) and in the store if it takes the write (a few attempts).
    /// If it does not, the message says so; a restart then lists the run as
    /// `interrupted`, never `running`.
    async fn fail_run(&self, handle: &RunHandle, generation: u64, message: String) {
        let status = RunStatus::Failed {
            message: message.clone(),
        };
        let summary = handle.set_summary(|s| s.status = status.clone());
        handle.broadcast_status(summary);
        let mut last = None;
        for wait_ms in FAILED_STATUS_RETRY_MS {
            tokio::time::sleep(Duration::from_millis(wait_ms)).await;
            match self
                .store_status(handle, Some(generation), status.clone())
                .await
            {
                Ok(()) => return,
                // Another task drives the run now, or it was deleted: not ours to mark.
                Err(e) if e.is_stale() || matches!(e, RunError::NotFound(_)) => return,
                Err(e) => last = Some(e),
            }
        }
        if let Some(e) = last {
            let status = RunStatus::Failed {
                message: format!(
                    "{message}; this status could not be stored either ({e}): after a restart the run is listed as interrupted"
                ),
            };
            let summary = handle.set_summary(|s| s.status = status);
            handle.broadcast_status(summary);
        }
    }

    /// The run is stopped: at once in memory (and to viewers), and in the
    /// store as soon as it takes the write (retried in the background every
    /// [`STOPPED_STATUS_RETRY_MS`], at most [`STOPPED_STATUS_RETRIES`] times).
    /// A stop always works: no task drives the run any more.
    async fn settle_stopped(
        self: &Arc<Self>,
        handle: &Arc<RunHandle>,
        generation: Option<u64>,
    ) -> RunSummary {
        let summary = handle.set_summary(|s| s.status = RunStatus::Stopped);
        handle.broadcast_status(summary.clone());
        if self
            .store_status(handle, generation, RunStatus::Stopped)
            .await
            .is_ok()
        {
            return summary;
        }
        let (manager, handle) = (self.clone(), handle.clone());
        tokio::spawn(async move {
            for _ in 0..STOPPED_STATUS_RETRIES {
                tokio::time::sleep(Duration::from_millis(STOPPED_STATUS_RETRY_MS)).await;
                if handle.summary().status != RunStatus::Stopped {
                    return;
                }
                match manager
                    .store_status(&handle, generation, RunStatus::Stopped)
                    .await
                {
                    Ok(()) => return,
                    Err(e) if e.is_stale() || matches!(e, RunError::NotFound(_)) => return,
                    Err(_) => {}
                }
            }
        });
        summary
    }

    /// Store a status (with `generation`: only for that task), no broadcast.
    async fn store_status(
        &self,
        handle: &RunHandle,
        generation: Option<u64>,
        status: RunStatus,
    ) -> Result<(), RunError> {
        let store = self.store.clone();
        let id = handle.id;
        blocking(move || store.set_status(id, generation, &status)).await
    }

    async fn set_status_offline(
        &self,
        handle: &RunHandle,
        status: RunStatus,
    ) -> Result<RunSummary, RunError> {
        self.store_status(handle, None, status.clone()).await?;
        let summary = handle.set_summary(|s| s.status = status);
        handle.broadcast_status(summary.clone());
        Ok(summary)
    }

    /// Commit one iteration record (JSON) with the checkpoint taken right after
    /// it, then update the summary and broadcast it to the viewers. Returns the
    /// record's seq. This is the only path by which iterations reach viewers.
    async fn commit_and_broadcast(
        &self,
        handle: &RunHandle,
        generation: Option<u64>,
        record: Arc<IterationRecord>,
        record_json: String,
        checkpoint_json: String,
    ) -> Result<u64, RunError> {
        let (lab_seconds, tuned) = (record.lab_seconds, record.tuned);
        let seq = handle.summary().iterations;
        let store = self.store.clone();
        let id = handle.id;
        let full = iteration_frame_text(&record_json);
        let summary_json = serde_json::to_string(&record.summary())
            .map_err(|e| RunError::Internal(format!("cannot serialize a summary: {e}")))?;
        let text = iteration_frame_text(&summary_json);
        blocking(move || {
            store.commit_iteration(
                id,
                generation,
                seq,
                &record_json,
                &checkpoint_json,
                lab_seconds,
                tuned,
            )
        })
        .await?;
        handle.set_summary(|s| {
            s.iterations = seq + 1;
            s.lab_seconds = lab_seconds;
            s.tuned = tuned;
        });
        handle.remember_summary(seq, Utf8Bytes::from(summary_json));
        let _ = handle.tx.send(Frame {
            seq: Some(seq),
            text: Utf8Bytes::from(text),
            full: Some(Utf8Bytes::from(full)),
            event: FrameEvent::Iteration(record),
        });
        Ok(seq)
    }

    /// Publish a record produced outside a run task (the load bench's synthetic
    /// source) through the same commit-then-broadcast path. The run must have
    /// no live task; `checkpoint_json` is stored as its checkpoint (pass the
    /// present one, [`Store::checkpoint`], to keep it).
    pub async fn publish_external(
        &self,
        id: u64,
        record: &IterationRecord,
        checkpoint_json: String,
    ) -> Result<u64, RunError> {
        let handle = self.get(id)?;
        if handle.is_live() {
            return Err(RunError::Conflict(format!(
                "run {id} has a live task; stop it before publishing external records"
            )));
        }
        let json = serde_json::to_string(record).map_err(|e| RunError::Internal(e.to_string()))?;
        self.commit_and_broadcast(
            &handle,
            None,
            Arc::new(record.clone()),
            json,
            checkpoint_json,
        )
        .await
    }

    /// Stop run `id` (if live) and delete it with its iterations.
    pub async fn delete(self: &Arc<Self>, id: u64) -> Result<(), RunError> {
        let handle = self.get(id)?;
        if handle.is_live() {
            // Stop the task first so it does not write after the delete.
            let _ = self.control(id, ControlCommand::Stop).await;
            self.wait_idle(id).await?;
        }
        let _lock = handle.lifecycle.lock().await;
        handle.set_control(None);
        let store = self.store.clone();
        blocking(move || store.delete_run(id)).await?;
        self.bridges.remove(id);
        if let Some(h) = self.runs().remove(&id) {
            let _ = h.tx.send(Frame::message(&ServerMessage::Error {
                message: format!("run {id} was deleted"),
            }));
        }
        Ok(())
    }

    /// Let go of run `id`'s task without changing its stored status (e.g. the
    /// headless CLI leaving a faulted run resumable): its control channel
    /// closes and the task exits.
    pub async fn detach(&self, id: u64) -> Result<(), RunError> {
        let handle = self.get(id)?;
        let _lock = handle.lifecycle.lock().await;
        handle.set_control(None);
        Ok(())
    }

    /// Wait until run `id` has no live task. For the headless CLI and tests.
    pub async fn wait_idle(&self, id: u64) -> Result<RunSummary, RunError> {
        loop {
            let handle = self.get(id)?;
            if !handle.is_live() {
                return Ok(handle.summary());
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Mark every run with a live task `Interrupted` in the store (for a clean
    /// shutdown on Ctrl-C; a crash leaves them `Running`, which the next start
    /// turns into `Interrupted`).
    pub fn mark_live_interrupted(&self) {
        for h in self.runs().values() {
            if h.is_live() {
                let _ = self.store.set_status(h.id, None, &RunStatus::Interrupted);
            }
        }
    }

    /// Under the lifecycle lock: claim a new generation and spawn the run's
    /// one task from `checkpoint`.
    async fn start_task(
        self: &Arc<Self>,
        handle: &Arc<RunHandle>,
        checkpoint: Checkpoint,
    ) -> Result<(), RunError> {
        let store = self.store.clone();
        let id = handle.id;
        let generation = blocking(move || store.claim(id)).await?;
        let scfg = session_config(&handle.config, self.options.iteration_delay);
        let (mut session, device_state) = checkpoint.into_session(scfg.clone())?;
        session.set_iteration_delay_ms(scfg.iteration_delay_ms);
        let bridge = handle
            .config
            .backend
            .uses_bridge()
            .then(|| self.bridges.get(handle.id));
        let device: Box<dyn Device> = match devices::open(&handle.config, device_state, bridge) {
            Ok(d) => d,
            Err(e) => {
                let status = RunStatus::Failed {
                    message: format!("cannot open the device: {e}"),
                };
                self.set_status_offline(handle, status).await?;
                return Ok(());
            }
        };
        let (tx, rx) = mpsc::channel(CONTROL_QUEUE);
        handle.set_control(Some(tx.clone()));
        let task = task::RunTask {
            manager: self.clone(),
            handle: handle.clone(),
            session,
            device,
            control: rx,
            generation,
        };
        let h = handle.clone();
        let manager = self.clone();
        tokio::spawn(async move {
            manager.supervise(&h, generation, task.run()).await;
            // Only this task's channel is cleared (a detached task must not
            // clear its successor's).
            let mut control = h.control.lock().unwrap_or_else(|p| p.into_inner());
            if control.as_ref().is_some_and(|c| c.same_channel(&tx)) {
                *control = None;
            }
        });
        Ok(())
    }
}

/// Short name of a status.
pub fn status_name(s: &RunStatus) -> &'static str {
    s.name()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tuner_only_checkpoint_of_an_older_release_still_resumes() {
        let cfg = spintune::driver::SimulationConfig::paper_default();
        let tuner = Tuner::new(cfg.tuner).unwrap();
        let old = serde_json::json!({ "tuner": tuner, "device": null });
        let cp: Checkpoint = serde_json::from_value(old).unwrap();
        let (session, _) = cp.into_session(SessionConfig::default()).unwrap();
        assert_eq!(session.tuner().iteration(), 0);
        assert_eq!(session.status(), RunStatus::Running);
    }

    #[tokio::test]
    async fn a_panicking_run_task_fails_the_run_in_memory_and_in_the_store() {
        let dir = std::env::temp_dir().join(format!("spintune-panic-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let store = Arc::new(Store::open(&dir.join("p.db")).unwrap());
        let manager = Manager::open(store.clone(), ManagerOptions::default()).unwrap();
        let id = manager
            .create(RunConfig::paper_default(), true)
            .await
            .unwrap()
            .id;
        let handle = manager.get(id).unwrap();
        // A new task generation takes the run over (the paused one goes stale).
        let generation = store.claim(id).unwrap();
        manager
            .supervise(&handle, generation, async { panic!("boom") })
            .await;
        let failed = |s: &RunStatus| matches!(s, RunStatus::Failed { message } if message.contains("panicked: boom"));
        assert!(
            failed(&handle.summary().status),
            "{:?}",
            handle.summary().status
        );
        assert!(failed(&store.get_run(id).unwrap().summary.status));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn stale_store_errors_are_told_apart() {
        let e = RunError::from(StoreError::Stale {
            run: 1,
            generation: 1,
            current: 2,
        });
        assert!(e.is_stale());
        assert!(!RunError::from(StoreError::NotFound(1)).is_stale());
    }
}
