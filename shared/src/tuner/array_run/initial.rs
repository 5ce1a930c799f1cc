//! The joint loop's first phase: each cell's initial measurement in its
//! own single-cell [`RunSession`](crate::session::RunSession) (stepped in parallel and in lockstep, one
//! request per cell and batch), the lead-transition widths they measured,
//! and the [`JointArrayTuner`] started from what they learned. Methods of
//! [`ArrayRun`].

use super::lines::borrow_line_jacobians;
use super::{ArrayRun, ArrayRunError, CellLower, Joint};
use crate::fit::lead_widths_mv;
use crate::protocol::{Request, Response, ScanOutcome};
use crate::session::Output;
use crate::sim::array::split_gate;
use crate::tuner::array::{lockstep_factor, CellKnowledge, JointArrayTuner, Measured};
use crate::tuner::borrowed_gradient::borrow_failed_gradients;
use crate::tuner::flank::FlankModel;
use crate::tuner::level_forecast::{compensation_columns, LevelForecast};
use crate::tuner::pooled_gradient::pool_gradients;
use crate::tuner::thermal_floor::{self, floor_from_lead_widths, FloorLog};
use crate::tuner::{InitialGradient, LevelKind, ParameterForecast};

impl ArrayRun {
    /// Poll cell `k`'s session until it hands out a request or ends.
    pub(super) fn step_session(&mut self, k: usize) -> Result<(), ArrayRunError> {
        let halted = |message: String| ArrayRunError::Halted {
            cell: k as u32,
            message,
        };
        while self.session_pending[k].is_none() {
            let Some(session) = self.sessions[k].as_mut() else {
                return Ok(());
            };
            match session.poll() {
                Output::Execute(mut request) => {
                    if let Request::Measure { scan } = &mut request {
                        scan.cell = Some(k as u32);
                    }
                    self.session_pending[k] = Some(request);
                }
                Output::Commit(_) | Output::Save | Output::Publish(_) | Output::Sleep { .. } => {}
                Output::Wait => return Err(halted(format!("{:?}", session.status()))),
                Output::Done(_) => {
                    self.initial_failed[k] = session.tuner().failed_evaluations();
                    // kept: its learned gradients start the joint tuner
                    return Ok(());
                }
            }
        }
        Ok(())
    }

    /// Which cells' pending requests the initial measurements' next batch
    /// sends. The cells measure in lockstep: a request that moves a cell's
    /// tuning gates (a finite-difference step) waits while another cell
    /// still has a scan or any other request pending, so every cell moves
    /// its gates at the same time and scans with its neighbours standing
    /// still (the joint prior's lockstep factor,
    /// [`crate::tuner::array::lockstep_factor`], assumes exactly this). A cell
    /// that needs extra requests (a re-sweep, a line correction) delays the
    /// others' next move instead of moving out of step. No deadlock: when
    /// every pending request is a move, all are sent.
    pub(super) fn initial_sent(&self) -> Vec<bool> {
        let moves: Vec<bool> = self
            .session_pending
            .iter()
            .zip(&self.sessions)
            .map(|(r, s)| match (r, s) {
                (Some(Request::SetVoltages { voltages_mv }), Some(s)) => s
                    .tuner()
                    .config()
                    .top()
                    .gates
                    .iter()
                    .any(|g| voltages_mv.contains_key(g)),
                _ => false,
            })
            .collect();
        let busy = self
            .session_pending
            .iter()
            .zip(&moves)
            .any(|(r, &m)| r.is_some() && !m);
        self.session_pending
            .iter()
            .zip(&moves)
            .map(|(r, &m)| r.is_some() && !(busy && m))
            .collect()
    }

    pub(super) fn feed_sessions(
        &mut self,
        batch: &[Request],
        answers: Vec<Response>,
    ) -> Result<(), ArrayRunError> {
        let mut answers = answers.into_iter();
        let mut sent = batch.iter();
        // the cells whose pending request this batch carried, in order
        let in_batch = self.initial_sent();
        for k in (0..in_batch.len()).filter(|&k| in_batch[k]) {
            let (Some(_), Some(answer)) = (sent.next(), answers.next()) else {
                return Err(ArrayRunError::Protocol("an answer is missing".into()));
            };
            self.session_pending[k] = None;
            self.note_lead_widths(k, &answer);
            if let Some(s) = self.sessions[k].as_mut() {
                s.feed(answer).map_err(|e| ArrayRunError::Halted {
                    cell: k as u32,
                    message: e.to_string(),
                })?;
            }
        }
        Ok(())
    }

