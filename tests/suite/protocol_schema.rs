//! The protocol's JSON Schema against the code: docs/protocol.schema.json is what the code
//! generates, and a real daemon's traffic (every request sent, every reply and event it
//! writes, over its socket) validates against it. The lines are checked against a closed
//! copy of the schema (no property it does not describe), so a field the daemon sends
//! that the schema lacks fails here too; the committed schema itself stays open, since
//! clients must ignore fields they do not know.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::Daemon;
use crate::support::schema::{closed, errors, validator};
use rigd::daemon::protocol::{EVENT_KINDS, REQUEST_KINDS};
use rigd::daemon::schema::{document, document_text};
use rigd::rig::simulated;
use serde_json::{json, Value};
use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::Path;

const REGENERATE: &str = "cargo run --bin rigctl -- schema > docs/protocol.schema.json";

#[test]
fn the_committed_schema_is_what_the_code_generates() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/protocol.schema.json");
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == document_text(),
        "docs/protocol.schema.json is not what the wire types generate (a request, event or \
         field was added or changed): regenerate it with `{REGENERATE}` and commit it"
    );
}

/// The reply body (a `$defs` name) each request kind's `result` has. A new request adds
/// its line here and to the traffic below.
fn body_of(req: &Value) -> &'static str {
    let kind = req["kind"].as_str().unwrap();
    match kind {
        "hello" => "HelloReply",
        "submit" | "replay" | "resume_session" => "SubmitReply",
        "status" if req.get("job_id").is_some() => "JobStatus",
        "status" => "DaemonStatus",
        "list" => "ListReply",
        "cancel" => "CancelReply",
        "result" => "ResultReply",
        "subscribe" => "SubscribeReply",
        "unlock" | "home" | "reconnect" => "RigActionReply",
        "snap" => "SnapReply",
        "preview" => "PreviewReply",
        "preview_stop" => "PreviewStopReply",
        "position" => "PositionReply",
        "move" => "MoveReply",
        "stop" => "StopReply",
        "pause" | "resume" => "PauseReply",
        _ => panic!(
            "no reply body for `{kind}`: add it to body_of in tests/suite/protocol_schema.rs"
        ),
    }
}

/// A client that keeps every line it sends and receives.
struct Tap {
    out: UnixStream,
    input: BufReader<UnixStream>,
    next_id: u64,
    sent: Vec<Value>,
    got: Vec<Value>,
    /// Each ok reply's result with the request it answers.
    results: Vec<(Value, Value)>,
}

impl Tap {
    fn connect(socket: &Path) -> Tap {
        let s = UnixStream::connect(socket).unwrap();
        Tap {
            input: BufReader::new(s.try_clone().unwrap()),
            out: s,
            next_id: 1,
            sent: Vec::new(),
            got: Vec::new(),
            results: Vec::new(),
        }
    }

    fn line(&mut self) -> Value {
        let mut l = String::new();
        assert!(self.input.read_line(&mut l).unwrap() > 0, "rigd closed");
        let v: Value = serde_json::from_str(&l).unwrap();
        self.got.push(v.clone());
        v
    }

    /// Send `req` (with `v` and a fresh `id`); its reply.
    fn send(&mut self, mut req: Value) -> Value {
        let id = self.next_id;
        self.next_id += 1;
        req["v"] = 1.into();
        req["id"] = id.into();
        writeln!(self.out, "{req}").unwrap();
        self.sent.push(req.clone());
        loop {
            let l = self.line();
            if l["type"] == "reply" && l["id"] == id {
                if l["ok"] == true {
                    self.results.push((req, l["result"].clone()));
                }
                return l;
            }
        }
    }

    /// The result of `req`, which must succeed.
    fn ok(&mut self, req: Value) -> Value {
        let r = self.send(req);
        assert_eq!(r["ok"], true, "{r}");
        r["result"].clone()
    }

    /// Lines until job `id`'s terminal event; that event.
    fn until_end(&mut self, id: u64) -> Value {
        loop {
            let l = self.line();
            let end =
                ["finished", "failed", "cancelled"].contains(&l["event"].as_str().unwrap_or(""));
            if l["job_id"] == id && end {
                return l;
            }
        }
    }

    /// Lines until an event of this kind.
    fn until_event(&mut self, kind: &str) {
        while self.line()["event"] != kind {}
    }

    /// Lines until job `id`'s first `step` event.
    fn until_step(&mut self, id: u64) {
        while !(self.line()["event"] == "step" && self.got.last().unwrap()["job_id"] == id) {}
    }
}

