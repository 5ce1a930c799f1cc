//! Small form widgets shared by the dashboard's panels.

use leptos::prelude::*;

pub use crate::model::FieldError;

/// What a [`NumberField`] says of the text typed into it: `Ok(v)` to apply,
/// or the plain reason it is not applied (an empty field, not a number, or
/// what `check` refused).
pub fn parse_field(
    text: &str,
    check: Option<&dyn Fn(f64) -> Result<(), FieldError>>,
) -> Result<f64, FieldError> {
    let text = text.trim();
    if text.is_empty() {
        return Err(FieldError::new("empty: enter a number"));
    }
    let v = text
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| FieldError::new("not a number"))?;
    if let Some(check) = check {
        check(v)?;
    }
    Ok(v)
}

/// A labelled numeric input bound to a field of the settings. A value that
/// is empty, not a number or refused by `check` is not applied: the reason
/// is shown under the field (`data-testid="<testid>-error"`, wrapping), the
/// input is marked invalid and its `testid` is held in `invalid` until the
/// field holds a valid value again.
#[component]
pub(crate) fn NumberField(
    label: &'static str,
    unit: &'static str,
    testid: &'static str,
    step: &'static str,
    get: Signal<f64>,
    set: Callback<f64>,
    /// Which values are allowed (all finite numbers if not given).
    #[prop(optional)]
    check: Option<Callback<f64, Result<(), FieldError>>>,
    /// The fields now holding a value that was not applied.
    #[prop(optional)]
    invalid: Option<RwSignal<Vec<&'static str>>>,
    /// A hover explanation of the field.
    #[prop(optional)]
    title: &'static str,
) -> impl IntoView {
    let problem = RwSignal::new(None::<String>);
    let mark = move |bad: bool| {
        if let Some(set) = invalid {
            let has = set.with_untracked(|s| s.contains(&testid));
            if bad && !has {
                set.update(|s| s.push(testid));
            } else if !bad && has {
                set.update(|s| s.retain(|t| *t != testid));
            }
        }
    };
    on_cleanup(move || mark(false));
    view! {
        <label class="field" class:invalid=move || problem.with(|p| p.is_some()) title=title>
            <span class="field-label">{label}</span>
            <span class="field-input">
                <input type="number" step=step data-testid=testid
                    aria-invalid=move || problem.with(|p| p.is_some()).to_string()
                    prop:value=move || get.get().to_string()
                    on:change=move |ev| {
                        let checker = check.map(|c| move |v: f64| c.run(v));
                        let parsed = parse_field(
                            &event_target_value(&ev),
                            checker.as_ref().map(|c| c as &dyn Fn(f64) -> Result<(), FieldError>),
                        );
                        match parsed {
                            Ok(v) => {
                                problem.set(None);
                                mark(false);
                                set.run(v);
                            }
                            Err(e) => {
                                problem.set(Some(e.to_string()));
                                mark(true);
                            }
                        }
                    } />
                <span class="unit">{unit}</span>
            </span>
            {move || problem.get().map(|p| view! {
                <span class="field-error" role="alert" data-testid=format!("{testid}-error")>{p}</span>
            })}
        </label>
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg_attr(not(target_arch = "wasm32"), test)]
    #[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
    fn a_cleared_or_refused_field_says_why_and_is_not_applied() {
        assert_eq!(parse_field(" 2.5 ", None), Ok(2.5));
        assert_eq!(
            parse_field("", None).unwrap_err().to_string(),
            "empty: enter a number"
        );
        assert_eq!(
            parse_field("abc", None).unwrap_err(),
            FieldError::new("not a number")
        );
        let positive = |v: f64| {
            if v > 0.0 {
                Ok(())
            } else {
                Err(FieldError::new("must be more than 0"))
            }
        };
        assert_eq!(
            parse_field("-3", Some(&positive)).unwrap_err().message,
            "must be more than 0"
        );
        assert_eq!(parse_field("3", Some(&positive)), Ok(3.0));
    }
}
