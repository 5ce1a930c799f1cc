//! A run's task: the async shell around the core's [`RunSession`]. It owns
//! nothing of the run's logic — lifecycle, deferred targets, faults and the
//! safety guard are the session's — and only does IO: execute requests on
//! the device, commit records with checkpoints, publish statuses, sleep,
//! and hand control commands to the session, also while a request is at the
//! device. Every store write carries the task's generation: a task that has
//! been superseded cannot write and exits, and so does a task whose control
//! channel closes.

use std::sync::Arc;
use std::time::Duration;

use serde::Serialize;
use serde_json::Value;
use spintune::protocol::{ControlCommand, Response, RunStatus};
use spintune::session::Output;
use tokio::sync::mpsc;

use super::any_session::AnySession;
use super::checkpoint::CHECKPOINT_VERSION;
use super::error::RunError;
use super::handle::{ControlMsg, RunHandle};
use super::persist;
use crate::devices::Device;
use crate::store::Store;

pub(super) struct RunTask {
    pub store: Arc<Store>,
    pub handle: Arc<RunHandle>,
    pub session: AnySession,
    pub device: Box<dyn Device>,
    pub control: mpsc::Receiver<ControlMsg>,
    pub generation: u64,
}

/// Why the task loop ended early.
enum Exit {
    /// Superseded or detached: leave the stored state alone.
    Quiet,
    /// The store refused a write: the run cannot continue.
    Failed(String),
}

impl RunTask {
    /// Drive the session until it is done; store `failed` if the store breaks.
    pub async fn run(mut self) {
        if let Err(Exit::Failed(message)) = self.drive().await {
            if self.session.status() == RunStatus::Stopped {
                // A user stopped it and the store refused the status: it is
                // stopped all the same (nothing more reaches the device), and
                // stored as such when the store allows.
                persist::settle_stopped(&self.store, &self.handle, Some(self.generation)).await;
            } else {
                persist::fail_run(&self.store, &self.handle, self.generation, message).await;
            }
        }
    }

    async fn drive(&mut self) -> Result<(), Exit> {
        loop {
            match self.session.poll() {
                Output::Execute(request) => {
                    let response = {
                        let fut = self.device.execute(request);
                        tokio::pin!(fut);
                        loop {
                            tokio::select! {
                                r = &mut fut => break r,
                                msg = self.control.recv() => {
                                    let msg = msg.ok_or(Exit::Quiet)?;
                                    if handle_control(&mut self.session, &self.handle, msg) {
                                        // Stop: abandon the request (a ramp stops between
                                        // stages); nothing further reaches the device.
                                        break Response::error("stopped while the request was at the device");
                                    }
                                }
                            }
                        }
                    };
                    self.session
                        .feed(response)
                        .map_err(|e| Exit::Failed(format!("internal: {e}")))?;
                }
                Output::Commit(record) => {
                    let checkpoint = self.checkpoint_json()?;
                    let record_json = serde_json::to_string(&*record)
                        .map_err(|e| Exit::Failed(format!("cannot serialize record: {e}")))?;
                    persist::commit_and_broadcast(
                        &self.store,
                        &self.handle,
                        Some(self.generation),
                        Arc::from(record),
                        record_json,
                        checkpoint,
                    )
                    .await
                    .map_err(exit)?;
                }
                Output::Save => {
                    let checkpoint = self.checkpoint_json()?;
                    let store = self.store.clone();
                    let (id, g) = (self.handle.id, self.generation);
                    persist::blocking(move || store.save_checkpoint(id, Some(g), &checkpoint))
                        .await
                        .map_err(exit)?;
                }
                Output::Publish(status) => {
                    persist::store_status(
                        &self.store,
                        &self.handle,
                        Some(self.generation),
                        status.clone(),
                    )
                    .await
                    .map_err(exit)?;
                    let summary = self.handle.set_summary(|s| s.status = status);
                    self.handle.broadcast_status(summary);
                }
                Output::Sleep { ms } => {
                    let deadline = tokio::time::Instant::now() + Duration::from_millis(ms);
                    loop {
                        tokio::select! {
                            _ = tokio::time::sleep_until(deadline) => break,
                            msg = self.control.recv() => {
                                handle_control(&mut self.session, &self.handle, msg.ok_or(Exit::Quiet)?);
                                if self.session.status() != RunStatus::Running {
                                    break;
                                }
                            }
                        }
                    }
                }
                Output::Wait => {
                    // Only a fault the policy lets clear on reconnect waits for
                    // the device; every other waits for a person.
                    let awaits_reconnect = self.session.awaits_reconnect();
                    let recovered = self.device.recovered();
                    tokio::select! {
                        msg = self.control.recv() => {
                            handle_control(&mut self.session, &self.handle, msg.ok_or(Exit::Quiet)?);
                        }
                        _ = recovered, if awaits_reconnect => {
                            self.session.device_recovered();
                        }
                    }
                }
                Output::Done(_) => return Ok(()),
            }
        }
    }

    fn checkpoint_json(&self) -> Result<String, Exit> {
        let device = self
            .device
            .checkpoint()
            .map_err(|e| Exit::Failed(format!("cannot serialize device state: {e}")))?;
        #[derive(Serialize)]
        struct CheckpointRef<'a, S> {
            version: u32,
            #[serde(rename = "session")]
            cell: Option<&'a S>,
            #[serde(skip_serializing_if = "Option::is_none")]
            array_session:
                Option<&'a spintune::session::RunSession<spintune::tuner::array_run::ArrayRun>>,
            device: Value,
        }
        let (cell, array_session) = match &self.session {
            AnySession::Cell(s) => (Some(&**s), None),
            AnySession::Array(s) => (None, Some(&**s)),
        };
        serde_json::to_string(&CheckpointRef {
            version: CHECKPOINT_VERSION,
            cell,
            array_session,
            device,
        })
        .map_err(|e| Exit::Failed(format!("cannot serialize session state: {e}")))
    }
}

fn exit(e: RunError) -> Exit {
    if e.is_stale() || matches!(e, RunError::NotFound(_)) {
        Exit::Quiet
    } else {
        Exit::Failed(format!("the store refused a write: {e}"))
    }
}

/// Apply one control command to the session and answer it at once with the
/// new status (it is stored and broadcast by the next `Publish`). Returns
/// whether the command was a stop.
fn handle_control(session: &mut AnySession, handle: &RunHandle, msg: ControlMsg) -> bool {
    let ControlMsg { command, reply } = msg;
    let stop = command == ControlCommand::Stop;
    let result = session
        .control(&command)
        .map(|status| handle.set_summary(|s| s.status = status))
        .map_err(|e| match e {
            spintune::session::ControlError::Conflict { .. } => RunError::Conflict(e.to_string()),
            e => RunError::Invalid(e.to_string()),
        });
    let _ = reply.send(result);
    stop
}
