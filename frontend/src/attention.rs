//! How the page asks for attention when a run raises an alert (ui layer):
//! the banner listing the alerts ([`AlertBanner`]), a prefix on the
//! document title and a badge on the favicon while alerts are unseen (a
//! focus of the window or a click in the page marks them seen), and a
//! browser notification ([`notify`]) when the person allowed them — the
//! banner's "Notify me" button asks; the page never asks on load.

use leptos::prelude::*;
use wasm_bindgen::JsCast;
use web_sys::{HtmlCanvasElement, HtmlImageElement, HtmlLinkElement};

use crate::alerts::{base_title, describe, AlertCenter};
use spintune::protocol::Alert;

/// The page's alerts, provided by the app as context.
pub type Alerts = RwSignal<AlertCenter>;

/// The alerts of the app's context (a fresh, unshown list if none).
pub fn use_alerts() -> Alerts {
    use_context::<Alerts>().unwrap_or_else(|| RwSignal::new(AlertCenter::new()))
}

/// List `alert` in `alerts` and, if it is new, show a browser
/// notification when the person allowed them.
pub fn raise(alerts: Alerts, alert: Alert, at: Option<String>) {
    let text = describe(&alert);
    let tag = format!("spintune-run-{}-{}", alert.run, alert.kind.name());
    let added = alerts.try_update(|c| c.push(alert, at)).unwrap_or(false);
    if added {
        notify(&text, &tag);
    }
}

/// Whether the browser lets this page show notifications.
fn permission() -> web_sys::NotificationPermission {
    // `Notification` is missing in some contexts (e.g. insecure origins in
    // some browsers): then it counts as denied.
    let has = js_sys::Reflect::has(&window(), &"Notification".into()).unwrap_or(false);
    if has {
        web_sys::Notification::permission()
    } else {
        web_sys::NotificationPermission::Denied
    }
}

/// A browser notification, if permitted (otherwise nothing).
pub fn notify(text: &str, tag: &str) {
    if permission() != web_sys::NotificationPermission::Granted {
        return;
    }
    let options = web_sys::NotificationOptions::new();
    options.set_body(text);
    options.set_tag(tag);
    let _ = web_sys::Notification::new_with_options("spintune alert", &options);
}

/// The page's icon link (`<link rel="icon">`).
fn icon_link() -> Option<HtmlLinkElement> {
    document()
        .query_selector("link[rel~='icon']")
        .ok()
        .flatten()?
        .dyn_into::<HtmlLinkElement>()
        .ok()
}

/// The favicon with a red badge counting `unseen`, as a PNG data URL
/// (drawn over `icon` if it has loaded, else over a plain tile).
fn badged_icon(icon: Option<&HtmlImageElement>, unseen: usize) -> Option<String> {
    let canvas = document()
        .create_element("canvas")
        .ok()?
        .dyn_into::<HtmlCanvasElement>()
        .ok()?;
    canvas.set_width(32);
    canvas.set_height(32);
    let ctx = canvas
        .get_context("2d")
        .ok()??
        .dyn_into::<web_sys::CanvasRenderingContext2d>()
        .ok()?;
    match icon.filter(|i| i.complete() && i.natural_width() > 0) {
        Some(img) => {
            let _ = ctx.draw_image_with_html_image_element_and_dw_and_dh(img, 0.0, 0.0, 32.0, 32.0);
        }
        None => {
            ctx.set_fill_style_str("#0072b2");
            ctx.fill_rect(0.0, 0.0, 32.0, 32.0);
        }
    }
    ctx.begin_path();
    let _ = ctx.arc(22.0, 10.0, 10.0, 0.0, std::f64::consts::TAU);
    ctx.set_fill_style_str("#d55e00");
    ctx.fill();
    ctx.set_fill_style_str("#ffffff");
    ctx.set_font("bold 15px sans-serif");
    ctx.set_text_align("center");
    ctx.set_text_baseline("middle");
    let label = if unseen > 9 {
        "!".to_string()
    } else {
        unseen.to_string()
    };
    let _ = ctx.fill_text(&label, 22.0, 11.0);
    canvas.to_data_url().ok()
}

