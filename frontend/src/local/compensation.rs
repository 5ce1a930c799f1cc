//! Editor of the in-browser mode's virtual-gate (compensation) matrix: the
//! configuration a lab writes down after measuring the transition-line
//! slopes (rows: plungers PA, PB; columns: the qubit level's gates N, SA,
//! SB, T; mV of plunger per mV of gate), with its relative uncertainty.
//!
//! The page only edits numbers: the default is the core's
//! `PAPER_DEFAULT_COMPENSATION` ([`default_matrix`]), "perturb" is the core's benchmark
//! perturbation ([`spintune::benchmark::perturbed_compensation`]) and the
//! check is the core's config validation
//! ([`SimulationConfig::with_compensation`], which names a refused cell).
//! The edited matrix is used by the next run (after Reset), which cannot
//! start while the matrix is refused ([`LocalSettings::try_config`]).

use leptos::prelude::*;
use spintune::driver::SimulationConfig;
#[cfg(test)]
use spintune::driver::PAPER_DEFAULT_COMPENSATION;

use super::settings::{default_matrix, LocalSettings};
use super::LocalError;
use crate::widgets::NumberField;

/// Row (compensating plunger) and column (tuning gate) names of the matrix,
/// from the paper's setup.
pub fn axes() -> (Vec<String>, Vec<String>) {
    let cfg = SimulationConfig::paper_default();
    let rows = cfg
        .compensation()
        .map(|c| c.gates.clone())
        .unwrap_or_default();
    (rows, cfg.tuner.top().gates.clone())
}

/// The matrix a lab might have measured on the simulated device: its
/// first-order crosstalk perturbed by up to ± the settings' relative
/// uncertainty (uniform, seeded), as the benchmark gives each seed.
pub fn perturbed(settings: &LocalSettings, seed: u64) -> Vec<Vec<f64>> {
    let (rows, cols) = axes();
    let rows: Vec<&str> = rows.iter().map(String::as_str).collect();
    let cols: Vec<&str> = cols.iter().map(String::as_str).collect();
    spintune::benchmark::perturbed_compensation(
        &settings.to_config().device,
        &cols,
        &rows,
        settings.compensation_uncertainty,
        seed,
    )
}

/// What the core says of the settings' matrix and uncertainty: `Ok`, or the
/// refused cell (row, column) if one is at fault and the message.
pub fn check(settings: &LocalSettings) -> Result<(), (Option<(usize, usize)>, String)> {
    match settings.try_config() {
        Err(LocalError::Compensation(c)) => {
            let cell = c.cell;
            Err((cell, LocalError::Compensation(c).to_string()))
        }
        // Another setting is refused: its field says so.
        _ => Ok(()),
    }
}

/// A number for an input (empty for a non-finite one).
fn cell_text(x: f64) -> String {
    if x.is_finite() {
        format!("{x}")
    } else {
        String::new()
    }
}

