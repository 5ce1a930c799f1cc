//! "What the filter believes" (issue 25, for students): for one iteration,
//! each gradient element ∂p/∂V with ±1σ and its unit, and for the move that
//! led to it the change of each parameter the filter predicted (g·Δv) next
//! to the change measured. Pure arithmetic on a [`RunHistory`] (data layer).
//!
//! The prediction uses the gradient the filter held after the previous
//! iteration (the one it planned the move with) and the gates' move Δv
//! between the two measurements. In log space (gradient unit `1/mV`) the
//! gradient is ∂ln p/∂V: g·Δv is the predicted change of ln p, i.e. p is
//! predicted to change by the factor e^(g·Δv).

use crate::history::RunHistory;

/// One element ∂p/∂V_gate of a gradient.
#[derive(Debug, Clone, PartialEq)]
pub struct Element {
    /// The gate V.
    pub gate: String,
    /// ∂p/∂V in the gradient's unit.
    pub value: f64,
    /// ±1σ (√ of the covariance's diagonal; NaN without a covariance).
    pub sigma: f64,
}

/// One parameter's gradient as the filter holds it after an iteration.
#[derive(Debug, Clone, PartialEq)]
pub struct Gradient {
    /// Parameter name.
    pub parameter: String,
    /// Unit of the elements, e.g. `ns/mV`, or `1/mV (log space)`.
    pub unit: String,
    /// The gradient is of ln p (unit 1/mV).
    pub log_space: bool,
    /// Per gate.
    pub elements: Vec<Element>,
}

/// Predicted against measured change of one parameter over one move.
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// Parameter name.
    pub parameter: String,
    /// The parameter's unit.
    pub unit: String,
    /// g·Δv with the previous iteration's gradient (in log space: of ln p).
    pub g_dv: f64,
    /// Predicted change of p, in its unit (log space: p_before·(e^(g·Δv) − 1)).
    pub predicted: f64,
    /// Measured change of p (NaN if either measurement is missing).
    pub measured: f64,
    /// The gradient is of ln p.
    pub log_space: bool,
    /// The tuner rejected one of the two measurements.
    pub rejected: bool,
}

/// What the filter believes at one iteration.
#[derive(Debug, Clone, PartialEq)]
pub struct Belief {
    /// The iteration.
    pub iteration: u64,
    /// Its gradients (after its update).
    pub gradients: Vec<Gradient>,
    /// The previous iteration, when it is loaded (`iteration − 1`).
    pub previous: Option<u64>,
    /// The gates' move since the previous measurement, mV (empty without one).
    pub moves: Vec<(String, f64)>,
    /// Per parameter with a gradient (empty without a previous iteration).
    pub predictions: Vec<Prediction>,
}

/// Whether a gradient unit is of ln p.
pub fn is_log_space(unit: &str) -> bool {
    unit.starts_with("1/")
}

/// What the filter believes at iteration `k` (None if it is not loaded).
pub fn belief(h: &RunHistory, k: u64) -> Option<Belief> {
    let i = h.rows().binary_search_by_key(&k, |r| r.iteration).ok()?;
    let layout = h.layout();
    let at = |c: usize, i: usize| h.column(c).get(i).copied().unwrap_or(f64::NAN);
    let gradient_at = |g: usize, i: usize| -> Gradient {
        let (parameter, unit) = layout.gradients[g].clone();
        Gradient {
            log_space: is_log_space(&unit),
            parameter,
            unit,
            elements: layout
                .gates
                .iter()
                .enumerate()
                .map(|(j, gate)| Element {
                    gate: gate.clone(),
                    value: at(layout.grad(g, j), i),
                    sigma: at(layout.grad(g, j) + 1, i),
                })
                .collect(),
        }
    };
    let gradients = (0..layout.gradients.len())
        .map(|g| gradient_at(g, i))
        .collect();
    let prev = i.checked_sub(1).filter(|&j| h.rows()[j].iteration + 1 == k);
    let (mut moves, mut predictions) = (Vec::new(), Vec::new());
    if let Some(j) = prev {
        moves = layout
            .gates
            .iter()
            .enumerate()
            .map(|(g, gate)| (gate.clone(), at(layout.gate(g), i) - at(layout.gate(g), j)))
            .collect();
        for (p, (name, unit)) in layout.parameters.iter().enumerate() {
            let Some(g) = layout.gradients.iter().position(|x| &x.0 == name) else {
                continue;
            };
            let grad = gradient_at(g, j);
            let g_dv: f64 = grad
                .elements
                .iter()
                .zip(&moves)
                .map(|(e, (_, dv))| e.value * dv)
                .sum();
            let (before, after) = (at(layout.param(p), j), at(layout.param(p), i));
            let predicted = if grad.log_space {
                before * g_dv.exp_m1()
            } else {
                g_dv
            };
            predictions.push(Prediction {
                parameter: name.clone(),
                unit: unit.clone(),
                g_dv,
                predicted,
                measured: after - before,
                log_space: grad.log_space,
                rejected: h.is_rejected(layout.param(p), i) || h.is_rejected(layout.param(p), j),
            });
        }
    }
    Some(Belief {
        iteration: k,
        gradients,
        previous: prev.map(|j| h.rows()[j].iteration),
        moves,
        predictions,
    })
}

