//! The viewer client, natively: each test plays the server (and the shell)
//! and checks what the client asks for.

use spintune::protocol::{Fault, FaultKind, RunStatus};

use super::*;
use crate::api::ApiError;
use crate::model::{fake_records, status_label};

/// A client and the history it fills, fed by the test.
struct Viewer {
    client: LiveClient,
    history: RunHistory,
}

impl Viewer {
    fn new(run: u64, total_hint: Option<u64>) -> Self {
        Self {
            client: LiveClient::new(run, total_hint),
            history: RunHistory::new(),
        }
    }

    /// Feed one event and return every action it caused.
    fn feed(&mut self, event: Event) -> Vec<Action> {
        self.client.handle(event, &mut self.history);
        std::iter::from_fn(|| self.client.poll()).collect()
    }

    /// The server sends `message` on `socket` (as text, like the browser).
    fn frame(&mut self, socket: SocketId, message: &ServerMessage) -> Vec<Action> {
        self.feed(Event::Frame {
            socket,
            text: serde_json::to_string(message).unwrap(),
        })
    }

    /// Start (or tick) until a socket is asked for; open it; the server says hello.
    fn start_open(&mut self, hello: &ServerMessage) -> (SocketId, Vec<Action>) {
        let socket = opened(&self.feed(Event::Start)).expect("a socket").0;
        assert_eq!(
            self.feed(Event::Opened(socket)),
            [Action::Conn(ConnState::Open)]
        );
        let actions = self.frame(socket, hello);
        (socket, actions)
    }
}

/// The client messages sent among `actions`.
fn sent(actions: &[Action]) -> Vec<ClientMessage> {
    actions
        .iter()
        .filter_map(|a| match a {
            Action::Send { text, .. } => Some(serde_json::from_str(text).unwrap()),
            _ => None,
        })
        .collect()
}

/// The socket asked for among `actions`, and its `from`.
fn opened(actions: &[Action]) -> Option<(SocketId, u64)> {
    actions.iter().find_map(|a| match a {
        Action::Open { socket, from } => Some((*socket, *from)),
        _ => None,
    })
}

fn notices(actions: &[Action]) -> Vec<&str> {
    actions
        .iter()
        .filter_map(|a| match a {
            Action::Notice(n) => Some(n.as_str()),
            _ => None,
        })
        .collect()
}

fn summary(iterations: u64, status: RunStatus) -> RunSummary {
    RunSummary {
        id: 1,
        name: "demo".into(),
        status,
        iterations,
        lab_seconds: 0.0,
        tuned: false,
        driver: None,
    }
}

fn hello(iterations: u64) -> ServerMessage {
    ServerMessage::Hello {
        version: PROTOCOL_VERSION,
        run: summary(iterations, RunStatus::Running),
    }
}

/// A page of `recs[a..b]` (as summaries, like the server sends).
fn page(recs: &[IterationRecord], a: usize, b: usize, more_before: bool) -> ServerMessage {
    ServerMessage::History {
        records: recs[a..b].iter().map(|r| r.summary()).collect(),
        more_before,
    }
}

fn error(message: &str) -> ServerMessage {
    ServerMessage::Error {
        message: message.into(),
    }
}

