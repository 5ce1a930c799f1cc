//! [`LocalRunner`]: drives one in-browser run (session + simulated device)
//! through its session. Its records go into the [`RunHistory`] the page lends to
//! [`LocalRunner::advance`] (the one history type of the dashboard, as in the
//! live mode's client).

use spintune::driver::{Halt, SimulationRun, Step};
use spintune::parameter::Tolerance;
use spintune::protocol::{ControlCommand, IterationRecord, RunStatus};
use spintune::session::RunSession;
use spintune::sim::SimulatedDevice;
use spintune::tuner::Tuner;

use super::settings::LocalSettings;
use super::LocalError;
use crate::history::RunHistory;
use crate::landscape::Landscape;

/// Targets and tolerances of one record, per parameter.
type Targets = Vec<(Option<f64>, Option<f64>)>;

/// How far [`LocalRunner::advance_for`] got.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Progress {
    /// Iteration `k` completed and was recorded.
    Recorded(u64),
    /// The time slice ran out within an iteration (call again).
    Working,
    /// The run is over (finished or stopped).
    Over,
}

/// Drives a [`SimulationRun`] (session + simulated device) in time slices
/// of its steps, so the page never blocks for a whole iteration; every
/// change of the run's course goes through the session
/// ([`LocalRunner::control`]).
pub struct LocalRunner {
    run: SimulationRun,
    /// Targets of the latest record (a change resets [`LocalRunner::tuned_at`]).
    last_targets: Option<Targets>,
    /// First iteration at which every parameter was in band since the targets
    /// last changed (by the user or by the schedule).
    pub tuned_at: Option<u64>,
}

impl LocalRunner {
    /// Start from settings (the session starts running).
    pub fn new(settings: &LocalSettings) -> Result<Self, LocalError> {
        let run = SimulationRun::new(settings.try_config()?).map_err(LocalError::Config)?;
        Ok(Self::with_run(run))
    }

    /// Drive a session against a device (e.g. a specially prepared one).
    pub fn from_parts(session: RunSession, device: SimulatedDevice) -> Self {
        Self::with_run(SimulationRun::from_parts(session, device))
    }

    fn with_run(run: SimulationRun) -> Self {
        Self {
            run,
            last_targets: None,
            tuned_at: None,
        }
    }

    /// The tuner.
    pub fn tuner(&self) -> &Tuner {
        self.run.tuner()
    }

    /// The simulated device.
    pub fn device(&self) -> &SimulatedDevice {
        self.run.device()
    }

    /// The simulated device, to change it behind the run's back (tests).
    pub fn device_mut(&mut self) -> &mut SimulatedDevice {
        self.run.device_mut()
    }

    /// The session's status.
    pub fn status(&self) -> RunStatus {
        self.run.session().status()
    }

    /// Whether the session wants iterations (running or stepping): the
    /// animation timer ticks only then.
    pub fn is_advancing(&self) -> bool {
        matches!(self.status(), RunStatus::Running | RunStatus::Stepping)
    }

    /// One whole iteration, its record inserted into `history`.
    /// `Ok(Some(k))`: iteration `k` was recorded; `Ok(None)`: the
    /// run is over (finished or stopped); `Err(Halt::Paused)`: paused
    /// (also after a single step); `Err(Halt::Fault(_))`: the session
    /// paused the run with a fault (resumable).
    pub fn advance(&mut self, history: &mut RunHistory) -> Result<Option<u64>, Halt> {
        match self.advance_for(history, f64::INFINITY, &|| 0.0)? {
            Progress::Recorded(k) => Ok(Some(k)),
            Progress::Over => Ok(None),
            Progress::Working => unreachable!("an unlimited slice ends with the iteration"),
        }
    }

