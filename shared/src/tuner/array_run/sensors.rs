//! The joint loop's sensing dots: each cell's sensor swept and parked on its
//! fitted flank, or parked on the flank its model predicts from the
//! neighbourhood's gates ([`ArrayRunSettings::flank_prediction`](super::ArrayRunSettings::flank_prediction)).

use super::{who_scans, ArrayRun, ArrayRunError, Parks};
use crate::protocol::{EventKind, Request, Response, ScanKind, ScanRequest, Sweep, TunerEvent};
use crate::tuner::flank::FlankForecast;

impl ArrayRun {
    /// Sweep each cell's sensing gate around its present voltage.
    pub(super) fn sensor_sweeps(&self, cells: &[u32]) -> Result<Vec<Request>, ArrayRunError> {
        let joint = self.joint()?;
        Ok(cells
            .iter()
            .map(|&c| {
                let l = &joint.lower[c as usize];
                let now = self.voltages_mv.get(&l.sd_gate).copied().unwrap_or(0.0);
                let spec = self.limits.gate(&l.sd_gate);
                Request::Measure {
                    scan: ScanRequest {
                        kind: ScanKind::SensingDot,
                        sweep: Some(Sweep {
                            gate: l.sd_gate.clone(),
                            from_mv: spec.map_or(now, |s| (now - l.sd_half_width_mv).max(s.min_mv)),
                            to_mv: spec.map_or(now, |s| (now + l.sd_half_width_mv).min(s.max_mv)),
                            points: l.sd_points,
                        }),
                        cell: Some(c),
                    },
                }
            })
            .collect())
    }

    /// Park each swept sensor on its fitted flank (a failed fit leaves it);
    /// the cell's flank model learns from it.
    pub(super) fn sensor_flanks(
        &mut self,
        cells: &[u32],
        answers: &[Response],
    ) -> Result<Vec<(String, f64)>, ArrayRunError> {
        let mut flanks = Vec::new();
        let noise = self.settings.flank_prediction.noise_mv;
        for (&c, a) in cells.iter().zip(answers) {
            let found = self.evaluate(c as usize, a, "sd_flank_mv");
            let v = &self.voltages_mv;
            let Some(joint) = self.joint.as_mut() else {
                continue;
            };
            let l = &mut joint.lower[c as usize];
            match found {
                Some((flank, variance)) => {
                    if let Some(model) = l.flank.as_mut() {
                        model.observe(v, flank, variance, noise);
                    }
                    l.failed_since_sweep = false;
                    flanks.push((l.sd_gate.clone(), flank));
                }
                None => {
                    l.failed_since_sweep = true;
                    self.failed_fits += 1;
                }
            }
        }
        Ok(flanks)
    }

    /// Which of `cells` sweep their sensor, and the flanks (gate, mV) of
    /// those parked from their prediction instead
    /// ([`ArrayRunSettings::flank_prediction`](super::ArrayRunSettings::flank_prediction)). A cell sweeps when its
    /// prediction is not confident, or when its readout group's sweeps in
    /// this batch leave room for it: the batch lasts as long as its busiest
    /// group, so such a sweep costs no lab time. Records the skips as events.
    pub(super) fn plan_parks(&mut self, cells: &[u32]) -> Result<Parks, ArrayRunError> {
        let p = self.settings.flank_prediction.clone();
        let v = self.voltages_mv.clone();
        let limits = &self.limits;
        let joint = self.joint()?;
        let forecasts: Vec<Option<FlankForecast>> = cells
            .iter()
            .map(|&c| {
                let l = &joint.lower[c as usize];
                if l.failed_since_sweep {
                    return None;
                }
                let spec = limits.gate(&l.sd_gate)?;
                let parked = v.get(&l.sd_gate).copied()?;
                l.flank.as_ref()?.confident(
                    &v,
                    &p,
                    (spec.min_mv, spec.max_mv),
                    parked,
                    l.sd_half_width_mv,
                )
            })
            .collect();
        let confident: Vec<bool> = forecasts.iter().map(Option::is_some).collect();
        let sweep = who_scans(cells, &confident, &self.readout_group);
        let mut predicted = Vec::new();
        let skipped: Vec<(u32, FlankForecast)> = cells
            .iter()
            .zip(forecasts)
            .filter(|(c, _)| !sweep.contains(c))
            .filter_map(|(&c, f)| Some((c, f?)))
            .collect();
        let Some(joint) = self.joint.as_mut() else {
            return Ok((sweep, predicted));
        };
        for (c, f) in skipped {
            let l = &mut joint.lower[c as usize];
            if let Some(model) = l.flank.as_mut() {
                model.skips += 1;
            }
            predicted.push((l.sd_gate.clone(), f.flank_mv));
            if let Some(record) = self.scratch.record.as_mut() {
                record.events.push(TunerEvent {
                    level: "array".into(),
                    kind: EventKind::SweepSkipped {
                        gate: l.sd_gate.clone(),
                        predicted_mv: f.flank_mv,
                        std_mv: f.std_mv,
                    },
                });
            }
        }
        Ok((sweep, predicted))
    }
}