fn history_request(before: u64, limit: u32) -> ClientMessage {
    ClientMessage::History {
        before: Some(before),
        limit: Some(limit),
    }
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn backoff_grows_and_caps() {
    assert_eq!(backoff_ms(1), 500);
    assert_eq!(backoff_ms(2), 1000);
    assert_eq!(backoff_ms(4), 4000);
    assert_eq!(backoff_ms(6), 10_000);
    assert_eq!(backoff_ms(60), 10_000);
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn the_first_socket_asks_for_the_newest_page_and_states_the_protocol_path() {
    // Known size: connect at once, from the start of the newest page.
    let mut v = Viewer::new(3, Some(1000));
    let actions = v.feed(Event::Start);
    assert_eq!(
        actions,
        [
            Action::Conn(ConnState::Connecting { attempt: 0 }),
            Action::Open {
                socket: SocketId(0),
                from: 1000 - DEFAULT_HISTORY_PAGE as u64
            }
        ]
    );
    // Unknown size: the summary first, then the socket.
    let mut v = Viewer::new(3, None);
    assert_eq!(
        v.feed(Event::Start),
        [Action::FetchSummary {
            path: "/api/runs/3".into()
        }]
    );
    let actions = v.feed(Event::Summary(Ok(summary(50, RunStatus::Running))));
    assert_eq!(opened(&actions), Some((SocketId(0), 0)));
    // A server that cannot be reached: connect anyway (and retry from there).
    let mut v = Viewer::new(3, None);
    v.feed(Event::Start);
    let actions = v.feed(Event::Summary(Err(ApiError::Unreachable("x".into()))));
    assert_eq!(opened(&actions), Some((SocketId(0), 0)));
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn an_error_before_hello_is_a_refused_handshake_and_is_not_retried() {
    let mut v = Viewer::new(1, Some(0));
    let socket = opened(&v.feed(Event::Start)).unwrap().0;
    v.feed(Event::Opened(socket));
    let actions = v.frame(
        socket,
        &error("this server speaks protocol v3; the client stated v2"),
    );
    assert!(actions.contains(&Action::Close { socket }), "{actions:?}");
    assert!(actions.contains(&Action::Conn(ConnState::Closed {
        reason: "refused by the server: this server speaks protocol v3; the client stated v2"
            .into()
    })));
    assert!(notices(&actions)[0].contains(&format!("speaks protocol v{PROTOCOL_VERSION}")));
    assert!(!actions
        .iter()
        .any(|a| matches!(a, Action::ScheduleReconnect { .. } | Action::Open { .. })));
    // The server closes the socket: nothing more, ever.
    assert_eq!(
        v.feed(Event::Closed {
            socket,
            code: 1000,
            reason: String::new()
        }),
        []
    );
    assert_eq!(v.feed(Event::Tick { now_ms: 3_600_000 }), []);
    assert!(matches!(v.client.conn(), ConnState::Closed { .. }));
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn after_hello_an_error_is_a_notice_and_the_status_shows() {
    let mut v = Viewer::new(1, Some(0));
    let faulted = ServerMessage::Hello {
        version: PROTOCOL_VERSION,
        run: summary(
            0,
            RunStatus::Faulted {
                fault: Fault::new(FaultKind::Device, "timeout"),
            },
        ),
    };
    let (socket, actions) = v.start_open(&faulted);
    assert_eq!(
        sent(&actions),
        [ClientMessage::Subscribe {
            scans: true,
            alerts: true
        }]
    );
    assert_eq!(
        v.client.summary().map(|s| status_label(&s.status)),
        Some(
            "faulted — Instrument fault: timeout — needs a person: check the instrument, then Resume"
                .into()
        )
    );
    // The subscription is accepted silently; an unasked page and an answer
    // to a control accept it. Here the error is the control's.
    v.frame(socket, &page(&fake_records(0), 0, 0, false));
    v.feed(Event::Unlock { token: "t".into() });
    v.frame(socket, &ServerMessage::AuthOk);
    v.feed(Event::Control(ControlCommand::Pause));
    let actions = v.frame(socket, &error("unknown parameter x"));
    assert_eq!(notices(&actions), ["server: unknown parameter x"]);
    assert!(!actions.iter().any(|a| matches!(a, Action::Close { .. })));
    assert_eq!(v.client.conn(), &ConnState::Open);
    // An alert frame (the socket asked for them) is handed to the page,
    // and changes nothing else.
    let alert = spintune::protocol::Alert {
        run: 1,
        name: "night".into(),
        kind: spintune::protocol::AlertKind::Faulted,
        message: "device fault: timeout".into(),
        lab_seconds: 60.0,
        iteration: None,
    };
    let actions = v.frame(
        socket,
        &ServerMessage::Alert {
            alert: alert.clone(),
            at: "2026-11-24T09:10:11Z".into(),
        },
    );
    assert_eq!(
        actions,
        [Action::Alert {
            alert,
            at: "2026-11-24T09:10:11Z".into()
        }]
    );
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn hello_of_another_version_is_named_and_cannot_cause_a_reconnection_storm() {
    let mut v = Viewer::new(1, Some(0));
    let old = ServerMessage::Hello {
        version: 1,
        run: summary(0, RunStatus::Running),
    };
    let (mut socket, actions) = v.start_open(&old);
    assert!(notices(&actions)[0].contains("protocol v1"), "{actions:?}");
    // Such a server drops every socket after its hello: the delays keep
    // growing (its hello does not count as a good connection), bounded.
    let mut delays = Vec::new();
    let mut now = 0;
    for _ in 0..8 {
        let actions = v.feed(Event::Closed {
            socket,
            code: 1006,
            reason: String::new(),
        });
        let delay = actions
            .iter()
            .find_map(|a| match a {
                Action::ScheduleReconnect { delay_ms } => Some(*delay_ms),
                _ => None,
            })
            .expect("a reconnection");
        delays.push(delay);
        now += delay as u64;
        socket = opened(&v.feed(Event::Tick { now_ms: now })).unwrap().0;
        v.feed(Event::Opened(socket));
        v.frame(socket, &old);
    }
    assert_eq!(
        delays,
        [500, 1000, 2000, 4000, 8000, 10_000, 10_000, 10_000]
    );
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn a_dropped_socket_reconnects_with_growing_bounded_delays_resuming_after_the_held() {
    let recs = fake_records(30);
    let mut v = Viewer::new(1, Some(30));
    let (mut socket, _) = v.start_open(&hello(30));
    v.frame(socket, &page(&recs, 0, 30, false));
    let mut now = 1_000;
    v.feed(Event::Tick { now_ms: now });
    // The server goes down: the open socket drops, then every new socket
    // closes without opening.
    let mut delays = Vec::new();
    for attempt in 1..=8u32 {
        let actions = v.feed(Event::Closed {
            socket,
            code: 1006,
            reason: String::new(),
        });
        let delay_ms = backoff_ms(attempt);
        assert_eq!(
            actions[..3],
            [
                Action::Close { socket },
                Action::Conn(ConnState::Reconnecting { attempt, delay_ms }),
                Action::ScheduleReconnect { delay_ms }
            ]
        );
        // A socket that never opened: does the run still exist? The server
        // is down, not missing the run: retrying goes on.
        let check = Action::FetchSummary {
            path: "/api/runs/1".into(),
        };
        assert_eq!(actions.get(3), (attempt > 1).then_some(&check));
        if attempt > 1 {
            assert_eq!(
                v.feed(Event::Summary(Err(ApiError::Unreachable("x".into())))),
                []
            );
        }
        delays.push(delay_ms);
        // Not yet due: nothing.
        assert_eq!(
            v.feed(Event::Tick {
                now_ms: now + delay_ms as u64 - 1
            }),
            []
        );
        now += delay_ms as u64;
        let actions = v.feed(Event::Tick { now_ms: now });
        assert_eq!(actions[0], Action::Conn(ConnState::Connecting { attempt }));
        // Resume after the newest held iteration.
        let (next, from) = opened(&actions).unwrap();
        assert_eq!(from, 30);
        assert_ne!(next, socket);
        socket = next;
    }
    assert_eq!(
        delays,
        [500, 1000, 2000, 4000, 8000, 10_000, 10_000, 10_000]
    );
    // The server is back: a good hello resets the back-off.
    v.feed(Event::Opened(socket));
    v.frame(socket, &hello(30));
    let actions = v.feed(Event::Closed {
        socket,
        code: 1006,
        reason: String::new(),
    });
    assert!(actions.contains(&Action::ScheduleReconnect { delay_ms: 500 }));
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn events_of_a_replaced_socket_are_ignored() {
    let mut v = Viewer::new(1, Some(0));
    let (old, _) = v.start_open(&hello(0));
    v.feed(Event::Closed {
        socket: old,
        code: 1006,
        reason: String::new(),
    });
    let new = opened(&v.feed(Event::Tick { now_ms: 500 })).unwrap().0;
    assert_eq!(v.frame(old, &hello(5)), []);
    assert_eq!(v.feed(Event::Opened(old)), []);
    assert_eq!(
        v.feed(Event::Closed {
            socket: old,
            code: 1006,
            reason: String::new()
        }),
        []
    );
    assert_eq!(v.history.total(), 0);
    assert_eq!(v.feed(Event::Opened(new)), [Action::Conn(ConnState::Open)]);
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn an_unknown_run_stops_retrying() {
    // `#live/99`: the summary is a 404 → closed, no socket, no retry.
    let mut v = Viewer::new(99, None);
    v.feed(Event::Start);
    let actions = v.feed(Event::Summary(Err(ApiError::Status {
        status: 404,
        detail: r#"{"error":"no run with id 99"}"#.into(),
    })));
    assert_eq!(opened(&actions), None);
    assert_eq!(
        v.client.conn(),
        &ConnState::Closed {
            reason: "no run 99 on the server".into()
        }
    );
    assert!(notices(&actions)[0].contains("no run with id 99"));
    assert_eq!(v.feed(Event::Tick { now_ms: 3_600_000 }), []);

    // A listed run deleted meanwhile: its socket is refused (closes without
    // opening); the check finds no run → the retry is cancelled for good.
    let mut v = Viewer::new(99, Some(10));
    let socket = opened(&v.feed(Event::Start)).unwrap().0;
    let actions = v.feed(Event::Closed {
        socket,
        code: 1006,
        reason: String::new(),
    });
    assert!(actions.contains(&Action::ScheduleReconnect { delay_ms: 500 }));
    assert!(actions.contains(&Action::FetchSummary {
        path: "/api/runs/99".into()
    }));
    let actions = v.feed(Event::Summary(Err(ApiError::Status {
        status: 404,
        detail: r#"{"error":"no run with id 99"}"#.into(),
    })));
    assert!(actions.contains(&Action::CancelReconnect), "{actions:?}");
    assert!(matches!(v.client.conn(), ConnState::Closed { .. }));
    assert_eq!(v.feed(Event::Tick { now_ms: 3_600_000 }), []);

    // The run exists (the socket failed for another reason): retrying goes on.
    let mut v = Viewer::new(5, Some(10));
    let socket = opened(&v.feed(Event::Start)).unwrap().0;
    v.feed(Event::Closed {
        socket,
        code: 1006,
        reason: String::new(),
    });
    assert_eq!(
        v.feed(Event::Summary(Ok(summary(10, RunStatus::Running)))),
        []
    );
    assert!(opened(&v.feed(Event::Tick { now_ms: 500 })).is_some());
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn a_socket_closing_after_the_run_ended_is_not_reopened() {
    let mut v = Viewer::new(1, Some(0));
    let (socket, _) = v.start_open(&hello(0));
    v.frame(
        socket,
        &ServerMessage::Status {
            run: summary(4, RunStatus::Finished),
        },
    );
    let actions = v.feed(Event::Closed {
        socket,
        code: 1000,
        reason: String::new(),
    });
    assert_eq!(
        actions,
        [
            Action::Close { socket },
            Action::Conn(ConnState::Closed {
                reason: "run has ended".into()
            })
        ]
    );
    assert_eq!(v.feed(Event::Tick { now_ms: 60_000 }), []);
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn history_pages_are_requested_and_merged_then_scans_and_live_gaps() {
    let recs = fake_records(106);
    let mut v = Viewer::new(1, Some(100));
    let (socket, _) = v.start_open(&hello(100));
    assert_eq!(v.history.total(), 100);
    // The newest page, unasked after hello: the page below it is asked for,
    // within the largest page.
    let actions = v.frame(socket, &page(&recs, 80, 100, true));
    assert_eq!(sent(&actions), [history_request(80, 80)]);
    // Asked once while it is on its way.
    assert_eq!(
        sent(&v.frame(
            socket,
            &ServerMessage::Status {
                run: summary(100, RunStatus::Running)
            }
        )),
        Vec::<ClientMessage>::new()
    );
    // The answer: the server holds nothing older than 30.
    let actions = v.frame(socket, &page(&recs, 30, 80, false));
    assert_eq!(v.history.len(), 70);
    assert_eq!(v.history.gaps(), vec![]);
    assert_eq!(sent(&actions), []);
    assert!(v.client.pending.is_empty() && v.client.page_in_flight.is_none());
    // Scans on request go to the inspected iteration.
    let actions = v.feed(Event::WantScans(42));
    assert_eq!(sent(&actions), [ClientMessage::Scans { iteration: 42 }]);
    v.frame(
        socket,
        &ServerMessage::Scans {
            iteration: 42,
            scans: recs[42].scans.clone(),
        },
    );
    assert_eq!(v.history.scans(42).map(|s| s.len()), Some(1));
    assert!(v.client.pending.is_empty());
    // A live frame after a gap: kept, the gap is asked for next.
    let actions = v.frame(
        socket,
        &ServerMessage::Iteration {
            record: recs[105].clone(),
        },
    );
    assert_eq!(sent(&actions), [history_request(105, 5)]);
    assert_eq!(v.client.summary().map(|s| s.iterations), Some(106));
    assert!(actions
        .iter()
        .any(|a| matches!(a, Action::Summary(s) if s.iterations == 106)));
    v.frame(socket, &page(&recs, 100, 105, true));
    assert_eq!(v.history.gaps(), vec![]);
    assert_eq!(v.history.len(), 76);
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn a_large_gap_is_paged_in_pages_of_at_most_the_largest() {
    let n = 4500;
    assert_eq!(MAX_HISTORY_PAGE, 2000);
    let recs = fake_records(n);
    let mut v = Viewer::new(1, Some(n));
    let (socket, _) = v.start_open(&hello(n));
    let top = n as usize - 200;
    let mut actions = v.frame(socket, &page(&recs, top, n as usize, true));
    let mut asked = Vec::new();
    while let [ClientMessage::History {
        before: Some(before),
        limit: Some(limit),
    }] = sent(&actions)[..]
    {
        assert!(limit <= MAX_HISTORY_PAGE);
        asked.push((before, limit));
        let a = (before - limit as u64) as usize;
        actions = v.frame(socket, &page(&recs, a, before as usize, a > 0));
    }
    assert_eq!(
        asked,
        [
            (4300, MAX_HISTORY_PAGE),
            (2300, MAX_HISTORY_PAGE),
            (300, 300)
        ]
    );
    assert_eq!(v.history.len(), n as usize);
    assert_eq!(v.history.gaps(), vec![]);
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn lagged_takes_the_newest_page_unasked_and_pages_back_the_gap() {
    let recs = fake_records(400);
    let mut v = Viewer::new(1, Some(100));
    let (socket, _) = v.start_open(&hello(100));
    v.frame(socket, &page(&recs, 0, 100, false));
    assert_eq!(v.history.gaps(), vec![]);
    // Live up to 110, then the viewer falls behind.
    for r in &recs[100..110] {
        v.frame(socket, &ServerMessage::Iteration { record: r.clone() });
    }
    let actions = v.frame(socket, &ServerMessage::Lagged { skipped: 150 });
    assert!(notices(&actions)[0].contains("150 live messages skipped"));
    // The newest page follows, unasked: 200..400. The gap 110..200 is asked for.
    let actions = v.frame(socket, &page(&recs, 200, 400, true));
    assert_eq!(v.history.gaps(), vec![(110, 200)]);
    assert_eq!(sent(&actions), [history_request(200, 90)]);
    v.frame(socket, &page(&recs, 110, 200, true));
    assert_eq!(v.history.gaps(), vec![]);
    assert_eq!(v.history.len(), 400);

    // Lagged while a page request is on its way: the unasked page is not
    // taken for its answer (which comes after it).
    let recs = fake_records(1000);
    let mut v = Viewer::new(1, Some(1000));
    let (socket, _) = v.start_open(&hello(1000));
    let actions = v.frame(socket, &page(&recs, 800, 1000, true));
    assert_eq!(sent(&actions), [history_request(800, 800)]);
    v.frame(socket, &ServerMessage::Lagged { skipped: 1 });
    v.frame(socket, &page(&recs, 800, 1000, true));
    assert_eq!(v.client.page_in_flight, Some((800, 800)));
    v.frame(socket, &page(&recs, 0, 800, false));
    assert_eq!(v.client.page_in_flight, None);
    assert_eq!(v.history.gaps(), vec![]);
    assert_eq!(v.history.len(), 1000);
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn a_server_refusing_socket_paging_is_paged_over_http() {
    let recs = fake_records(106);
    let mut v = Viewer::new(1, Some(100));
    let (socket, _) = v.start_open(&hello(100));
    let actions = v.frame(socket, &page(&recs, 80, 100, true));
    assert_eq!(sent(&actions), [history_request(80, 80)]);
    // Such a server refuses `subscribe` and `history`: the first error is
    // the subscription's (ignored), the second moves paging to HTTP with a
    // notice; the socket stays.
    let actions = v.frame(socket, &error("not implemented yet"));
    assert_eq!(actions, []);
    assert_eq!(v.client.paging(), PagingMode::Socket);
    let actions = v.frame(socket, &error("not implemented yet"));
    assert_eq!(v.client.paging(), PagingMode::Http);
    assert!(actions.contains(&Action::Paging(PagingMode::Http)));
    assert!(
        notices(&actions)[0].contains("over HTTP")
            && notices(&actions)[0].contains("not implemented yet")
    );
    // … and the same page is fetched over HTTP at once.
    assert!(actions.contains(&Action::FetchPage {
        before: 80,
        limit: 80,
        path: "/api/runs/1/iterations?from=0&limit=80".into()
    }));
    // The HTTP answer (records from 30; newer ones are dropped) is merged,
    // nothing older is left to ask for.
    let actions = v.feed(Event::Page {
        before: 80,
        limit: 80,
        result: Ok(recs[30..90].to_vec()),
    });
    assert_eq!(v.history.len(), 70);
    assert_eq!(v.history.gaps(), vec![(0, 30)]);
    assert_eq!(
        actions,
        [Action::FetchPage {
            before: 30,
            limit: 30,
            path: "/api/runs/1/iterations?from=0&limit=30".into(),
        }]
    );
    // Nothing there: the floor is set, no more requests.
    assert_eq!(
        v.feed(Event::Page {
            before: 30,
            limit: 30,
            result: Ok(vec![])
        }),
        []
    );
    assert_eq!(v.history.gaps(), vec![]);
    // Scans over HTTP too from now on.
    assert_eq!(
        v.feed(Event::WantScans(42)),
        [Action::FetchScans {
            iteration: 42,
            path: "/api/runs/1/iterations?from=42&limit=1".into()
        }]
    );
    v.feed(Event::Scans {
        iteration: 42,
        result: Ok(recs[42..43].to_vec()),
    });
    assert_eq!(v.history.scans(42).map(|s| s.len()), Some(1));
    // An HTTP failure is a notice.
    let actions = v.feed(Event::Scans {
        iteration: 43,
        result: Err(ApiError::Status {
            status: 500,
            detail: String::new(),
        }),
    });
    assert_eq!(
        notices(&actions),
        ["cannot load the scans of iteration 43: HTTP 500"]
    );
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn auth_and_control_answers_are_correlated() {
    let recs = fake_records(1000);
    let mut v = Viewer::new(1, Some(1000));
    // Controls before the socket is open are not sent.
    v.feed(Event::Start);
    let actions = v.feed(Event::Control(ControlCommand::Pause));
    assert_eq!(
        notices(&actions),
        ["not connected; try again when the badge says live"]
    );
    let socket = SocketId(0);
    v.feed(Event::Opened(socket));
    v.frame(socket, &hello(1000));
    // Unlock: the token goes out; a refusal is the token's.
    let actions = v.feed(Event::Unlock {
        token: " wrong ".into(),
    });
    assert_eq!(
        sent(&actions),
        [ClientMessage::Auth {
            token: "wrong".into()
        }]
    );
    assert_eq!(v.client.auth(), &AuthState::Pending);
    let actions = v.frame(socket, &error("invalid token"));
    assert_eq!(
        actions,
        [Action::Auth(AuthState::Refused("invalid token".into()))]
    );
    // The right one.
    v.feed(Event::Unlock {
        token: "secret".into(),
    });
    let actions = v.frame(socket, &ServerMessage::AuthOk);
    assert_eq!(actions, [Action::Auth(AuthState::Ok)]);
    // A page request is on its way, then a control.
    let actions = v.frame(socket, &page(&recs, 800, 1000, true));
    assert_eq!(sent(&actions), [history_request(800, 800)]);
    let actions = v.feed(Event::Control(ControlCommand::Stop));
    assert_eq!(
        sent(&actions),
        [ClientMessage::Control {
            command: ControlCommand::Stop
        }]
    );
    // A status broadcast before the page's answer is not the control's answer.
    v.frame(
        socket,
        &ServerMessage::Status {
            run: summary(1000, RunStatus::Paused),
        },
    );
    // (the run is paused now: no live frame brings scans, so its newest
    // iteration's scans are asked for)
    assert_eq!(
        v.client.pending,
        [Pending::History, Pending::Control, Pending::Scans(999)]
    );
    // The page's answer, then the control's refusal: the refusal is a
    // notice; paging stays on the socket.
    v.frame(socket, &page(&recs, 0, 800, false));
    let actions = v.frame(socket, &error("run is stopping"));
    assert_eq!(notices(&actions), ["server: run is stopping"]);
    assert_eq!(v.client.paging(), PagingMode::Socket);
    v.frame(
        socket,
        &ServerMessage::Scans {
            iteration: 999,
            scans: recs[999].scans.clone(),
        },
    );
    assert!(v.client.pending.is_empty());
    // An accepted control is answered with the status.
    v.feed(Event::Control(ControlCommand::Resume));
    let actions = v.frame(
        socket,
        &ServerMessage::Status {
            run: summary(1000, RunStatus::Running),
        },
    );
    assert!(v.client.pending.is_empty());
    assert!(actions
        .iter()
        .any(|a| matches!(a, Action::Summary(s) if s.status == RunStatus::Running)));
    // The token is sent again on the next socket.
    v.feed(Event::Closed {
        socket,
        code: 1006,
        reason: String::new(),
    });
    let next = opened(&v.feed(Event::Tick { now_ms: 500 })).unwrap().0;
    let actions = v.feed(Event::Opened(next));
    assert_eq!(
        sent(&actions),
        [ClientMessage::Auth {
            token: "secret".into()
        }]
    );
    // … where the server (restarted with another token) refuses it.
    v.frame(next, &hello(1000));
    let actions = v.frame(next, &error("invalid token"));
    assert_eq!(
        actions,
        [Action::Auth(AuthState::Refused("invalid token".into()))]
    );
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn shutdown_closes_and_never_retries() {
    let mut v = Viewer::new(1, Some(0));
    let (socket, _) = v.start_open(&hello(0));
    v.feed(Event::Closed {
        socket,
        code: 1006,
        reason: String::new(),
    });
    assert_eq!(v.feed(Event::Shutdown), [Action::CancelReconnect]);
    assert_eq!(v.feed(Event::Tick { now_ms: 60_000 }), []);
    let mut v = Viewer::new(1, Some(0));
    let (socket, _) = v.start_open(&hello(0));
    assert_eq!(v.feed(Event::Shutdown), [Action::Close { socket }]);
}

#[cfg_attr(not(target_arch = "wasm32"), test)]
#[cfg_attr(target_arch = "wasm32", wasm_bindgen_test::wasm_bindgen_test)]
fn undecodable_frames_and_close_reasons_are_notices() {
    let mut v = Viewer::new(1, Some(0));
    let (socket, _) = v.start_open(&hello(0));
    let actions = v.feed(Event::Frame {
        socket,
        text: "{nope".into(),
    });
    assert!(notices(&actions)[0].starts_with("undecodable message from server"));
    let actions = v.feed(Event::Closed {
        socket,
        code: 1008,
        reason: "nothing received for 45 s (no pong)".into(),
    });
    assert_eq!(
        notices(&actions),
        ["socket closed: nothing received for 45 s (no pong)"]
    );
    let socket = opened(&v.feed(Event::Tick { now_ms: 500 })).unwrap().0;
    let actions = v.feed(Event::OpenFailed {
        socket,
        error: "ws://x: SyntaxError".into(),
    });
    assert_eq!(notices(&actions), ["cannot open ws://x: SyntaxError"]);
    assert!(actions.contains(&Action::ScheduleReconnect { delay_ms: 1000 }));
}