    /// Work on the run for about `budget_ms` (by the clock `now`, ms): the
    /// session's requests are executed one by one (a scan and its fit each)
    /// until an iteration completes, the run stops or waits, or the time
    /// is used up after a request ([`Progress::Working`]; call again after
    /// yielding to the browser). Errors as [`LocalRunner::advance`].
    pub fn advance_for(
        &mut self,
        history: &mut RunHistory,
        budget_ms: f64,
        now: &dyn Fn() -> f64,
    ) -> Result<Progress, Halt> {
        let t0 = now();
        loop {
            match self.run.step()? {
                Step::Executed => {
                    if now() - t0 >= budget_ms {
                        return Ok(Progress::Working);
                    }
                }
                Step::Iteration(record) => {
                    let k = record.iteration;
                    self.record(*record, history);
                    return Ok(Progress::Recorded(k));
                }
                Step::Over => return Ok(Progress::Over),
            }
        }
    }

    fn record(&mut self, rec: IterationRecord, history: &mut RunHistory) {
        let targets: Targets = rec
            .parameters
            .iter()
            .map(|p| (p.target, p.tolerance))
            .collect();
        if self.last_targets.as_ref().is_some_and(|t| *t != targets) {
            self.tuned_at = None;
        }
        if rec.tuned && self.tuned_at.is_none() {
            self.tuned_at = Some(rec.iteration);
        }
        self.last_targets = Some(targets);
        history.insert([rec]);
        history.set_total(history.len() as u64);
    }

    /// Apply a control command through the session; the new status, or why
    /// the session refused it (nothing changed then).
    pub fn control(&mut self, command: &ControlCommand) -> Result<RunStatus, LocalError> {
        self.run.control(command).map_err(LocalError::Refused)
    }

    /// Change both targets (and the relative tolerance) through the session
    /// (they apply from the next iteration). Both are checked before either
    /// is applied.
    pub fn set_targets(
        &mut self,
        t_sr: f64,
        w: f64,
        tolerance: f64,
    ) -> Result<RunStatus, LocalError> {
        let tolerance = Some(Tolerance::Relative(tolerance));
        let changes = [("t_sr", t_sr), ("w", w)];
        for (parameter, target) in changes {
            self.tuner()
                .validate_target(parameter, Some(target), tolerance)
                .map_err(LocalError::Target)?;
        }
        for (parameter, target) in changes {
            self.control(&ControlCommand::SetTarget {
                parameter: parameter.into(),
                target: Some(target),
                tolerance,
            })?;
        }
        self.tuned_at = None;
        Ok(self.status())
    }

    /// The run's path in the (`gx`, `gy`) plane, mV, from its `history`.
    pub fn landscape_path(history: &RunHistory, gx: &str, gy: &str) -> Vec<(f64, f64)> {
        let l = history.layout();
        let gate = |g: &str| l.gates.iter().position(|x| x == g).map(|i| l.gate(i));
        let (Some(cx), Some(cy)) = (gate(gx), gate(gy)) else {
            return Vec::new();
        };
        let (xs, ys) = (history.column(cx), history.column(cy));
        xs.iter()
            .zip(ys)
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .map(|(x, y)| (*x, *y))
            .collect()
    }

