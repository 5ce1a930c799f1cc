//! The run manager: many concurrent runs, each a tokio task driving the core's
//! sans-IO [`Tuner`] through an async [`Device`].
//!
//! Per iteration the task (1) commits the record and the checkpoint (tuner +
//! device state) to the [`Store`] in one transaction, (2) updates the run's
//! summary, (3) broadcasts the pre-serialized `ServerMessage::Iteration` frame
//! to the run's viewers over a bounded `tokio::sync::broadcast` channel. A slow
//! viewer therefore never blocks the run: it lags, is told so, and refills from
//! the store (see [`crate::server`]).
//!
//! Control commands are handled between requests (pause, stop) and between
//! iterations (step, resume, target changes; a target change is checkpointed at
//! once so it survives a crash). A run without a live task (interrupted by a
//! restart, failed, paused after a restart) is restarted from its last stored
//! checkpoint on `Resume`/`Step`.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::extract::ws::Utf8Bytes;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use spintune::driver::SimulationRun;
use spintune::protocol::{
    ControlCommand, IterationRecord, Request, RunStatus, RunSummary, ServerMessage,
};
use spintune::tuner::{Action, Tuner};
use tokio::sync::{broadcast, mpsc, oneshot};

use crate::bridge::{BridgeLink, Links};
use crate::config::RunConfig;
use crate::device::{self, BoxFuture, Device, SimulatorDevice};
use crate::store::{Store, StoreError};

/// One frame for a run's viewers: pre-serialized JSON of a [`ServerMessage`],
/// shared (not copied) between all viewers.
#[derive(Debug, Clone)]
pub struct Frame {
    /// For `Iteration` frames: the record's position in the store (0-based).
    pub seq: Option<u64>,
    /// JSON text of the `ServerMessage`.
    pub text: Utf8Bytes,
}

impl Frame {
    /// A frame for any server message (no seq).
    pub fn message(msg: &ServerMessage) -> Self {
        Self {
            seq: None,
            text: Utf8Bytes::from(serde_json::to_string(msg).expect("ServerMessage serializes")),
        }
    }
}

/// `{"type":"iteration","record":…}` built around an already serialized record
/// (the same bytes that were stored), identical to serializing
/// `ServerMessage::Iteration`.
pub fn iteration_frame_text(record_json: &str) -> String {
    format!("{{\"type\":\"iteration\",\"record\":{record_json}}}")
}

/// `{"type":"history","records":[…]}` from serialized records.
pub fn history_frame_text(records_json: &[String]) -> String {
    let mut s = String::with_capacity(32 + records_json.iter().map(|r| r.len() + 1).sum::<usize>());
    s.push_str("{\"type\":\"history\",\"records\":[");
    for (i, r) in records_json.iter().enumerate() {
        if i > 0 {
            s.push(',');
        }
        s.push_str(r);
    }
    s.push_str("]}");
    s
}

/// Everything needed to continue a run: stored after every iteration.
#[derive(Debug, Serialize, Deserialize)]
pub struct Checkpoint {
    /// The tuner's complete state.
    pub tuner: Tuner,
    /// The device's state (`null` for devices without restorable state).
    pub device: Value,
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
    /// Store or internal failure (500).
    #[error("{0}")]
    Internal(String),
}

impl From<StoreError> for RunError {
    fn from(e: StoreError) -> Self {
        match e {
            StoreError::NotFound(id) => RunError::NotFound(id),
            e => RunError::Internal(e.to_string()),
        }
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
    control: Mutex<Option<mpsc::UnboundedSender<ControlMsg>>>,
}

impl RunHandle {
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

    fn set_summary(&self, f: impl FnOnce(&mut RunSummary)) -> RunSummary {
        let mut s = self.summary.lock().unwrap_or_else(|p| p.into_inner());
        f(&mut s);
        s.clone()
    }