/// Drive a daemon through every request kind and every event a job can end with but
/// `failed` (which needs a faulty rig: tests/suite/daemon_faults.rs).
fn traffic(tap: &mut Tap) {
    let hello = tap.ok(json!({"kind": "hello"}));
    assert_eq!(hello["capabilities"]["requests"], json!(REQUEST_KINDS));
    assert_eq!(hello["capabilities"]["events"], json!(EVENT_KINDS));
    tap.ok(json!({"kind": "status"}));
    tap.ok(json!({"kind": "subscribe"}));
    let job = json!({"step_um": 50.0, "steps": 3, "settle_ms": 0, "k": 2, "label": "schema"});
    let id = tap.ok(json!({"kind": "submit", "job": job}))["job_id"]
        .as_u64()
        .unwrap();
    let end = tap.until_end(id);
    assert_eq!(end["event"], "finished", "{end}");
    let session = end["session"].clone();
    tap.ok(json!({"kind": "status", "job_id": id}));
    tap.ok(json!({"kind": "result", "job_id": id}));
    // A study of two cases, twice: its `result.json` holds the study's summary.
    let study = json!({"study": ["case1", "case2"], "repeats": 2, "settle_ms": 0});
    let study = tap.ok(json!({"kind": "submit", "job": study}))["job_id"]
        .as_u64()
        .unwrap();
    assert_eq!(tap.until_end(study)["event"], "finished");
    tap.ok(json!({"kind": "result", "job_id": study}));
    tap.ok(json!({"kind": "list", "limit": 5}));
    tap.ok(json!({"kind": "subscribe", "job_id": id}));
    let replay = json!({"kind": "replay", "session": session, "processing": {"combine": "mean"}});
    let again = tap.ok(replay)["job_id"].as_u64().unwrap();
    tap.until_end(again);
    // A long capture, cancelled once it has a frame: `cancelled` with its detail.
    let long = json!({"step_um": 10.0, "steps": 2000, "settle_ms": 5, "process": false});
    let long = tap.ok(json!({"kind": "submit", "job": long}))["job_id"]
        .as_u64()
        .unwrap();
    tap.until_step(long);
    tap.ok(json!({"kind": "cancel", "job_id": long}));
    let end = tap.until_end(long);
    assert_eq!(end["event"], "cancelled");
    // Resumed from its first missing frame (`resumed_from` in the reply), cancelled again.
    let resumed = json!({"kind": "resume_session", "session": end["session"]});
    let resumed = tap.ok(resumed)["job_id"].as_u64().unwrap();
    tap.until_step(resumed);
    tap.ok(json!({"kind": "cancel", "job_id": resumed}));
    tap.until_end(resumed);
    tap.ok(json!({"kind": "unlock"}));
    tap.ok(json!({"kind": "home"}));
    tap.send(json!({"kind": "reconnect", "stage": "piezo"}));
    at_the_rig(tap);
    // Error replies: a job the rig refuses, a job that is not there.
    tap.send(json!({"kind": "submit", "job": {"step_um": 0.0, "steps": 3}}));
    tap.send(json!({"kind": "cancel", "job_id": 999_999}));
    tap.send(json!({"kind": "resume_session", "session": "nope"}));
}

/// Manual control, the live view, pause and resume, a 2-D plan.
fn at_the_rig(tap: &mut Tap) {
    tap.ok(json!({"kind": "position"}));
    tap.ok(json!({"kind": "move", "stage": "axis", "by_um": 100.0}));
    tap.ok(json!({"kind": "stop"}));
    tap.ok(json!({"kind": "snap", "scale": 0.5}));
    tap.ok(json!({"kind": "preview", "max_fps": 5.0, "scale": 0.25}));
    tap.until_event("preview");
    tap.ok(json!({"kind": "preview_stop"}));
    let grid = json!({"plan": {"grid": {"inner": {"stage": "axis", "step_um": 50.0, "steps": 2},
        "outer": {"stage": "piezo", "step_um": 10.0, "steps": 2}}}, "settle_ms": 0, "k": 2});
    let grid = tap.ok(json!({"kind": "submit", "job": grid}))["job_id"]
        .as_u64()
        .unwrap();
    tap.until_end(grid);
    let long = json!({"step_um": 10.0, "steps": 2000, "settle_ms": 5, "process": false});
    let long = tap.ok(json!({"kind": "submit", "job": long}))["job_id"]
        .as_u64()
        .unwrap();
    tap.until_step(long);
    tap.ok(json!({"kind": "pause", "job_id": long}));
    tap.until_event("paused");
    tap.ok(json!({"kind": "resume", "job_id": long}));
    tap.until_event("resumed");
    tap.ok(json!({"kind": "cancel", "job_id": long}));
    tap.until_end(long);
}

/// A `rigd --sim` rig whose small frames show the small board's two targets, so frames are
/// processed (`processed` events).
fn small_sim_rig(dir: &Path) -> rigd::rig::Rig {
    simulated(&crate::support::daemon::small_board_sim(dir)).unwrap()
}

