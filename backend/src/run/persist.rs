//! A run's writes: the store first, then the run's summary in memory and its
//! viewers. Used by the manager and by the run's task alike (neither depends
//! on the other for them). Store calls run off the async runtime
//! ([`blocking`]).

use std::sync::Arc;
use std::time::Duration;

use axum::extract::ws::Utf8Bytes;
use spintune::protocol::{IterationRecord, RunStatus, RunSummary};

use super::error::RunError;
use super::handle::RunHandle;
use super::viewer_update::{iteration_message_json, RunEvent, ViewerUpdate};
use crate::store::{Store, StoreError};

/// Waits before each attempt to store a run's `failed` status, ms.
const FAILED_STATUS_RETRY_MS: [u64; 3] = [0, 200, 1_000];

/// A `stopped` status the store refused is stored again every this many ms
/// (the run is stopped in memory at once: nothing reaches the device).
const STOPPED_STATUS_RETRY_MS: u64 = 2_000;

/// ... at most this many times (one hour); after that a restart lists the
/// run with its last stored status (never `running`: `interrupted`).
const STOPPED_STATUS_RETRIES: u32 = 1_800;

/// Run a store call on the blocking pool.
pub(super) async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, StoreError> + Send + 'static,
) -> Result<T, RunError> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| RunError::Internal(format!("store task failed: {e}")))?
        .map_err(RunError::from)
}

/// A run task failed (the store refused a write, or the task panicked):
/// the run is `failed` with `message`, in memory at once (nobody is told
/// `running`) and in the store if it takes the write (a few attempts).
/// If it does not, the message says so; a restart then lists the run as
/// `interrupted`, never `running`.
pub(super) async fn fail_run(
    store: &Arc<Store>,
    handle: &RunHandle,
    generation: u64,
    message: String,
) {
    let status = RunStatus::Failed {
        message: message.clone(),
    };
    let summary = handle.set_summary(|s| s.status = status.clone());
    handle.broadcast_status(summary);
    let mut last = None;
    for wait_ms in FAILED_STATUS_RETRY_MS {
        tokio::time::sleep(Duration::from_millis(wait_ms)).await;
        match store_status(store, handle, Some(generation), status.clone()).await {
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
pub(super) async fn settle_stopped(
    store: &Arc<Store>,
    handle: &Arc<RunHandle>,
    generation: Option<u64>,
) -> RunSummary {
    let summary = handle.set_summary(|s| s.status = RunStatus::Stopped);
    handle.broadcast_status(summary.clone());
    if store_status(store, handle, generation, RunStatus::Stopped)
        .await
        .is_ok()
    {
        return summary;
    }
    let (store, handle) = (store.clone(), handle.clone());
    tokio::spawn(async move {
        for _ in 0..STOPPED_STATUS_RETRIES {
            tokio::time::sleep(Duration::from_millis(STOPPED_STATUS_RETRY_MS)).await;
            if handle.summary().status != RunStatus::Stopped {
                return;
            }
            match store_status(&store, &handle, generation, RunStatus::Stopped).await {
                Ok(()) => return,
                Err(e) if e.is_stale() || matches!(e, RunError::NotFound(_)) => return,
                Err(_) => {}
            }
        }
    });
    summary
}

/// Store a status (with `generation`: only for that task), no broadcast.
pub(super) async fn store_status(
    store: &Arc<Store>,
    handle: &RunHandle,
    generation: Option<u64>,
    status: RunStatus,
) -> Result<(), RunError> {
    let store = store.clone();
    let id = handle.id;
    blocking(move || store.set_status(id, generation, &status)).await
}

/// Store a status of a run without a task, then update and broadcast its
/// summary.
pub(super) async fn set_status_offline(
    store: &Arc<Store>,
    handle: &RunHandle,
    status: RunStatus,
) -> Result<RunSummary, RunError> {
    store_status(store, handle, None, status.clone()).await?;
    let summary = handle.set_summary(|s| s.status = status);
    handle.broadcast_status(summary.clone());
    Ok(summary)
}

/// Commit one iteration record (JSON) with the checkpoint taken right after
/// it, then update the summary and broadcast it to the viewers. Returns the
/// record's seq. This is the only path by which iterations reach viewers.
pub(super) async fn commit_and_broadcast(
    store: &Arc<Store>,
    handle: &RunHandle,
    generation: Option<u64>,
    record: Arc<IterationRecord>,
    record_json: String,
    checkpoint_json: String,
) -> Result<u64, RunError> {
    let (lab_seconds, tuned) = (record.lab_seconds, record.tuned);
    let seq = handle.summary().iterations;
    let store = store.clone();
    let id = handle.id;
    let full = iteration_message_json(&record_json);
    let summary_json = serde_json::to_string(&record.summary())
        .map_err(|e| RunError::Internal(format!("cannot serialize a summary: {e}")))?;
    let text = iteration_message_json(&summary_json);
    let alerts = spintune::alert::record_alerts(handle.id, handle.config.name(), &record);
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
    handle.broadcast(ViewerUpdate {
        seq: Some(seq),
        text: Utf8Bytes::from(text),
        full: Some(Utf8Bytes::from(full)),
        event: RunEvent::Iteration(record),
    });
    for alert in alerts {
        handle.raise(alert);
    }
    Ok(seq)
}
