//! [`LocalRunner`]: drives one in-browser [`SimulationRun`] through its
//! session and keeps its records.

use spintune::driver::{Halt, SimulationRun};
use spintune::parameter::Tolerance;
use spintune::protocol::{ControlCommand, IterationRecord, RunStatus};

use super::settings::LocalSettings;
use crate::landscape::Landscape;
use crate::model::History;

/// Drives a [`SimulationRun`] and collects its records. Every change of
/// the run's course goes through the session ([`LocalRunner::control`]).
pub struct LocalRunner {
    run: SimulationRun,
    /// Iterations so far.
    pub history: History,
    /// First iteration at which every parameter was in band since the targets
    /// last changed (by the user or by the schedule).
    pub tuned_at: Option<u64>,
}

impl LocalRunner {
    /// Start from settings (the session starts running).
    pub fn new(settings: &LocalSettings) -> Result<Self, String> {
        Ok(Self::from_run(settings.build()?))
    }

    /// Drive an existing run (e.g. one with a specially prepared device).
    pub fn from_run(run: SimulationRun) -> Self {
        Self {
            run,
            history: History::new(),
            tuned_at: None,
        }
    }

    /// The run.
    pub fn run(&self) -> &SimulationRun {
        &self.run
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

    /// One tick of the animation: [`SimulationRun::next_iteration`], with the
    /// record kept. `Ok(Some(k))`: iteration `k` was recorded; `Ok(None)`: the
    /// run is over (finished or stopped); `Err(Halt::Paused)`: paused
    /// (also after a single step); `Err(Halt::Fault(_))`: the session
    /// paused the run with a fault (resumable).
    pub fn advance(&mut self) -> Result<Option<u64>, Halt> {
        let Some(rec) = self.run.next_iteration()? else {
            return Ok(None);
        };
        let k = rec.iteration;
        self.record(rec);
        Ok(Some(k))
    }

    fn record(&mut self, rec: IterationRecord) {
        let targets = |r: &IterationRecord| {
            r.parameters
                .iter()
                .map(|p| (p.target, p.tolerance))
                .collect::<Vec<_>>()
        };
        if self
            .history
            .last()
            .is_some_and(|prev| targets(prev) != targets(&rec))
        {
            self.tuned_at = None;
        }
        if rec.tuned && self.tuned_at.is_none() {
            self.tuned_at = Some(rec.iteration);
        }
        self.history.push(rec);
    }

    /// Apply a control command through the session; the new status, or why
    /// the session refused it (nothing changed then).
    pub fn control(&mut self, command: &ControlCommand) -> Result<RunStatus, String> {
        self.run.control(command).map_err(|e| e.to_string())
    }

    /// Change both targets (and the relative tolerance) through the session
    /// (they apply from the next iteration). Both are checked before either
    /// is applied.
    pub fn set_targets(&mut self, t_sr: f64, w: f64, tolerance: f64) -> Result<RunStatus, String> {
        let tolerance = Some(Tolerance::Relative(tolerance));
        let changes = [("t_sr", t_sr), ("w", w)];
        for (parameter, target) in changes {
            self.run
                .tuner()
                .validate_target(parameter, Some(target), tolerance)
                .map_err(|e| e.to_string())?;
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

    /// The run's path in the (`gx`, `gy`) plane, mV.
    pub fn landscape_path(&self, gx: &str, gy: &str) -> Vec<(f64, f64)> {
        self.history
            .records()
            .iter()
            .filter_map(|r| Some((*r.voltages_mv.get(gx)?, *r.voltages_mv.get(gy)?)))
            .collect()
    }

    /// The simulator's noiseless truth on an `n`×`n` grid in the (`gx`, `gy`)
    /// plane, ±`half_mv` around the present voltages (other gates fixed):
    /// the largest `|p − p*| / tolerance` over the top level's targeted
    /// parameters (≤ 1: in band), computed by the core's simulator.
    pub fn landscape(&self, gx: &str, gy: &str, half_mv: f64, n: usize) -> Option<Landscape> {
        let device = self.run.device();
        let v0 = device.voltages_mv();
        let (cx, cy) = (*v0.get(gx)?, *v0.get(gy)?);
        let parameters = &self.run.tuner().config().top().parameters;
        let grid = device.error_grid(gx, gy, half_mv, n, parameters)?;
        let (xs, ys, error) = (grid.xs, grid.ys, grid.error);
        let path = self.landscape_path(gx, gy);
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
        assert_eq!(r.status(), RunStatus::Running);
        assert_eq!(r.advance(), Ok(Some(0)));
        assert_eq!(r.advance(), Ok(Some(1)));

        assert_eq!(r.control(&ControlCommand::Pause), Ok(RunStatus::Paused));
        assert!(!r.is_advancing());
        assert_eq!(r.advance(), Err(Halt::Paused));
        assert_eq!(r.history.len(), 2);

        // A single step: exactly one more iteration, then paused again.
        assert_eq!(r.control(&ControlCommand::Step), Ok(RunStatus::Stepping));
        assert!(r.is_advancing());
        assert_eq!(r.advance(), Ok(Some(2)));
        assert_eq!(r.status(), RunStatus::Paused);
        assert_eq!(r.advance(), Err(Halt::Paused));
        assert_eq!(r.history.len(), 3);

        // A target change while paused goes through the session too.
        assert_eq!(r.set_targets(70.0, 270.0, 0.1), Ok(RunStatus::Paused));
        assert!(r.set_targets(f64::NAN, 270.0, 0.1).is_err());
        assert!(r.set_targets(70.0, 270.0, -1.0).is_err());

        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        assert_eq!(r.advance(), Ok(Some(3)));
        let t_sr = r.history.records()[3]
            .parameters
            .iter()
            .find(|p| p.name == "t_sr")
            .unwrap();
        assert_eq!(t_sr.target, Some(70.0));

        assert_eq!(r.control(&ControlCommand::Stop), Ok(RunStatus::Stopped));
        assert_eq!(r.advance(), Ok(None));
        assert!(r.control(&ControlCommand::Resume).is_err());
        assert_eq!(r.status(), RunStatus::Stopped);
        assert_eq!(r.history.len(), 4);
        let its: Vec<u64> = r.history.records().iter().map(|r| r.iteration).collect();
        assert_eq!(its, vec![0, 1, 2, 3]);
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
        let mut r = LocalRunner::from_run(SimulationRun::from_parts(session, device));

        let fault = match r.advance() {
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
        assert!(r.history.is_empty());

        // Resume: the session reads the gates back and retries the request,
        // which this device refuses again.
        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        assert!(matches!(r.advance(), Err(Halt::Fault(f)) if f.kind == FaultKind::Device));
        // A faulted run can be held (paused) or stopped by the user.
        assert_eq!(r.control(&ControlCommand::Pause), Ok(RunStatus::Paused));
        assert_eq!(r.advance(), Err(Halt::Paused));
        assert_eq!(r.control(&ControlCommand::Stop), Ok(RunStatus::Stopped));
        assert_eq!(r.advance(), Ok(None));
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
        assert_eq!(r.advance(), Ok(Some(0)));
        assert_eq!(r.control(&ControlCommand::Pause), Ok(RunStatus::Paused));
        let left = r.run.device().voltages_mv()["N"];
        let moved_to = left + 5.0;
        let answer = r.run.device_mut().execute(&Request::SetVoltages {
            voltages_mv: [("N".to_string(), moved_to)].into(),
        });
        assert!(matches!(answer, Response::VoltagesSet { .. }), "{answer:?}");

        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        let fault = match r.advance() {
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
        assert!(matches!(r.advance(), Err(Halt::Fault(f)) if f.kind == FaultKind::Moved));
        // Accept: paused, nothing sent until resume.
        assert_eq!(
            r.control(&ControlCommand::AcceptPositions),
            Ok(RunStatus::Paused)
        );
        assert!(!ControlsEnabled::for_status(&r.status()).accept_positions);
        assert!(r.control(&ControlCommand::AcceptPositions).is_err());
        assert_eq!(r.advance(), Err(Halt::Paused));
        assert_eq!(r.control(&ControlCommand::Resume), Ok(RunStatus::Running));
        assert_eq!(r.advance(), Ok(Some(1)));
        assert_eq!(r.status(), RunStatus::Running);
    }
}