    fn control_sender(&self) -> Option<mpsc::UnboundedSender<ControlMsg>> {
        self.control
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .filter(|s| !s.is_closed())
            .cloned()
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
}

impl Default for ManagerOptions {
    fn default() -> Self {
        Self {
            iteration_delay: Duration::from_millis(0),
            viewer_buffer: 256,
            recover: true,
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

impl Manager {
    /// Load all runs from the store. Runs left running by a previous process are
    /// marked `Interrupted`; no task is started for them until they are resumed.
    pub fn open(store: Arc<Store>, options: ManagerOptions) -> Result<Arc<Self>, RunError> {
        if options.recover {
            store.mark_interrupted()?;
        }
        let mut runs = BTreeMap::new();
        for stored in store.list_runs()? {
            let config: RunConfig = match serde_json::from_str(&stored.config_json) {
                Ok(c) => c,
                Err(e) => {
                    eprintln!(
                        "warning: run {} has an unreadable config ({e}); skipped",
                        stored.summary.id
                    );
                    continue;
                }
            };
            let id = stored.summary.id;
            runs.insert(
                id,
                Arc::new(RunHandle {
                    id,
                    config,
                    summary: Mutex::new(stored.summary),
                    tx: broadcast::channel(options.viewer_buffer.max(1)).0,
                    control: Mutex::new(None),
                }),
            );
        }
        Ok(Arc::new(Self {
            store,
            runs: Mutex::new(runs),
            options,
            bridges: Links::default(),
        }))
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
        let sim = SimulationRun::new(config.simulation.clone())
            .map_err(|e| RunError::Invalid(e.to_string()))?;
        let checkpoint = Checkpoint {
            tuner: sim.tuner().clone(),
            device: SimulatorDevice::new(sim.device().clone())
                .checkpoint()
                .map_err(|e| RunError::Internal(e.to_string()))?,
        };
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
        let handle = Arc::new(RunHandle {
            id,
            summary: Mutex::new(RunSummary {
                id,
                name: config.name().to_string(),
                status,
                iterations: 0,
                lab_seconds: 0.0,
                tuned: false,
            }),
            config,
            tx: broadcast::channel(self.options.viewer_buffer.max(1)).0,
            control: Mutex::new(None),
        });
        self.runs().insert(id, handle.clone());
        let mode = if start_paused {
            Mode::Paused
        } else {
            Mode::Running
        };
        self.spawn_task(handle.clone(), checkpoint, mode);
        Ok(handle.summary())
    }

    /// Apply a control command to run `id`.
    pub async fn control(
        self: &Arc<Self>,
        id: u64,
        command: ControlCommand,
    ) -> Result<RunSummary, RunError> {
        let handle = self.get(id)?;
        if let Some(sender) = handle.control_sender() {
            let (reply, rx) = oneshot::channel();
            if sender
                .send(ControlMsg {
                    command: command.clone(),
                    reply,
                })
                .is_ok()
            {
                if let Ok(result) = rx.await {
                    return result;
                }
            }
            // The task ended in between: handle the command offline.
        }
        self.control_offline(handle, command).await
    }

    async fn control_offline(
        self: &Arc<Self>,
        handle: Arc<RunHandle>,
        command: ControlCommand,
    ) -> Result<RunSummary, RunError> {
        let status = handle.summary().status;
        match command {
            ControlCommand::Resume | ControlCommand::Step => {
                if status == RunStatus::Stopped {
                    return Err(RunError::Conflict(format!(
                        "run {} was stopped and cannot be resumed",
                        handle.id
                    )));
                }
                let checkpoint = self.load_checkpoint(handle.id).await?;
                let mode = if command == ControlCommand::Step {
                    Mode::Step
                } else {
                    Mode::Running
                };
                let summary = self.set_status(&handle, RunStatus::Running).await?;
                self.spawn_task(handle, checkpoint, mode);
                Ok(summary)
            }
            ControlCommand::Pause => match status {
                RunStatus::Interrupted | RunStatus::Failed { .. } => {
                    self.set_status(&handle, RunStatus::Paused).await
                }
                RunStatus::Paused => Ok(handle.summary()),
                _ => Err(RunError::Conflict(format!(
                    "run {} is not running (status {})",
                    handle.id,
                    status_name(&status)
                ))),
            },
            ControlCommand::Stop => match status {
                RunStatus::Finished | RunStatus::Stopped => Ok(handle.summary()),
                _ => self.set_status(&handle, RunStatus::Stopped).await,
            },
            ControlCommand::SetTarget {
                parameter,
                target,
                tolerance,
            } => {
                let mut checkpoint = self.load_checkpoint(handle.id).await?;
                checkpoint
                    .tuner
                    .set_target(&parameter, target, tolerance)
                    .map_err(|e| RunError::Invalid(e.to_string()))?;
                let json = serde_json::to_string(&checkpoint)
                    .map_err(|e| RunError::Internal(e.to_string()))?;
                let store = self.store.clone();
                let id = handle.id;
                blocking(move || store.save_checkpoint(id, &json)).await?;
                Ok(handle.summary())
            }
        }
    }

    async fn load_checkpoint(&self, id: u64) -> Result<Checkpoint, RunError> {
        let store = self.store.clone();
        let json = blocking(move || store.checkpoint(id)).await?;
        serde_json::from_str(&json)
            .map_err(|e| RunError::Internal(format!("run {id}: unreadable checkpoint: {e}")))
    }

    async fn set_status(
        &self,
        handle: &RunHandle,
        status: RunStatus,
    ) -> Result<RunSummary, RunError> {
        let store = self.store.clone();
        let id = handle.id;
        let st = status.clone();
        blocking(move || store.set_status(id, &st)).await?;
        let summary = handle.set_summary(|s| s.status = status);
        let _ = handle.tx.send(Frame::message(&ServerMessage::Status {
            run: summary.clone(),
        }));
        Ok(summary)
    }

    /// Commit one iteration record (JSON) with the checkpoint taken right after
    /// it, then update the summary and broadcast it to the viewers. Returns the
    /// record's seq. This is the only path by which iterations reach viewers.
    async fn commit_and_broadcast(
        &self,
        handle: &RunHandle,
        record_json: String,
        checkpoint_json: String,
        lab_seconds: f64,
        tuned: bool,
    ) -> Result<u64, RunError> {
        let seq = handle.summary().iterations;
        let store = self.store.clone();
        let id = handle.id;
        let text = iteration_frame_text(&record_json);
        blocking(move || {
            store.commit_iteration(id, seq, &record_json, &checkpoint_json, lab_seconds, tuned)
        })
        .await?;
        handle.set_summary(|s| {
            s.iterations = seq + 1;
            s.lab_seconds = lab_seconds;
            s.tuned = tuned;
        });
        let _ = handle.tx.send(Frame {
            seq: Some(seq),
            text: Utf8Bytes::from(text),
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
        if handle.control_sender().is_some() {
            return Err(RunError::Conflict(format!(
                "run {id} has a live task; stop it before publishing external records"
            )));
        }
        let json = serde_json::to_string(record).map_err(|e| RunError::Internal(e.to_string()))?;
        self.commit_and_broadcast(
            &handle,
            json,
            checkpoint_json,
            record.lab_seconds,
            record.tuned,
        )
        .await
    }

    /// Stop run `id` (if live) and delete it with its iterations.
    pub async fn delete(self: &Arc<Self>, id: u64) -> Result<(), RunError> {
        let handle = self.get(id)?;
        if handle.control_sender().is_some() {
            // Stop the task first so it does not write after the delete.
            let _ = self.control(id, ControlCommand::Stop).await;
        }
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

    /// Wait until run `id` has no live task (finished, stopped, paused-and-idle
    /// does not count: only task exit). For the headless CLI and tests.
    pub async fn wait_idle(&self, id: u64) -> Result<RunSummary, RunError> {
        loop {
            let handle = self.get(id)?;
            if handle.control_sender().is_none() {
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
            if h.control_sender().is_some() {
                let _ = self.store.set_status(h.id, &RunStatus::Interrupted);
            }
        }
    }

    fn spawn_task(self: &Arc<Self>, handle: Arc<RunHandle>, checkpoint: Checkpoint, mode: Mode) {
        let (tx, rx) = mpsc::unbounded_channel();
        *handle.control.lock().unwrap_or_else(|p| p.into_inner()) = Some(tx);
        let delay = handle
            .config
            .backend
            .iteration_delay_ms
            .map(Duration::from_millis)
            .unwrap_or(self.options.iteration_delay);
        let manager = self.clone();
        let bridge = handle
            .config
            .backend
            .uses_bridge()
            .then(|| self.bridges.get(handle.id));
        tokio::spawn(async move {
            let device = match device::open(&handle.config, checkpoint.device, bridge) {
                Ok(d) => d,
                Err(e) => {
                    let _ = manager
                        .set_status(
                            &handle,
                            RunStatus::Failed {
                                message: format!("cannot restore device state: {e}"),
                            },
                        )
                        .await;
                    return;
                }
            };
            let mut task = RunTask {
                manager: manager.clone(),
                handle: handle.clone(),
                tuner: checkpoint.tuner,
                device,
                control: rx,
                mode,
                delay,
                deferred: Vec::new(),
                recovery: None,
            };
            let end = task.run().await;
            // Close the control channel before the final status so that any
            // command racing with the exit is handled offline.
            *handle.control.lock().unwrap_or_else(|p| p.into_inner()) = None;
            drop(task);
            if let Some(status) = end {
                if let Err(e) = manager.set_status(&handle, status).await {
                    eprintln!("run {}: cannot store final status: {e}", handle.id);
                }
            }
        });
    }
}

/// Short name of a status.
pub fn status_name(s: &RunStatus) -> &'static str {
    match s {
        RunStatus::Running => "running",
        RunStatus::Paused => "paused",
        RunStatus::Finished => "finished",
        RunStatus::Stopped => "stopped",
        RunStatus::Interrupted => "interrupted",
        RunStatus::Failed { .. } => "failed",
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Running,
    /// Run one iteration, then pause.
    Step,
    Paused,
}

/// Result of handling a control message.
enum Flow {
    Continue,
    Stop,
}

struct RunTask {
    manager: Arc<Manager>,
    handle: Arc<RunHandle>,
    tuner: Tuner,
    device: Box<dyn Device>,
    control: mpsc::UnboundedReceiver<ControlMsg>,
    mode: Mode,
    delay: Duration,
    /// Target changes received mid-iteration, applied at the next boundary.
    deferred: Vec<ControlCommand>,
    /// While paused by a device fault: resolves when the device recovered by
    /// itself (the lab bridge reconnected), which resumes the run.
    /// (In a `Mutex` only to make the task `Sync`; it is polled through `get_mut`.)
    recovery: Option<Mutex<BoxFuture<'static, ()>>>,
}

impl RunTask {
    /// Drive the tuner until it finishes, is stopped or fails. Returns the final
    /// status to store (`None` if already stored).
    async fn run(&mut self) -> Option<RunStatus> {
        if self.mode == Mode::Paused {
            self.publish_status(RunStatus::Paused).await;
        }
        let mut at_boundary = true;
        loop {
            // Control: at a boundary everything applies; mid-iteration only pause/stop.
            while let Ok(msg) = self.control.try_recv() {
                if let Flow::Stop = self.handle_control(msg, at_boundary).await {
                    return Some(RunStatus::Stopped);
                }
            }
            if at_boundary {
                if let Err(e) = self.apply_deferred().await {
                    return Some(failed(e));
                }
            }
            while self.mode == Mode::Paused {
                let next = match self.recovery.as_mut() {
                    Some(recovered) => tokio::select! {
                        msg = self.control.recv() => Some(msg),
                        _ = recovered.get_mut().unwrap_or_else(|p| p.into_inner()) => None,
                    },
                    None => Some(self.control.recv().await),
                };
                match next {
                    Some(Some(msg)) => {
                        if let Flow::Stop = self.handle_control(msg, at_boundary).await {
                            return Some(RunStatus::Stopped);
                        }
                    }
                    Some(None) => return None,
                    None => {
                        // The device recovered by itself: re-issue the request.
                        self.recovery = None;
                        self.mode = Mode::Running;
                        self.publish_status(RunStatus::Running).await;
                    }
                }
                if at_boundary {
                    if let Err(e) = self.apply_deferred().await {
                        return Some(failed(e));
                    }
                }
            }
            match self.tuner.poll() {
                Action::Request(request) => {
                    at_boundary = false;
                    if let Request::SetVoltages { voltages_mv } = &request {
                        if let Err(e) = self
                            .tuner
                            .safety()
                            .check(self.tuner.voltages_mv(), voltages_mv)
                        {
                            return Some(failed(format!("safety limits refused a request: {e}")));
                        }
                    }
                    let response = self.device.execute(request).await;
                    if let Err(e) = self.tuner.feed(response) {
                        // The tuner keeps the request (its state is unchanged):
                        // pause with the reason and re-issue it on resume.
                        self.fault(e.to_string()).await;
                    }
                }
                Action::Iteration(record) => {
                    at_boundary = true;
                    if let Err(e) = self.commit(record).await {
                        return Some(failed(e));
                    }
                    if self.mode == Mode::Step {
                        self.mode = Mode::Paused;
                        self.publish_status(RunStatus::Paused).await;
                    } else if let Flow::Stop = self.pace().await {
                        return Some(RunStatus::Stopped);
                    }
                }
                Action::Finished => return Some(RunStatus::Finished),
            }
        }
    }

    /// A device fault: pause with a clear message, keeping the tuner's
    /// outstanding request and everything measured so far in this iteration.
    async fn fault(&mut self, message: String) {
        self.recovery = Some(Mutex::new(self.device.recovered()));
        self.mode = Mode::Paused;
        self.publish_status(RunStatus::Failed {
            message: format!(
                "paused by a device fault: {message} — the request is kept and re-issued on resume; no data lost"
            ),
        })
        .await;
    }

    fn checkpoint_json(&self) -> Result<String, String> {
        let device = self
            .device
            .checkpoint()
            .map_err(|e| format!("cannot serialize device state: {e}"))?;
        #[derive(Serialize)]
        struct CheckpointRef<'a> {
            tuner: &'a Tuner,
            device: Value,
        }
        serde_json::to_string(&CheckpointRef {
            tuner: &self.tuner,
            device,
        })
        .map_err(|e| format!("cannot serialize tuner state: {e}"))
    }

    /// Commit, then broadcast.
    async fn commit(&mut self, record: IterationRecord) -> Result<(), String> {
        let checkpoint = self.checkpoint_json()?;
        let record_json =
            serde_json::to_string(&record).map_err(|e| format!("cannot serialize record: {e}"))?;
        self.manager
            .commit_and_broadcast(
                &self.handle,
                record_json,
                checkpoint,
                record.lab_seconds,
                record.tuned,
            )
            .await
            .map(|_| ())
            .map_err(|e| format!("cannot commit iteration: {e}"))
    }

    /// Wall-clock pause between iterations, answering control messages meanwhile.
    async fn pace(&mut self) -> Flow {
        if self.delay.is_zero() {
            return Flow::Continue;
        }
        let deadline = tokio::time::Instant::now() + self.delay;
        loop {
            tokio::select! {
                _ = tokio::time::sleep_until(deadline) => return Flow::Continue,
                msg = self.control.recv() => match msg {
                    Some(msg) => {
                        if let Flow::Stop = self.handle_control(msg, true).await {
                            return Flow::Stop;
                        }
                        if self.mode != Mode::Running {
                            return Flow::Continue;
                        }
                    }
                    None => return Flow::Continue,
                }
            }
        }
    }

    async fn publish_status(&self, status: RunStatus) -> RunSummary {
        match self.manager.set_status(&self.handle, status).await {
            Ok(s) => s,
            Err(e) => {
                eprintln!("run {}: cannot store status: {e}", self.handle.id);
                self.handle.summary()
            }
        }
    }

    async fn handle_control(&mut self, msg: ControlMsg, at_boundary: bool) -> Flow {
        let ControlMsg { command, reply } = msg;
        let (result, flow) = match command {
            ControlCommand::Pause => {
                // A user's pause is not lifted by a device recovering.
                self.recovery = None;
                self.mode = Mode::Paused;
                (
                    Ok(self.publish_status(RunStatus::Paused).await),
                    Flow::Continue,
                )
            }
            ControlCommand::Resume => {
                self.recovery = None;
                self.mode = Mode::Running;
                (
                    Ok(self.publish_status(RunStatus::Running).await),
                    Flow::Continue,
                )
            }
            ControlCommand::Step => {
                self.recovery = None;
                self.mode = Mode::Step;
                (
                    Ok(self.publish_status(RunStatus::Running).await),
                    Flow::Continue,
                )
            }
            ControlCommand::Stop => {
                let summary = self.handle.set_summary(|s| s.status = RunStatus::Stopped);
                (Ok(summary), Flow::Stop)
            }
            cmd @ ControlCommand::SetTarget { .. } => {
                if at_boundary {
                    (self.set_target(&cmd).await, Flow::Continue)
                } else {
                    // Validate now on a copy, apply at the iteration boundary.
                    let mut probe = self.tuner.clone();
                    let r = apply_target(&mut probe, &cmd).map(|_| self.handle.summary());
                    if r.is_ok() {
                        self.deferred.push(cmd);
                    }
                    (r, Flow::Continue)
                }
            }
        };
        let _ = reply.send(result);
        flow
    }

    async fn set_target(&mut self, cmd: &ControlCommand) -> Result<RunSummary, RunError> {
        apply_target(&mut self.tuner, cmd)?;
        let json = self.checkpoint_json().map_err(RunError::Internal)?;
        let store = self.manager.store.clone();
        let id = self.handle.id;
        blocking(move || store.save_checkpoint(id, &json)).await?;
        Ok(self.handle.summary())
    }

    async fn apply_deferred(&mut self) -> Result<(), String> {
        for cmd in std::mem::take(&mut self.deferred) {
            self.set_target(&cmd).await.map_err(|e| e.to_string())?;
        }
        Ok(())
    }
}

fn apply_target(tuner: &mut Tuner, cmd: &ControlCommand) -> Result<(), RunError> {
    if let ControlCommand::SetTarget {
        parameter,
        target,
        tolerance,
    } = cmd
    {
        tuner
            .set_target(parameter, *target, *tolerance)
            .map_err(|e| RunError::Invalid(e.to_string()))?;
    }
    Ok(())
}

fn failed(message: String) -> RunStatus {
    RunStatus::Failed { message }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hand_built_frames_match_serde() {
        let rec = r#"{"iteration":3}"#;
        let v: Value = serde_json::from_str(&iteration_frame_text(rec)).unwrap();
        assert_eq!(v["type"], "iteration");
        assert_eq!(v["record"]["iteration"], 3);
        let h: Value =
            serde_json::from_str(&history_frame_text(&[rec.to_string(), rec.to_string()])).unwrap();
        assert_eq!(h["records"].as_array().unwrap().len(), 2);
        let empty = serde_json::to_string(&ServerMessage::History { records: vec![] }).unwrap();
        assert_eq!(history_frame_text(&[]), empty);
    }
}
