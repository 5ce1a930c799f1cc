//! What the dashboard shows, as a CSV table for a lab notebook or pandas
//! ([`window_csv`]): the iterations in the chart window, every number with
//! its unit in the column header.

use crate::history::RunHistory;

/// The rows of `h` with iterations in `[lo, hi]` as CSV: iteration, lab
/// time (s), tuned, per parameter its value, σ, target, tolerance and
/// whether the tuner rejected the value, per gradient element its value
/// and σ, per gate its voltage and step (mV). Missing numbers are empty.
pub fn window_csv(h: &RunHistory, lo: f64, hi: f64) -> String {
    let l = h.layout();
    let mut head = vec![
        "iteration".to_string(),
        "lab_time_s".to_string(),
        "tuned".to_string(),
    ];
    for (name, unit) in &l.parameters {
        for part in ["", "_sigma", "_target", "_tolerance"] {
            head.push(format!("{name}{part}_{unit}"));
        }
        head.push(format!("{name}_rejected"));
    }
    for (name, unit) in &l.gradients {
        for gate in &l.gates {
            let unit = unit.replace('/', "_per_");
            head.push(format!("d{name}_dV{gate}_{unit}"));
            head.push(format!("d{name}_dV{gate}_sigma_{unit}"));
        }
    }
    for gate in &l.gates {
        head.push(format!("V_{gate}_mV"));
        head.push(format!("step_{gate}_mV"));
    }
    let num = |x: f64| {
        if x.is_finite() {
            format!("{x}")
        } else {
            String::new()
        }
    };
    let mut out = head.join(",");
    out.push('\n');
    let range = h.range(lo, hi);
    for i in range {
        let r = &h.rows()[i];
        let mut cells = vec![
            r.iteration.to_string(),
            num(r.lab_seconds),
            r.tuned.to_string(),
        ];
        let c = |k: usize| h.column(k)[i];
        for p in 0..l.parameters.len() {
            let o = l.param(p);
            for k in 0..4 {
                cells.push(num(c(o + k)));
            }
            cells.push(c(l.rejected(p)).is_finite().to_string());
        }
        for g in 0..l.gradients.len() {
            for gi in 0..l.gates.len() {
                let o = l.grad(g, gi);
                cells.push(num(c(o)));
                cells.push(num(c(o + 1)));
            }
        }
        for gi in 0..l.gates.len() {
            cells.push(num(c(l.gate(gi))));
            cells.push(num(c(l.gate(gi) + 1)));
        }
        out.push_str(&cells.join(","));
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::fake_records;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn the_window_exports_with_units_in_the_header() {
        let mut h = RunHistory::new();
        h.insert(fake_records(10));
        let csv = window_csv(&h, 3.0, 6.0);
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 1 + 4, "{csv}");
        let head: Vec<&str> = lines[0].split(',').collect();
        assert_eq!(&head[..3], ["iteration", "lab_time_s", "tuned"]);
        assert!(head.contains(&"t_sr_ns"), "{head:?}");
        assert!(head.contains(&"w_sigma_µV"), "{head:?}");
        assert!(head.contains(&"V_N_mV"), "{head:?}");
        assert!(
            head.iter().any(|c| c.starts_with("dt_sr_dVN_ns_per_mV")),
            "{head:?}"
        );
        assert!(lines[1].starts_with("3,"), "{}", lines[1]);
        for l in &lines[1..] {
            assert_eq!(l.split(',').count(), head.len(), "{l}");
        }
    }
}
