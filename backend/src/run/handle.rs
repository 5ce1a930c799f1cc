//! A run known to the manager ([`RunHandle`]): its config, its summary, the
//! broadcast channel of its live updates, the ring of its newest summaries
//! ([`RECENT_SUMMARIES`]), its open viewer sockets, the control channel of
//! its task (if one drives it) and its lifecycle lock. Every status change
//! and every committed record passes through here to its viewers, so this
//! is where the run's alerts are raised ([`spintune::alert`] decides;
//! [`RunHandle::raise`] sends them to the viewers and the webhook).

use std::collections::VecDeque;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use axum::extract::ws::Utf8Bytes;
use spintune::protocol::{Alert, ControlCommand, RunStatus, RunSummary, ServerMessage};
use tokio::sync::{broadcast, mpsc, oneshot};

use super::error::RunError;
use super::viewer_update::ViewerUpdate;
use crate::alerts::{now_rfc3339, AlertSink};
use crate::config::RunConfig;

/// Summaries of the newest iterations each run keeps in memory (one default
/// history page), so the page sent after `Hello`/`Lagged` needs no store read.
pub const RECENT_SUMMARIES: usize = spintune::protocol::DEFAULT_HISTORY_PAGE as usize;

/// Alert frames buffered per viewer socket that asked for alerts; a viewer
/// further behind skips the older ones.
pub const ALERTS_PER_VIEWER: usize = 16;

/// The newest alerts each run keeps in memory (since the server started):
/// a viewer that asks for alerts gets them first, so a dashboard opened
/// after a run needed a person still says so.
pub const RECENT_ALERTS: usize = 8;

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

/// A control command for a run's task, with where its answer goes.
pub(super) struct ControlMsg {
    pub(super) command: ControlCommand,
    pub(super) reply: oneshot::Sender<Result<RunSummary, RunError>>,
}

/// A run known to the manager (live task or not).
pub struct RunHandle {
    /// Run id.
    pub id: u64,
    /// The run's configuration.
    pub config: RunConfig,
    summary: Mutex<RunSummary>,
    tx: broadcast::Sender<ViewerUpdate>,
    /// The run's alerts (`ServerMessage::Alert`), apart from the live frames.
    alerts_tx: broadcast::Sender<ViewerUpdate>,
    /// The newest alert frames, at most [`RECENT_ALERTS`].
    recent_alerts: Mutex<VecDeque<Utf8Bytes>>,
    control: Mutex<Option<mpsc::Sender<ControlMsg>>>,
    /// Why the stored run is unreadable (`Some`: quarantined; listed, never driven).
    quarantine: Option<String>,
    /// Held while starting, resuming or controlling the run: at most one task.
    pub(super) lifecycle: tokio::sync::Mutex<()>,
    /// (seq, summary JSON) of the newest committed iterations, at most
    /// [`RECENT_SUMMARIES`].
    recent: Mutex<VecDeque<(u64, Utf8Bytes)>>,
    /// Open viewer sockets ([`RunHandle::add_viewer`]).
    viewer_sockets: Arc<AtomicUsize>,
    /// The status last broadcast (what a new one is compared with to
    /// decide an alert).
    last_status: Mutex<RunStatus>,
    /// The webhook's queue, if `--alert-webhook` is set.
    alerts: Option<AlertSink>,
}

