//! The alerts the page shows (data layer; no DOM): [`AlertCenter`] holds
//! the alerts of the runs this page follows — from a run's socket
//! (`alert` frames, the server decides) or from the run list's statuses
//! (the core's [`spintune::alert::status_alert`], never re-implemented) —
//! and how many of them the person has not seen yet, which the title
//! prefix and the favicon badge show (`attention`, the ui layer).

use spintune::protocol::Alert;

use crate::model::format_lab_time;

/// Alerts listed at most; an older one makes room for a newer one.
pub const MAX_SHOWN_ALERTS: usize = 20;

/// Dismissed alerts remembered at most (so that the server's replay of a
/// run's recent alerts on a reconnect does not bring them back).
pub const MAX_DISMISSED: usize = 64;

/// Whether two alerts report the same thing (run, kind, message).
fn same(a: &Alert, b: &Alert) -> bool {
    a.run == b.run && a.kind == b.kind && a.message == b.message
}

/// One listed alert.
#[derive(Debug, Clone, PartialEq)]
pub struct ShownAlert {
    /// Names it for the dismiss button.
    pub key: u64,
    /// What happened.
    pub alert: Alert,
    /// When the server raised it (RFC 3339 UTC), if it said.
    pub at: Option<String>,
}

impl ShownAlert {
    /// One line for a person, e.g. `Run #3 “night”: finished — finished
    /// after 12 iterations … (lab time 1.5 min)`.
    pub fn text(&self) -> String {
        describe(&self.alert)
    }
}

/// The alert in plain words, with the run and its lab time.
pub fn describe(a: &Alert) -> String {
    format!(
        "Run #{} “{}”: {} — {} (lab time {})",
        a.run,
        a.name,
        a.kind.label(),
        a.message,
        format_lab_time(a.lab_seconds)
    )
}

/// The listed alerts and how many are unseen.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct AlertCenter {
    items: Vec<ShownAlert>,
    unseen: usize,
    next_key: u64,
    /// Dismissed on this page, newest last (at most [`MAX_DISMISSED`]).
    dismissed: Vec<Alert>,
}

impl AlertCenter {
    /// Nothing listed.
    pub fn new() -> Self {
        Self::default()
    }

    /// List `alert` (unseen); `false` if the same alert (run, kind,
    /// message) is listed already — a run's socket and the run list may
    /// both report one status change, and a socket gets a run's recent
    /// alerts again when it reconnects — or was dismissed on this page.
    pub fn push(&mut self, alert: Alert, at: Option<String>) -> bool {
        if self.items.iter().any(|s| same(&s.alert, &alert))
            || self.dismissed.iter().any(|d| same(d, &alert))
        {
            return false;
        }
        if self.items.len() == MAX_SHOWN_ALERTS {
            self.items.remove(0);
        }
        self.items.push(ShownAlert {
            key: self.next_key,
            alert,
            at,
        });
        self.next_key += 1;
        self.unseen = (self.unseen + 1).min(self.items.len());
        true
    }

    /// The person has seen the page (focus, a click): nothing is unseen;
    /// the list stays.
    pub fn seen(&mut self) {
        self.unseen = 0;
    }

    /// Remove one alert (its dismiss button); the person has seen the rest.
    pub fn dismiss(&mut self, key: u64) {
        if let Some(i) = self.items.iter().position(|s| s.key == key) {
            let gone = self.items.remove(i);
            self.remember_dismissed(gone.alert);
        }
        self.unseen = 0;
    }

    /// Remove every alert.
    pub fn dismiss_all(&mut self) {
        for gone in std::mem::take(&mut self.items) {
            self.remember_dismissed(gone.alert);
        }
        self.unseen = 0;
    }

    fn remember_dismissed(&mut self, alert: Alert) {
        if self.dismissed.len() == MAX_DISMISSED {
            self.dismissed.remove(0);
        }
        self.dismissed.push(alert);
    }

    /// Listed alerts, oldest first.
    pub fn items(&self) -> &[ShownAlert] {
        &self.items
    }

    /// Alerts the person has not seen.
    pub fn unseen(&self) -> usize {
        self.unseen
    }

    /// The document title: `base`, with `(n) ⚠ ` in front while `n`
    /// alerts are unseen.
    pub fn title(&self, base: &str) -> String {
        if self.unseen == 0 {
            base.to_string()
        } else {
            format!("({}) ⚠ {base}", self.unseen)
        }
    }
}

/// `title` without a prefix [`AlertCenter::title`] put in front.
pub fn base_title(title: &str) -> &str {
    match title.strip_prefix('(').and_then(|t| t.split_once(") ⚠ ")) {
        Some((n, rest)) if !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()) => rest,
        _ => title,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use spintune::protocol::AlertKind;

    fn alert(run: u64, kind: AlertKind, message: &str) -> Alert {
        Alert {
            run,
            name: "night".into(),
            kind,
            message: message.into(),
            lab_seconds: 90.0,
            iteration: Some(11),
        }
    }

    #[test]
    fn unseen_alerts_prefix_the_title_until_seen_or_dismissed() {
        let mut c = AlertCenter::new();
        assert_eq!(c.title("spintune"), "spintune");
        assert!(c.push(
            alert(3, AlertKind::Finished, "finished after 12 iterations"),
            None
        ));
        assert_eq!(c.title("spintune"), "(1) ⚠ spintune");
        // The same alert again (the run list after the socket): not twice.
        assert!(!c.push(
            alert(3, AlertKind::Finished, "finished after 12 iterations"),
            None
        ));
        assert!(c.push(
            alert(4, AlertKind::Faulted, "device fault: leakage"),
            Some("t".into())
        ));
        assert_eq!(c.title("spintune"), "(2) ⚠ spintune");
        assert_eq!(base_title(&c.title("spintune — x")), "spintune — x");
        c.seen();
        assert_eq!((c.unseen(), c.items().len()), (0, 2));
        assert_eq!(c.title("spintune"), "spintune");
        let key = c.items()[0].key;
        assert!(c.push(alert(5, AlertKind::Failed, "failed: disk full"), None));
        c.dismiss(key);
        assert_eq!((c.unseen(), c.items().len()), (0, 2));
        c.dismiss_all();
        assert!(c.items().is_empty());
        // A reconnected socket replays the run's recent alerts: what was
        // dismissed here stays dismissed; a new alert of the run shows.
        assert!(!c.push(alert(5, AlertKind::Failed, "failed: disk full"), None));
        assert!(!c.push(
            alert(3, AlertKind::Finished, "finished after 12 iterations"),
            None
        ));
        assert!(c.push(alert(5, AlertKind::Failed, "failed: store gone"), None));
        assert_eq!(c.unseen(), 1);
    }

    #[test]
    fn the_list_is_bounded_and_says_what_happened_in_plain_words() {
        let mut c = AlertCenter::new();
        for run in 0..MAX_SHOWN_ALERTS as u64 + 3 {
            c.push(
                alert(run, AlertKind::NotBackInBand, "qubit: not back in band"),
                None,
            );
        }
        assert_eq!(c.items().len(), MAX_SHOWN_ALERTS);
        assert_eq!(c.items()[0].alert.run, 3);
        assert_eq!(c.unseen(), MAX_SHOWN_ALERTS);
        assert_eq!(
            c.items()[0].text(),
            "Run #3 “night”: not back in band — qubit: not back in band (lab time 1.5 min)"
        );
        assert_eq!(base_title("(x) ⚠ t"), "(x) ⚠ t");
    }
}
