//! The run manager ([`Manager`]): all runs of one server (or one headless
//! `spintune run`), by id. It creates runs, applies control commands (handed
//! to a run's live task, or applied to the stored run under the run's
//! lifecycle lock), starts at most one task per run ([`super::task`]) with a
//! new store generation, and deletes, detaches and waits for runs.
//!
//! Following one run's config: [`Manager::create`] validates it, builds the
//! session ([`session_config`]) and the first [`Checkpoint`], stores the run
//! and calls [`Manager::start_task`], which opens the device
//! ([`devices::open`]) and spawns the [`RunTask`].

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use spintune::lifecycle::Acceptance;
use spintune::protocol::{ControlCommand, IterationRecord, RunStatus, RunSummary, ServerMessage};
use spintune::session::{RunSession, SessionConfig};
use tokio::sync::{mpsc, oneshot};

use super::any_session::AnySession;
use super::checkpoint::Checkpoint;
use super::error::RunError;
use super::handle::{ControlMsg, RunHandle};
use super::persist::{self, blocking};
use super::task::RunTask;
use super::viewer_limits::ViewerLimits;
use super::viewer_update::ViewerUpdate;
use crate::alerts::AlertSink;
use crate::config::{DriverKind, RunConfig};
use crate::devices::bridge::{BridgeLink, Links};
use crate::devices::{self, Device, SimulatorDevice};
use crate::store::Store;

/// Control commands queued for one run's task (bounded by construction).
pub const CONTROL_QUEUE: usize = 16;

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
    /// The alert webhook's queue (`--alert-webhook`); `None`: alerts go to
    /// viewers only.
    pub alerts: Option<AlertSink>,
}

impl Default for ManagerOptions {
    fn default() -> Self {
        Self {
            iteration_delay: Duration::from_millis(0),
            viewer_buffer: 256,
            recover: true,
            viewers: ViewerLimits::default(),
            alerts: None,
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
                    options.alerts.clone(),
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
        let scfg = session_config(&config, self.options.iteration_delay);
        let (mut session, device) = match &config.array {
            Some(array) => {
                let invalid = |e: spintune::config_error::ConfigError| {
                    RunError::Invalid(e.within("array").to_string())
                };
                let plan = array.build_plan().map_err(invalid)?;
                // On the lab bridge nothing is simulated: the checkpoint
                // holds no device state (the bridge driver ignores it).
                let device = match config.backend.driver {
                    DriverKind::Simulator => Some(SimulatorDevice::array(
                        array.build_world().map_err(invalid)?,
                    )),
                    _ => None,
                };
                (
                    AnySession::Array(Box::new(RunSession::from_tuner(plan, scfg))),
                    device,
                )
            }
            None => {
                let sim = &config.simulation;
                sim.validate()
                    .map_err(|e| RunError::Invalid(e.to_string()))?;
                let session = RunSession::new(sim.tuner.clone(), scfg)
                    .map_err(|e| RunError::Invalid(e.to_string()))?;
                let device = sim
                    .simulated_device()
                    .map_err(|e| RunError::Invalid(e.to_string()))?;
                (
                    AnySession::Cell(Box::new(session)),
                    Some(SimulatorDevice::new(device)),
                )
            }
        };
        if start_paused {
            session
                .control(&ControlCommand::Pause)
                .map_err(|e| RunError::Internal(e.to_string()))?;
        }
        let device_state = match &device {
            Some(d) => d
                .checkpoint()
                .map_err(|e| RunError::Internal(e.to_string()))?,
            None => serde_json::Value::Null,
        };
        let checkpoint = Checkpoint::new(session, device_state);
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
            self.options.alerts.clone(),
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
            ControlCommand::Pause => {
                persist::set_status_offline(&self.store, handle, RunStatus::Paused).await
            }
            ControlCommand::Stop => Ok(persist::settle_stopped(&self.store, handle, None).await),
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
                // (the checkpoint was written with the tuned record, before
                // the session saw that its plan had finished: the plan says)
                let revived = status == RunStatus::Finished && !session.plan_done();
                let json = serde_json::to_string(&Checkpoint::new(session, device))
                    .map_err(|e| RunError::Internal(e.to_string()))?;
                let store = self.store.clone();
                let id = handle.id;
                blocking(move || store.save_checkpoint(id, None, &json)).await?;
                if revived {
                    return persist::set_status_offline(&self.store, handle, RunStatus::Paused)
                        .await;
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
                persist::set_status_offline(&self.store, handle, new_status).await
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
            persist::fail_run(&self.store, handle, generation, message).await;
        }
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
        persist::commit_and_broadcast(
            &self.store,
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
            h.broadcast(ViewerUpdate::message(&ServerMessage::Error {
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
        let backend = &handle.config.backend;
        let gates = handle.config.gates();
        let settings = devices::DeviceSettings {
            driver: backend.driver,
            scpi: backend.scpi.as_ref(),
            bridge: &backend.bridge,
            gates: &gates,
            array: handle.config.array.is_some(),
        };
        let device: Box<dyn Device> = match devices::open(settings, device_state, bridge) {
            Ok(d) => d,
            Err(e) => {
                let status = RunStatus::Failed {
                    message: format!("cannot open the device: {e}"),
                };
                persist::set_status_offline(&self.store, handle, status).await?;
                return Ok(());
            }
        };
        let (tx, rx) = mpsc::channel(CONTROL_QUEUE);
        handle.set_control(Some(tx.clone()));
        let task = RunTask {
            store: self.store.clone(),
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
            h.release_control(&tx);
        });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_panicking_run_task_fails_the_run_in_memory_and_in_the_store() {
        let dir = std::env::temp_dir().join(format!("spintune-panic-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let store = Arc::new(Store::open(&dir.join("p.db")).unwrap());
        let manager = Manager::open(store.clone(), ManagerOptions::default()).unwrap();
        let id = manager
            .create(RunConfig::recommended(), true)
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
}