    /// The simulator's noiseless truth on an `n`×`n` grid in the (`gx`, `gy`)
    /// plane, ±`half_mv` around the present voltages (other gates fixed):
    /// the largest `|p − p*| / tolerance` over the top level's targeted
    /// parameters (≤ 1: in band), computed by the core's simulator.
    pub fn landscape(
        &self,
        history: &RunHistory,
        gx: &str,
        gy: &str,
        half_mv: f64,
        n: usize,
    ) -> Option<Landscape> {
        let device = self.run.device();
        let v0 = device.voltages_mv();
        let (cx, cy) = (*v0.get(gx)?, *v0.get(gy)?);
        let parameters = &self.tuner().config().top().parameters;
        let grid = device.error_grid(gx, gy, half_mv, n, parameters)?;
        let (xs, ys, error) = (grid.xs, grid.ys, grid.error);
        let path = Self::landscape_path(history, gx, gy);
        Some(Landscape {
            gx: gx.to_string(),
            gy: gy.to_string(),
            xs,
            ys,
            error,
            path,
            now: (cx, cy),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn pause_step_resume_stop_go_through_the_session() {
        let mut r = LocalRunner::new(&LocalSettings::default()).unwrap();
        let mut h = RunHistory::new();
        assert_eq!(r.status(), RunStatus::Running);
        assert_eq!(r.advance(&mut h), Ok(Some(0)));
        assert_eq!(r.advance(&mut h), Ok(Some(1)));

        assert_eq!(r.control(&ControlCommand::Pause), Ok(RunStatus::Paused));
        assert!(!r.is_advancing());
        assert_eq!(r.advance(&mut h), Err(Halt::Paused));
        assert_eq!(h.len(), 2);

        // A single step: exactly one more iteration, then paused again.
        assert_eq!(r.control(&ControlCommand::Step), Ok(RunStatus::Stepping));
        assert!(r.is_advancing());
        assert_eq!(r.advance(&mut h), Ok(Some(2)));
        assert_eq!(r.status(), RunStatus::Paused);
        assert_eq!(r.advance(&mut h), Err(Halt::Paused));
        assert_eq!(h.len(), 3);

        // A target change while paused goes through the session too.
        assert_eq!(r.set_targets(70.0, 270.0, 0.1), Ok(RunStatus::Paused));
        assert!(r.set_targets(f64::NAN, 270.0, 0.1).is_err());
        assert!(r.set_targets(70.0, 270.0, -1.0).is_err());

        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        assert_eq!(r.advance(&mut h), Ok(Some(3)));
        let l = h.layout();
        let t_sr = l.param_index("t_sr").unwrap();
        assert_eq!(h.values(3).unwrap()[l.param(t_sr) + 2], 70.0);

        assert_eq!(r.control(&ControlCommand::Stop), Ok(RunStatus::Stopped));
        assert_eq!(r.advance(&mut h), Ok(None));
        assert!(r.control(&ControlCommand::Resume).is_err());
        assert_eq!(r.status(), RunStatus::Stopped);
        assert_eq!(h.len(), 4);
        let its: Vec<u64> = h.rows().iter().map(|r| r.iteration).collect();
        assert_eq!(its, vec![0, 1, 2, 3]);
    }

    /// Time slices: with no time budget every request is its own slice, and
    /// the records are exactly those of whole iterations.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn slices_of_an_iteration_give_the_same_records() {
        let settings = LocalSettings::default();
        let (mut a, mut b) = (
            LocalRunner::new(&settings).unwrap(),
            LocalRunner::new(&settings).unwrap(),
        );
        let (mut ha, mut hb) = (RunHistory::new(), RunHistory::new());
        for _ in 0..3 {
            a.advance(&mut ha).unwrap();
        }
        let mut slices = 0;
        while hb.len() < 3 {
            match b.advance_for(&mut hb, 0.0, &|| 0.0).unwrap() {
                Progress::Working => slices += 1,
                Progress::Recorded(_) => {}
                Progress::Over => panic!("over early"),
            }
        }
        assert!(slices >= 3 * 4, "only {slices} slices in 3 iterations");
        assert_eq!(ha.rows(), hb.rows());
        let bits = |h: &RunHistory| {
            h.values(2)
                .unwrap()
                .iter()
                .map(|v| v.to_bits())
                .collect::<Vec<_>>()
        };
        assert_eq!(bits(&ha), bits(&hb));
        // Pause between slices: the session finishes nothing more.
        assert_eq!(b.control(&ControlCommand::Pause), Ok(RunStatus::Paused));
    }

    /// A run whose device refuses to move gate N more than 0.5 mV: the
    /// session pauses the run with a device fault, which is resumable.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_device_fault_pauses_the_run_and_is_resumable() {
        use crate::model::{status_label, ControlsEnabled};
        use spintune::protocol::FaultKind;
        use spintune::session::{RunSession, SessionConfig};
        use spintune::sim::SimulatedDevice;

        let cfg = LocalSettings::default().to_config();
        let mut gates = cfg.tuner.gates.clone();
        let n = gates.iter_mut().find(|g| g.name == "N").unwrap();
        n.min_mv = n.initial_mv - 0.5;
        n.max_mv = n.initial_mv + 0.5;
        let device = SimulatedDevice::new(cfg.device.clone(), &gates, cfg.seed).unwrap();
        let session = RunSession::new(cfg.tuner, SessionConfig::default()).unwrap();
        let mut r = LocalRunner::from_parts(session, device);
        let mut h = RunHistory::new();

        let fault = match r.advance(&mut h) {
            Err(Halt::Fault(f)) => f,
            other => panic!("expected a fault, got {other:?}"),
        };
        assert_eq!(fault.kind, FaultKind::Device);
        assert!(fault.message.contains("\"N\""), "{}", fault.message);
        let status = r.status();
        assert_eq!(
            status,
            RunStatus::Faulted {
                fault: fault.clone()
            }
        );
        assert!(status.is_resumable() && !r.is_advancing());
        let label = status_label(&status);
        assert!(label.starts_with("faulted"), "{label}");
        assert!(
            label.contains("Instrument fault")
                && label.contains(&fault.message)
                && label.contains("needs a person"),
            "{label}"
        );
        assert!(ControlsEnabled::for_status(&status).resume);
        assert!(!ControlsEnabled::for_status(&status).accept_positions);
        assert!(h.is_empty());

        // Resume: the session reads the gates back and retries the request,
        // which this device refuses again.
        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        assert!(matches!(r.advance(&mut h), Err(Halt::Fault(f)) if f.kind == FaultKind::Device));
        // A faulted run can be held (paused) or stopped by the user.
        assert_eq!(r.control(&ControlCommand::Pause), Ok(RunStatus::Paused));
        assert_eq!(r.advance(&mut h), Err(Halt::Paused));
        assert_eq!(r.control(&ControlCommand::Stop), Ok(RunStatus::Stopped));
        assert_eq!(r.advance(&mut h), Ok(None));
    }

    /// Gate N moved by hand while the run was paused: resume reads it back
    /// and faults (moved); resume alone re-reads and faults again; accepting
    /// the positions leaves the run paused, and resume continues from them.
    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_gate_moved_while_paused_needs_its_position_accepted() {
        use crate::model::{moved_rows, status_label, ControlsEnabled};
        use spintune::protocol::{ClearedBy, FaultKind, Request, Response};

        let mut r = LocalRunner::new(&LocalSettings::default()).unwrap();
        let mut h = RunHistory::new();
        assert_eq!(r.advance(&mut h), Ok(Some(0)));
        assert_eq!(r.control(&ControlCommand::Pause), Ok(RunStatus::Paused));
        let left = r.device().voltages_mv()["N"];
        let moved_to = left + 5.0;
        let answer = r.device_mut().execute(&Request::SetVoltages {
            voltages_mv: [("N".to_string(), moved_to)].into(),
        });
        assert!(matches!(answer, Response::VoltagesSet { .. }), "{answer:?}");

        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        let fault = match r.advance(&mut h) {
            Err(Halt::Fault(f)) => f,
            other => panic!("expected a moved fault, got {other:?}"),
        };
        assert_eq!(fault.kind, FaultKind::Moved);
        assert_eq!(fault.cleared_by, ClearedBy::AcceptPositions);
        let rows = moved_rows(&fault);
        assert_eq!(rows.len(), 1, "{rows:?}");
        assert_eq!(rows[0].gate, "N");
        assert_eq!(rows[0].read, format!("{moved_to:.2}"));
        assert_eq!(rows[0].difference, "+5.00");
        let status = r.status();
        assert!(status_label(&status).contains("Gates moved"));
        let c = ControlsEnabled::for_status(&status);
        assert!(c.accept_positions && c.resume, "{c:?}");

        // Resume without accepting: the gate is read again, still far.
        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        assert!(matches!(r.advance(&mut h), Err(Halt::Fault(f)) if f.kind == FaultKind::Moved));
        // Accept: paused, nothing sent until resume.
        assert_eq!(
            r.control(&ControlCommand::AcceptPositions),
            Ok(RunStatus::Paused)
        );
        assert!(!ControlsEnabled::for_status(&r.status()).accept_positions);
        assert!(r.control(&ControlCommand::AcceptPositions).is_err());
        assert_eq!(r.advance(&mut h), Err(Halt::Paused));
        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        assert_eq!(r.advance(&mut h), Ok(Some(1)));
        assert_eq!(r.status(), RunStatus::Running);
    }
}
