//! Small form widgets shared by the dashboard's panels.

use leptos::prelude::*;

/// A labelled numeric input bound to a field of the settings.
#[component]
pub(crate) fn NumberField(
    label: &'static str,
    unit: &'static str,
    testid: &'static str,
    step: &'static str,
    get: Signal<f64>,
    set: Callback<f64>,
) -> impl IntoView {
    view! {
        <label class="field">
            <span class="field-label">{label}</span>
            <span class="field-input">
                <input type="number" step=step data-testid=testid
                    prop:value=move || get.get().to_string()
                    on:change=move |ev| {
                        if let Ok(v) = event_target_value(&ev).trim().parse::<f64>() {
                            if v.is_finite() { set.run(v) }
                        }
                    } />
                <span class="unit">{unit}</span>
            </span>
        </label>
    }
}