    /// Cell `k`'s lead-transition widths from a raw chemical-potential
    /// scan of its initial measurement (bounded; a lab's own evaluation
    /// gives none, and the cell's `w` is then learned as `ln w`). Only
    /// with [`JointConfig::thermal_floor`](crate::tuner::array::JointConfig::thermal_floor), and never for the oracle.
    pub(super) fn note_lead_widths(&mut self, k: usize, answer: &Response) {
        if !self.settings.joint.thermal_floor || self.oracle {
            return;
        }
        let Response::Scanned {
            outcome: ScanOutcome::Raw { scan },
            ..
        } = answer
        else {
            return;
        };
        if self.lead_widths_mv.len() != self.sessions.len() {
            self.lead_widths_mv = vec![Vec::new(); self.sessions.len()];
        }
        let kept = &mut self.lead_widths_mv[k];
        for w in lead_widths_mv(scan) {
            if kept.len() < thermal_floor::MAX_LEAD_WIDTHS {
                kept.push(w);
            }
        }
    }

    /// The lab's knowledge of every cell after its initial measurement.
    pub(super) fn start_joint(&mut self) -> Result<(), ArrayRunError> {
        let mut cells = Vec::new();
        let mut lower = Vec::new();
        for (k, session) in self.sessions.iter().enumerate() {
            let halted = |message: &str| ArrayRunError::Halted {
                cell: k as u32,
                message: message.into(),
            };
            let session = session.as_ref().ok_or_else(|| halted("no session"))?;
            let cfg = session.tuner().config_with_learned_gradients();
            let top = cfg.top();
            let (mut gradient, mut covariance) = match &top.initial_gradient {
                InitialGradient::Given {
                    gradient,
                    covariance,
                } => (gradient.clone(), covariance.clone()),
                _ => return Err(halted("no initial gradient was measured")),
            };
            let mut process_noise_per_mv: Vec<f64> = top
                .parameters
                .iter()
                .map(|p| p.process_noise_per_mv)
                .collect();
            // `w` over its measured thermal floor (widths are kept only
            // with `thermal_floor`, never for the oracle): the log-space
            // knowledge scaled by dy/dln w at the initial measurement's value
            let start = session.tuner().last_measured(0).unwrap_or_default();
            let floor = self
                .lead_widths_mv
                .get(k)
                .and_then(|w| floor_from_lead_widths(w));
            let mut floors = vec![0.0; top.parameters.len()];
            for (p, param) in top.parameters.iter().enumerate() {
                let value = start.get(p).and_then(|v| v.as_ref()).map(|v| v.value);
                let (Some(f), Some(value), true) = (floor, value, param.name == "w") else {
                    continue;
                };
                let gain = FloorLog::new(f).log_gain(value);
                floors[p] = f;
                gradient[p].iter_mut().for_each(|g| *g *= gain);
                covariance[p]
                    .iter_mut()
                    .flatten()
                    .for_each(|c| *c *= gain * gain);
                process_noise_per_mv[p] *= gain;
            }
            cells.push(CellKnowledge {
                gates: top.gates.clone(),
                parameters: top.parameters.iter().map(|p| p.name.clone()).collect(),
                gradient,
                covariance,
                process_noise_per_mv,
                floors,
                max_step_mv: top.solver.max_step_mv,
                compensation: top
                    .compensation
                    .as_ref()
                    .map(|c| (c.gates.clone(), c.matrix.clone())),
            });
            // the load curve's σ at least the run's floor (ArrayRunSettings::t_sr_floor)
            let mut references = cfg.fit_references;
            let t_sr = &mut references.t_sr.relative_floor;
            if !self.settings.t_sr_floor_filter_only {
                *t_sr = t_sr.max(self.settings.t_sr_floor);
            }
            let mut l = CellLower::empty(references);
            for level in cfg.levels.iter().skip(1) {
                match &level.kind {
                    LevelKind::SensingDot(sd) => {
                        l.sd_gate = sd.gate.clone();
                        l.sd_half_width_mv = sd.half_width_mv;
                        l.sd_points = sd.points;
                    }
                    LevelKind::Newton(n) if n.gates.len() == 2 => {
                        if let InitialGradient::Given { gradient, .. } = &n.initial_gradient {
                            for (r, row) in gradient.iter().take(2).enumerate() {
                                for (s, &g) in row.iter().take(2).enumerate() {
                                    l.line_jacobian[r][s] = g;
                                }
                            }
                        }
                        l.line_gates = n.gates.clone();
                        l.line_max_step_mv = n.solver.max_step_mv;
                        l.line_search = n.search.clone();
                    }
                    LevelKind::Newton(_) => {}
                }
            }
            // the lines' model sees the own and the nearest cells' gates
            let grid = self.grid();
            let near_cell =
                |g: &str| split_gate(g).is_some_and(|(j, _)| grid.distance(j as usize, k) <= 1);
            let near: Vec<String> = self
                .voltages_mv
                .keys()
                .filter(|g| near_cell(g) && !l.line_gates.contains(g))
                .cloned()
                .collect();
            let own = cells.last().expect("pushed above");
            let centre = own
                .compensation
                .as_ref()
                .map_or_else(Vec::new, |(rows, m)| {
                    compensation_columns(&own.gates, rows, m, &l.line_gates)
                });
            if !l.sd_gate.is_empty() {
                // the flank's model sees the neighbourhood's gates but the swept one
                let others = self
                    .voltages_mv
                    .keys()
                    .filter(|g| near_cell(g) && **g != l.sd_gate)
                    .cloned()
                    .collect();
                l.flank = Some(FlankModel::new(others, &self.settings.flank_prediction));
            }
            l.lines = LevelForecast::new(
                near,
                2,
                ParameterForecast::default().prior_lever_per_mv,
                centre,
            );
            lower.push(l);
        }
        if self.settings.joint_line_steps {
            // measured in lockstep: each cell saw its neighbours' plunger
            // moves too (`lockstep_factor`'s model)
            let grid = self.grid();
            for (k, l) in lower.iter_mut().enumerate() {
                let f = lockstep_factor(&grid, k, self.cross_calibration);
                l.line_jacobian.iter_mut().flatten().for_each(|j| *j /= f);
            }
        }
        borrow_line_jacobians(&mut lower);
        if self.settings.pool_initial_gradients {
            let grid = self.grid();
            let units: Vec<f64> = (0..cells.len())
                .map(|k| match self.settings.pool_in_lockstep_units {
                    true => lockstep_factor(&grid, k, self.cross_calibration),
                    false => 1.0,
                })
                .collect();
            pool_gradients(&mut cells, &units);
        } else if self.settings.borrow_failed_gradients {
            borrow_failed_gradients(&mut cells);
        }
        // the oracle knows the true Jacobian: it has nothing to explore for;
        // it keeps the paper's scaled step (its fastest, docs/array-history.md)
        let mut config = self.settings.joint.clone();
        if self.oracle {
            config.excitation = 0.0;
            config.trust_region = false;
        }
        let mut tuner =
            JointArrayTuner::with_grid(self.grid(), cells, &config, self.cross_calibration)?;
        // the initial measurement's last values start the filters' differences
        for (c, session) in self.sessions.iter().enumerate() {
            let last = session
                .as_ref()
                .and_then(|s| s.tuner().last_measured(0))
                .unwrap_or_default();
            let values: Vec<Option<Measured>> = last
                .iter()
                .map(|p| p.as_ref().map(|p| (p.value, p.variance)))
                .collect();
            tuner.observe(c, &values, &self.voltages_mv);
        }
        let last_good = (0..self.sessions.len())
            .map(|c| self.cell_voltages(c))
            .collect();
        let k = self.sessions.len();
        self.joint = Some(Joint {
            tuner,
            lower,
            last_good,
            in_band: vec![false; k],
            skip: vec![false; k],
            skips_in_a_row: vec![0; k],
            stalls: vec![Default::default(); k],
            flat_resets: vec![Default::default(); k],
            lags: vec![Default::default(); k],
            repeats: Vec::new(),
            clock: Default::default(),
            slack: Vec::new(),
            early: Vec::new(),
        });
        Ok(())
    }
}