/// The banner of the page's alerts, and the title, favicon and focus
/// handling that go with them. Mount once, under the page's header.
#[component]
pub fn AlertBanner() -> impl IntoView {
    let alerts = use_alerts();
    // The page's own title and icon, restored when nothing is unseen.
    let base = base_title(&document().title()).to_string();
    let original_icon = icon_link().map(|l| (l.href(), l.type_()));
    let icon_image = original_icon.as_ref().and_then(|(href, _)| {
        let img = HtmlImageElement::new().ok()?;
        img.set_src(href);
        Some(img)
    });
    let icon_image = send_wrapper::SendWrapper::new(icon_image);
    let unseen = Memo::new(move |_| alerts.with(|c| c.unseen()));
    Effect::new(move |_| {
        let n = unseen.get();
        document().set_title(&alerts.with_untracked(|c| c.title(&base)));
        let (Some(link), Some((href, kind))) = (icon_link(), original_icon.as_ref()) else {
            return;
        };
        match (n > 0)
            .then(|| badged_icon(icon_image.as_ref(), n))
            .flatten()
        {
            Some(url) => {
                link.set_type("image/png");
                link.set_href(&url);
            }
            None => {
                link.set_type(kind);
                link.set_href(href);
            }
        }
    });
    let mark_seen = move || {
        if alerts.with_untracked(|c| c.unseen() > 0) {
            alerts.update(|c| c.seen());
        }
    };
    let focus = window_event_listener(leptos::ev::focus, move |_| mark_seen());
    let click = window_event_listener(leptos::ev::pointerdown, move |_| mark_seen());
    on_cleanup(move || {
        focus.remove();
        click.remove();
    });
    view! {
        <Show when=move || alerts.with(|c| !c.items().is_empty())>
            <section class="alerts" role="alert" data-testid="alert-banner">
                <div class="alerts-head">
                    <strong>"⚠ Alerts"</strong>
                    <button data-testid="alert-dismiss-all" on:click=move |_| alerts.update(|c| c.dismiss_all())>"Dismiss all"</button>
                </div>
                <ul>
                    <For
                        each=move || alerts.with(|c| c.items().to_vec())
                        key=|s| s.key
                        children=move |s| {
                            let key = s.key;
                            let when = s.at.as_deref().map(|at| format!(" · raised {}", at.replace('T', " ").replace('Z', " UTC"))).unwrap_or_default();
                            view! {
                                <li data-testid="alert-item" data-kind=s.alert.kind.name() data-run=s.alert.run>
                                    <span class="alert-text">{s.text()}{when}</span>
                                    <button data-testid="alert-dismiss" title="remove this alert" on:click=move |_| alerts.update(|c| c.dismiss(key))>"Dismiss"</button>
                                </li>
                            }
                        }
                    />
                </ul>
            </section>
        </Show>
    }
}

/// "Notify me": asks the browser's permission for notifications (only when
/// pressed; shown while the browser has not been asked).
#[component]
pub fn NotifyButton() -> impl IntoView {
    let can_ask = RwSignal::new(permission() == web_sys::NotificationPermission::Default);
    let ask = move |_| {
        let Ok(promise) = web_sys::Notification::request_permission() else {
            can_ask.set(false);
            return;
        };
        leptos::task::spawn_local(async move {
            let _ = wasm_bindgen_futures::JsFuture::from(promise).await;
            let _ = can_ask.try_set(permission() == web_sys::NotificationPermission::Default);
        });
    };
    view! {
        <Show when=move || can_ask.get()>
            <button class="notify" data-testid="alert-notify"
                title="show a browser notification when a run faults, finishes or fails (asks the browser's permission)"
                on:click=ask>"Notify me"</button>
        </Show>
    }
}