fn signed(v: f64) -> String {
    if v.is_finite() {
        format!("{v:+.3}")
    } else {
        "–".into()
    }
}

/// The prediction in plain words, e.g. "t_sr: the filter expected a change
/// of +1.200 ns (g·Δv); it measured +0.800 ns."
pub fn sentence(p: &Prediction) -> String {
    let expected = if p.log_space {
        format!(
            "ln {} to change by g·Δv = {}, i.e. {} × {:.3}: a change of {} {}",
            p.parameter,
            signed(p.g_dv),
            p.parameter,
            p.g_dv.exp(),
            signed(p.predicted),
            p.unit
        )
    } else {
        format!("a change of {} {} (g·Δv)", signed(p.predicted), p.unit)
    };
    let mut s = format!(
        "{}: the filter expected {expected}; it measured {} {}.",
        p.parameter,
        signed(p.measured),
        p.unit
    );
    if p.rejected {
        s.push_str(" (One of the two values was rejected by the tuner: not acted on.)");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::fake_records;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn the_filter_s_gradient_and_its_prediction_of_the_last_move() {
        let recs = fake_records(6);
        let mut h = RunHistory::new();
        h.insert(recs.clone());
        let b = belief(&h, 3).unwrap();
        assert_eq!(b.previous, Some(2));
        // Gradients of iteration 3 with ±σ and units.
        let g = &b.gradients[0];
        assert_eq!((g.parameter.as_str(), g.unit.as_str()), ("t_sr", "ns/mV"));
        assert!(!g.log_space);
        assert_eq!(g.elements.len(), 4);
        assert_eq!(g.elements[1].gate, "SA");
        assert!((g.elements[1].value - recs[3].gradients[0].gradient[1]).abs() < 1e-12);
        let cov = recs[3].gradients[0].covariance.as_ref().unwrap();
        assert!((g.elements[1].sigma - cov[1][1].sqrt()).abs() < 1e-12);
        // Prediction of the move from 2 to 3 with iteration 2's gradient.
        let dv: Vec<f64> = recs[3]
            .gates
            .iter()
            .map(|x| recs[3].voltages_mv[x] - recs[2].voltages_mv[x])
            .collect();
        assert_eq!(b.moves.len(), 4);
        for (m, d) in b.moves.iter().zip(&dv) {
            assert!((m.1 - d).abs() < 1e-12);
        }
        let expect: f64 = recs[2].gradients[0]
            .gradient
            .iter()
            .zip(&dv)
            .map(|(g, d)| g * d)
            .sum();
        let p = &b.predictions[0];
        assert_eq!((p.parameter.as_str(), p.unit.as_str()), ("t_sr", "ns"));
        assert!((p.predicted - expect).abs() < 1e-12 && p.g_dv == p.predicted);
        let measured = recs[3].parameters[0].value.unwrap() - recs[2].parameters[0].value.unwrap();
        assert!((p.measured - measured).abs() < 1e-12);
        let s = sentence(p);
        assert!(
            s.starts_with("t_sr: the filter expected a change of "),
            "{s}"
        );
        assert!(s.contains(" ns (g·Δv); it measured "), "{s}");
        // The first iteration has nothing to compare with.
        let first = belief(&h, 0).unwrap();
        assert!(first.previous.is_none() && first.predictions.is_empty());
        assert!(belief(&h, 99).is_none());
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn in_log_space_the_gradient_predicts_a_factor() {
        let mut recs = fake_records(4);
        for r in &mut recs {
            for g in &mut r.gradients {
                g.unit = "1/mV (log space)".into();
                g.gradient.iter_mut().for_each(|v| *v *= 0.01);
            }
        }
        let mut h = RunHistory::new();
        h.insert(recs.clone());
        let b = belief(&h, 2).unwrap();
        assert!(b.gradients.iter().all(|g| g.log_space));
        let p = &b.predictions[1];
        let before = recs[1].parameters[1].value.unwrap();
        assert!((p.predicted - before * p.g_dv.exp_m1()).abs() < 1e-9);
        let s = sentence(p);
        assert!(
            s.starts_with("w: the filter expected ln w to change by g·Δv = "),
            "{s}"
        );
        assert!(s.contains(" µV; it measured "), "{s}");
        // A gap before the iteration: no prediction.
        let mut h = RunHistory::new();
        h.insert(vec![recs[0].clone(), recs[2].clone()]);
        assert!(belief(&h, 2).unwrap().predictions.is_empty());
    }
}
