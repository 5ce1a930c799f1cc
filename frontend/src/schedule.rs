//! Chart draws coalesced per animation frame.
//!
//! A chart whose inputs changed asks for a draw with [`request`]; all draws
//! asked for before the next `requestAnimationFrame` callback run in that
//! callback, once each (a chart asking twice is drawn once, with its latest
//! job). So many iterations arriving within one frame (a burst of live
//! records, a page of history) cost one redraw per chart, and all charts of
//! one update are drawn together: one [`metrics`] update per frame that drew
//! anything.
//!
//! A frame draws charts until [`FRAME_BUDGET_MS`] of drawing is spent; the
//! charts still queued then are drawn in the next frame (first in line), so
//! that a change that redraws every chart's axes (e.g. the x window of a
//! live run growing a step) does not block the page for longer than a
//! frame. Each chart is drawn whole (its axes and data agree); only the
//! moment differs, by one frame (≈ 16 ms).
//!
//! Outside a browser (no `window`) the jobs run at once.

use std::cell::{Cell, RefCell};
use std::rc::Rc;

use wasm_bindgen::closure::Closure;
use wasm_bindgen::JsCast;

use crate::metrics;

/// Drawing time after which a frame leaves the remaining charts to the
/// next frame, ms (at least one chart is drawn per frame).
pub const FRAME_BUDGET_MS: f64 = 10.0;

/// A draw job of one chart.
pub type Job = Rc<dyn Fn()>;

thread_local! {
    /// Charts waiting for the next frame, in the order they asked, with their
    /// latest job.
    static QUEUE: RefCell<Vec<(u64, Job)>> = const { RefCell::new(Vec::new()) };
    /// Whether a frame callback is already requested.
    static SCHEDULED: Cell<bool> = const { Cell::new(false) };
    /// Next chart id.
    static NEXT_ID: Cell<u64> = const { Cell::new(1) };
}

/// A new id for a chart (unique within the page).
pub fn new_id() -> u64 {
    NEXT_ID.with(|n| {
        let id = n.get();
        n.set(id + 1);
        id
    })
}

/// Draw chart `id` with `job` in the next animation frame (replacing a job
/// it queued earlier in this frame).
pub fn request(id: u64, job: Job) {
    QUEUE.with(|q| {
        let mut q = q.borrow_mut();
        match q.iter_mut().find(|e| e.0 == id) {
            Some(e) => e.1 = job,
            None => q.push((id, job)),
        }
    });
    schedule_frame();
}

/// Ask for an animation frame to run the queue, unless one is asked for.
fn schedule_frame() {
    if SCHEDULED.with(|s| s.replace(true)) {
        return;
    }
    let Some(w) = web_sys::window() else {
        run_frame();
        return;
    };
    let cb = Closure::once_into_js(run_frame);
    if w.request_animation_frame(cb.unchecked_ref()).is_err() {
        run_frame();
    }
}

/// Forget a queued draw of chart `id` (the chart was removed).
pub fn cancel(id: u64) {
    QUEUE.with(|q| q.borrow_mut().retain(|e| e.0 != id));
}

/// Run the queued draws as one update, within [`FRAME_BUDGET_MS`] (see
/// the module doc); what is left is queued first for the next frame.
fn run_frame() {
    SCHEDULED.with(|s| s.set(false));
    let jobs = QUEUE.with(|q| std::mem::take(&mut *q.borrow_mut()));
    if jobs.is_empty() {
        return;
    }
    metrics::begin_update();
    let t0 = metrics::now_ms();
    let mut jobs = jobs.into_iter();
    for (_, job) in jobs.by_ref() {
        job();
        // NaN outside a browser: never over budget.
        if metrics::now_ms() - t0 >= FRAME_BUDGET_MS {
            break;
        }
    }
    let rest: Vec<(u64, Job)> = jobs.collect();
    metrics::end_update();
    metrics::publish();
    if !rest.is_empty() {
        QUEUE.with(|q| {
            let mut q = q.borrow_mut();
            // Charts that asked again meanwhile keep their newer job.
            let newer: Vec<(u64, Job)> = std::mem::take(&mut *q);
            let mut merged: Vec<(u64, Job)> = rest
                .into_iter()
                .filter(|(id, _)| newer.iter().all(|n| n.0 != *id))
                .collect();
            merged.extend(newer);
            *q = merged;
        });
        schedule_frame();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn ids_are_unique_and_cancel_drops_a_queued_job() {
        let (a, b) = (new_id(), new_id());
        assert_ne!(a, b);
        // Queue directly (no frame is requested) to test the bookkeeping.
        QUEUE.with(|q| q.borrow_mut().push((a, Rc::new(|| {}) as Job)));
        cancel(a);
        assert!(QUEUE.with(|q| q.borrow().iter().all(|e| e.0 != a)));
    }
}