#[test]
fn a_daemons_traffic_validates_against_the_schema() {
    let dir = tempfile::tempdir().unwrap();
    let daemon = Daemon::start(small_sim_rig(dir.path()));
    let mut tap = Tap::connect(&daemon.bg.socket);
    traffic(&mut tap);

    let doc = closed(&document());
    let request = validator(&doc, "Request");
    for r in &tap.sent {
        let e = errors(&request, r);
        assert!(e.is_empty(), "request {r}: {e:?}");
    }
    let line = validator(&doc, "ServerLine");
    for l in &tap.got {
        let e = errors(&line, l);
        assert!(e.is_empty(), "line {l}: {e:?}");
    }
    let mut bodies = BTreeMap::new();
    for (req, result) in &tap.results {
        let name = body_of(req);
        let v = bodies.entry(name).or_insert_with(|| validator(&doc, name));
        let e = errors(v, result);
        assert!(e.is_empty(), "{name} (the reply to {req}): {result}: {e:?}");
    }
    // What the traffic held: every reply body, every event kind but `failed` and
    // `calibrated` (the small board's two targets are too few for a field model: a
    // calibration job on the webcam rig, tests/suite/daemon_calibration.rs, sends it).
    let seen: BTreeSet<&str> = tap.got.iter().filter_map(|l| l["event"].as_str()).collect();
    let want: BTreeSet<&str> = EVENT_KINDS
        .iter()
        .copied()
        .filter(|k| !matches!(*k, "failed" | "calibrated"))
        .collect();
    assert_eq!(seen, want, "event kinds in the traffic");
    assert_eq!(
        bodies.len(),
        16,
        "reply bodies checked: {:?}",
        bodies.keys()
    );
    assert!(tap.got.iter().any(|l| l["ok"] == false), "no error reply");

    // `result.json` is typed to its leaves: a scan's runs with their measured objects and a
    // study's summary validated above, and a field the schema lacks inside either is refused.
    let results: Vec<&Value> = (tap.results.iter())
        .filter(|(req, _)| req["kind"] == "result")
        .map(|(_, r)| r)
        .collect();
    let scan = results
        .iter()
        .find(|r| r["result"]["runs"][0]["result"]["objects"][0].is_object())
        .expect("a result with a measured object");
    let study = results
        .iter()
        .find(|r| {
            r["result"]["study"]["cases"]
                .as_array()
                .is_some_and(|c| c.len() == 2)
        })
        .expect("a study's result");
    let reply = &bodies["ResultReply"];
    for (body, at) in [
        (scan, "/result/runs/0/result/objects/0"),
        (study, "/result/study/cases/0"),
        (study, "/result/study/stats/cases/0/targets/0"),
    ] {
        let mut with = (*body).clone();
        with.pointer_mut(at).unwrap()["extra_um"] = 1.into();
        assert!(
            !reply.is_valid(&with),
            "the closed schema took a field at {at}"
        );
    }

    // The closed copy is strict: an unknown field anywhere is refused. The committed
    // schema lets it through (clients ignore what they do not know).
    let step = tap.got.iter().find(|l| l["event"] == "step").unwrap();
    let open = validator(&document(), "ServerLine");
    let mut top = step.clone();
    top["extra"] = 1.into();
    let mut nested = step.clone();
    nested["timings"]["extra"] = 1.into();
    for with in [top, nested] {
        assert!(!line.is_valid(&with), "closed schema took {with}");
        assert!(open.is_valid(&with), "open schema refused {with}");
    }
}

#[test]
fn what_the_daemon_refuses_the_schema_refuses() {
    let doc = document();
    let request = validator(&doc, "Request");
    for bad in [
        json!({"kind": "launch"}),
        json!({"kind": "status", "jobid": 3}),
        json!({"kind": "hello", "x": 1}),
        json!({"v": 2, "kind": "hello"}),
        json!({"id": 1.5, "kind": "hello"}),
        json!({"id": 9_007_199_254_740_992_u64, "kind": "hello"}),
        json!({"kind": "submit", "job": {"step_um": "fifty"}}),
        json!({"kind": "submit", "job": {"steps": 3, "step": 5}}),
        json!({"kind": "submit", "job": ["axis", 50, 3]}),
        json!({"kind": "cancel"}),
    ] {
        let line = bad.to_string();
        let refused = rigd::daemon::protocol::decode_request(line.as_bytes()).is_err();
        assert!(refused, "the daemon took {line}");
        assert!(!request.is_valid(&bad), "the schema took {line}");
    }
    for good in [
        json!({"kind": "hello"}),
        json!({"v": 1, "id": "a", "kind": "list", "limit": 5, "before": 40}),
        json!({"id": -9_007_199_254_740_991_i64, "kind": "submit", "job": {"steps": 3, "step_um": 5}}),
    ] {
        let line = good.to_string();
        assert!(
            rigd::daemon::protocol::decode_request(line.as_bytes()).is_ok(),
            "{line}"
        );
        let e = errors(&request, &good);
        assert!(e.is_empty(), "{line}: {e:?}");
    }
}
