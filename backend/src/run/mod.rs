//! Runs: many concurrent runs, each driven by at most one task ([`task`])
//! around the core's [`RunSession`](spintune::session::RunSession).
//!
//! Per iteration the task (1) commits the record and the checkpoint (session
//! and device state) to the [`Store`](crate::store::Store) in one
//! transaction, (2) updates the run's summary and its ring of recent
//! summaries ([`RECENT_SUMMARIES`]), (3) broadcasts the pre-serialized
//! `ServerMessage::Iteration` ([`viewer_update`]: summary and full text,
//! shared by all viewers) over a bounded `tokio::sync::broadcast` channel
//! ([`ManagerOptions::viewer_buffer`] updates). A slow viewer never blocks the
//! run: it lags, is told so, and is sent the newest page of summaries (see
//! [`crate::server`]).
//!
//! One run, one task (ARCHITECTURE.md, invariant 6): starting and resuming
//! a run go through the run's lifecycle lock, so concurrent `resume`s start
//! one task and hand the others to it; each task claims a new generation in
//! the store ([`Store::claim`](crate::store::Store::claim)) and every write
//! it makes is checked against it, so a superseded task (also one in another
//! process sharing the store) cannot write and exits. A task whose control
//! channel closes exits too.
//!
//! A run without a live task (interrupted by a restart, faulted and detached,
//! failed, paused after a restart) is restarted from its last stored
//! checkpoint on `Resume`/`Step`; the restored session reads every gate back
//! from the instrument before it moves one.
//!
//! | file | what it is |
//! |---|---|
//! | [`manager`] | [`Manager`]: the runs by id; create, control, start a task, delete |
//! | [`handle`] | [`RunHandle`](handle::RunHandle): one run's summary, viewers channel, recent summaries, control channel, lifecycle lock |
//! | [`task`] | the async shell around the run's `RunSession` |
//! | [`persist`] | a run's writes: the store first, then memory and viewers |
//! | [`checkpoint`] | [`Checkpoint`](checkpoint::Checkpoint): schema, version, migration of older checkpoints |
//! | [`error`] | [`RunError`] |
//! | [`viewer_update`] | [`ViewerUpdate`]: what a run broadcasts to its viewers, pre-serialized, with its typed [`RunEvent`] |
//! | [`viewer_limits`] | limits of a run's viewer sockets |
//!
//! Imports go one way: `manager` → `task` → `persist` → `handle` →
//! `viewer_update`, `error`; nothing here imports `crate::server`.

mod any_session;
mod checkpoint;
mod error;
mod handle;
mod manager;
mod persist;
mod task;
pub mod viewer_limits;
mod viewer_update;

pub use error::RunError;
pub use handle::ViewerSlot;
pub use manager::{Manager, ManagerOptions};
pub use viewer_limits::ViewerLimits;
pub use viewer_update::{history_message_json, RunEvent, ViewerUpdate};
// Named by ARCHITECTURE.md (invariant 8, the bounds) as `run::…`.
#[allow(unused_imports)]
pub use {
    handle::ALERTS_PER_VIEWER, handle::RECENT_ALERTS, handle::RECENT_SUMMARIES,
    manager::CONTROL_QUEUE,
};