impl RunHandle {
    pub(super) fn new(
        id: u64,
        config: RunConfig,
        summary: RunSummary,
        viewer_buffer: usize,
        alerts: Option<AlertSink>,
    ) -> Self {
        Self {
            id,
            config,
            last_status: Mutex::new(summary.status.clone()),
            alerts,
            summary: Mutex::new(summary),
            tx: broadcast::channel(viewer_buffer.max(1)).0,
            alerts_tx: broadcast::channel(ALERTS_PER_VIEWER).0,
            recent_alerts: Mutex::new(VecDeque::with_capacity(RECENT_ALERTS)),
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

    pub(super) fn remember_summary(&self, seq: u64, summary: Utf8Bytes) {
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
    pub(super) fn quarantined(
        id: u64,
        summary: RunSummary,
        error: String,
        viewer_buffer: usize,
    ) -> Self {
        Self {
            quarantine: Some(error),
            ..Self::new(id, RunConfig::recommended(), summary, viewer_buffer, None)
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

    /// Subscribe to the run's live updates.
    pub fn subscribe(&self) -> broadcast::Receiver<ViewerUpdate> {
        self.tx.subscribe()
    }

    /// Subscribe to the run's alerts (the viewers that asked for them):
    /// the receiver, and the newest alert frames raised before (oldest
    /// first, at most [`RECENT_ALERTS`]). An alert raised while this runs
    /// may come both ways; the dashboard lists an alert once.
    pub fn subscribe_alerts(&self) -> (broadcast::Receiver<ViewerUpdate>, Vec<Utf8Bytes>) {
        let rx = self.alerts_tx.subscribe();
        let recent = self
            .recent_alerts
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .cloned()
            .collect();
        (rx, recent)
    }

    /// Number of connected viewers.
    pub fn viewers(&self) -> usize {
        self.tx.receiver_count()
    }

    /// Whether a task drives the run in this process.
    pub fn is_live(&self) -> bool {
        self.control_sender().is_some()
    }

    pub(super) fn set_summary(&self, f: impl FnOnce(&mut RunSummary)) -> RunSummary {
        let mut s = self.summary.lock().unwrap_or_else(|p| p.into_inner());
        f(&mut s);
        s.clone()
    }

    /// Broadcast the run's status; then raise the alert the change raises,
    /// if any ([`spintune::alert::status_alert`], comparing with the status
    /// broadcast before).
    pub(super) fn broadcast_status(&self, run: RunSummary) {
        let previous = std::mem::replace(
            &mut *self.last_status.lock().unwrap_or_else(|p| p.into_inner()),
            run.status.clone(),
        );
        let alert = spintune::alert::status_alert(&previous, &run);
        self.broadcast(ViewerUpdate::message(&ServerMessage::Status { run }));
        if let Some(alert) = alert {
            self.raise(alert);
        }
    }

    /// Send `alert` to the run's viewers (those that subscribed to alerts)
    /// and queue it for the webhook; never waits.
    pub(super) fn raise(&self, alert: Alert) {
        let at = now_rfc3339();
        if let Some(sink) = &self.alerts {
            sink.offer(alert.clone(), at.clone());
        }
        let update = ViewerUpdate::message(&ServerMessage::Alert { alert, at });
        {
            let mut recent = self.recent_alerts.lock().unwrap_or_else(|p| p.into_inner());
            if recent.len() == RECENT_ALERTS {
                recent.pop_front();
            }
            recent.push_back(update.text.clone());
        }
        let _ = self.alerts_tx.send(update);
    }

    /// Send an update to the run's viewers (none listening is fine).
    pub(super) fn broadcast(&self, update: ViewerUpdate) {
        let _ = self.tx.send(update);
    }

    pub(super) fn control_sender(&self) -> Option<mpsc::Sender<ControlMsg>> {
        self.control
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .filter(|s| !s.is_closed())
            .cloned()
    }

    pub(super) fn set_control(&self, sender: Option<mpsc::Sender<ControlMsg>>) {
        *self.control.lock().unwrap_or_else(|p| p.into_inner()) = sender;
    }

    /// Clear the control channel if it is still `tx` (a task ending must not
    /// clear its successor's).
    pub(super) fn release_control(&self, tx: &mpsc::Sender<ControlMsg>) {
        let mut control = self.control.lock().unwrap_or_else(|p| p.into_inner());
        if control.as_ref().is_some_and(|c| c.same_channel(tx)) {
            *control = None;
        }
    }
}