/// The editor (in the in-browser mode's settings; applies on Reset).
#[component]
pub fn CompensationEditor(settings: RwSignal<LocalSettings>) -> impl IntoView {
    let (rows, cols) = axes();
    let seed = RwSignal::new(1.0f64);
    let verdict = Memo::new(move |_| settings.with(check));
    let bad_cell = move || verdict.with(|v| v.as_ref().err().and_then(|e| e.0));
    let unc = Signal::derive(move || settings.with(|s| s.compensation_uncertainty));
    let set_unc = Callback::new(move |v: f64| settings.update(|s| s.compensation_uncertainty = v));
    let set_seed = Callback::new(move |v: f64| seed.set(v.max(0.0).round()));
    // Shown transposed (a row per gate, a column per plunger) so that two
    // inputs share the sidebar's width; the matrix is [plunger][gate].
    let header = rows
        .iter()
        .map(|p| view! { <th scope="col">{p.clone()}</th> })
        .collect_view();
    let body = cols
        .iter()
        .enumerate()
        .map(|(c, gate)| {
            let cells = rows
                .iter()
                .enumerate()
                .map(|(r, plunger)| {
                    let label = format!("{plunger} per {gate} (mV/mV)");
                    view! {
                        <td>
                            <input type="number" step="0.01"
                                data-testid=format!("comp-{plunger}-{gate}")
                                aria-label=label.clone() title=label
                                class:invalid=move || bad_cell() == Some((r, c))
                                prop:value=move || settings.with(|s| {
                                    s.compensation.get(r).and_then(|row| row.get(c)).copied().map(cell_text).unwrap_or_default()
                                })
                                on:change=move |ev| {
                                    // Unparsable (or empty) is NaN: the core refuses it by name.
                                    let v = event_target_value(&ev).trim().parse::<f64>().unwrap_or(f64::NAN);
                                    settings.update(|s| {
                                        if let Some(x) = s.compensation.get_mut(r).and_then(|row| row.get_mut(c)) {
                                            *x = v;
                                        }
                                    });
                                } />
                        </td>
                    }
                })
                .collect_view();
            view! { <tr><th scope="row">{format!("V_{gate}")}</th>{cells}</tr> }
        })
        .collect_view();
    view! {
        <div class="comp" data-testid="compensation">
            <p class="field-label comp-title">
                "virtual-gate matrix " <span class="unit-inline">"(mV on PA, PB per mV on each gate)"</span>
            </p>
            <table class="comp-table">
                <thead><tr><th scope="col">"gate"</th>{header}</tr></thead>
                <tbody>{body}</tbody>
            </table>
            <NumberField label="matrix uncertainty (1σ)" unit="× value" testid="comp-uncertainty" step="0.05" get=unc set=set_unc />
            <div class="buttons comp-buttons">
                <button data-testid="comp-reset" on:click=move |_| settings.update(|s| s.compensation = default_matrix())>
                    "reset to default"
                </button>
                <button data-testid="comp-perturb"
                    title="the simulated device's crosstalk, each element off by up to ± the uncertainty (seeded), as the benchmark's per-seed matrices"
                    on:click=move |_| {
                        let s = seed.get_untracked() as u64;
                        settings.update(|st| st.compensation = perturbed(st, s));
                    }>
                    "perturb"
                </button>
            </div>
            <NumberField label="perturbation seed" unit="" testid="comp-seed" step="1" get=seed.into() set=set_seed />
            {move || verdict.get().err().map(|(_, e)| view! { <p class="error" data-testid="comp-error">{e}</p> })}
        </div>
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn an_edited_cell_reaches_the_runs_config_and_an_invalid_cell_is_named_and_refused() {
        let (rows, cols) = axes();
        assert_eq!(rows, ["PA", "PB"]);
        assert_eq!(cols, ["N", "SA", "SB", "T"]);
        let mut s = LocalSettings {
            compensation_uncertainty: 0.05,
            ..LocalSettings::default()
        };
        s.compensation[0][3] = -0.07;
        let run = s.build().expect("a valid matrix starts a run");
        let used = run.tuner().config().top().compensation.clone().unwrap();
        assert_eq!(used.matrix[0][3], -0.07);
        assert_eq!(used.matrix[1], PAPER_DEFAULT_COMPENSATION[1].to_vec());
        assert_eq!(used.relative_uncertainty, 0.05);
        assert_eq!(check(&s), Ok(()));
        // A non-finite cell: named, and the run does not start.
        s.compensation[1][2] = f64::NAN;
        let (cell, msg) = check(&s).unwrap_err();
        assert_eq!(cell, Some((1, 2)));
        assert!(msg.contains("PB per SB"), "{msg}");
        let Err(e) = s.build() else {
            panic!("an invalid matrix must not start a run");
        };
        assert!(e.to_string().contains("PB per SB"), "{e}");
        // Out of the core's bounds.
        s.compensation[1][2] = 5e6;
        let (cell, msg) = check(&s).unwrap_err();
        assert_eq!(cell, Some((1, 2)));
        assert!(msg.contains("out of range"), "{msg}");
        // An invalid uncertainty is refused too (no cell).
        s.compensation = default_matrix();
        s.compensation_uncertainty = -1.0;
        let (cell, msg) = check(&s).unwrap_err();
        assert_eq!(cell, None);
        // In plain words: no config path.
        assert!(msg.contains("matrix uncertainty"), "{msg}");
        assert!(
            !msg.contains("relative_uncertainty") && !msg.contains("tuner."),
            "{msg}"
        );
    }

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn perturbation_is_seeded_and_within_the_uncertainty_of_the_devices_crosstalk() {
        let s = LocalSettings {
            compensation_uncertainty: 0.2,
            ..LocalSettings::default()
        };
        let a = perturbed(&s, 7);
        assert_eq!(a, perturbed(&s, 7));
        assert_ne!(a, perturbed(&s, 8));
        let nominal = s
            .to_config()
            .device
            .nominal_compensation(&["N", "SA", "SB", "T"], &["PA", "PB"]);
        for (x, n) in a.iter().flatten().zip(nominal.iter().flatten()) {
            assert!((x - n).abs() <= 0.2 * n.abs() + 1e-15, "{x} vs {n}");
        }
        let run = LocalSettings {
            compensation: a.clone(),
            ..s
        }
        .build()
        .unwrap();
        assert_eq!(
            run.tuner()
                .config()
                .top()
                .compensation
                .as_ref()
                .unwrap()
                .matrix,
            a
        );
    }
}
