//! The request decoder under property tests (nothing panics, every bad line gets an error),
//! and bad requests over a live socket: each gets an error reply before anything moves and
//! the connection keeps serving.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::Daemon;
use proptest::prelude::*;
use rigd::daemon::protocol::{decode_request, ErrorCode, MAX_LINE_BYTES};
use rigd::rig::{simulated, SimSettings};
use rigd::sim::CameraModel;
use serde_json::Value;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let _ = decode_request(&bytes);
    }

    #[test]
    fn json_of_any_shape_decodes_or_names_an_error(v in arb_json()) {
        let line = serde_json::to_vec(&v).unwrap();
        match decode_request(&line) {
            Ok(_) => {}
            Err((_, e)) => prop_assert!(!e.message.is_empty()),
        }
    }

    #[test]
    fn mutated_submits_decode_or_name_an_error(
        key in "[a-z_]{1,10}",
        val in arb_json(),
    ) {
        let mut job = serde_json::json!({"step_um": 50.0, "steps": 3});
        job[key.as_str()] = val;
        let line = serde_json::to_vec(&serde_json::json!({"kind": "submit", "job": job})).unwrap();
        if let Err((_, e)) = decode_request(&line) {
            prop_assert!(matches!(e.code, ErrorCode::BadRequest), "{:?}", e);
        }
    }
}

/// Every kind and the fields it takes (`docs/protocol.md`).
const KINDS: &[(&str, &[&str])] = &[
    ("hello", &[]),
    ("submit", &["job"]),
    ("status", &["job_id"]),
    ("list", &["limit", "before"]),
    ("cancel", &["job_id"]),
    ("result", &["job_id"]),
    ("subscribe", &["job_id"]),
    ("replay", &["session", "processing"]),
    ("unlock", &["stage"]),
    ("home", &["stage"]),
    ("reconnect", &["stage"]),
    ("snap", &["scale", "crop"]),
    ("preview", &["max_fps", "scale", "crop"]),
    ("preview_stop", &[]),
    ("position", &[]),
    ("move", &["stage", "to_um", "by_um"]),
    ("stop", &[]),
    ("pause", &["job_id"]),
    ("resume", &["job_id"]),
    ("resume_session", &["session"]),
];

proptest! {
    #![proptest_config(ProptestConfig { cases: 500, ..ProptestConfig::default() })]

    /// Whatever the kind, a field it does not take is refused, naming the field.
    #[test]
    fn unknown_fields_are_refused_on_every_kind(
        kind in 0..KINDS.len(),
        key in "[a-z_]{1,8}",
        val in arb_json(),
    ) {
        let (name, fields) = KINDS[kind];
        prop_assume!(!fields.contains(&key.as_str()) && !["kind", "id", "v"].contains(&key.as_str()));
        let mut m = serde_json::Map::new();
        m.insert("kind".into(), Value::from(name));
        m.insert(key.clone(), val);
        let (_, e) = decode_request(&serde_json::to_vec(&m).unwrap()).unwrap_err();
        prop_assert_eq!(e.code, ErrorCode::BadRequest);
        prop_assert!(e.message.contains(&key), "{}", e.message);
    }

    /// A key twice, at the top or inside the job, is refused whatever the values: serde_json
    /// alone keeps the last one.
    #[test]
    fn duplicate_keys_are_refused_at_any_depth(
        key in prop_oneof![
            Just("steps".to_string()),
            Just("step_um".to_string()),
            Just("label".to_string()),
            "[a-z]{1,5}",
        ],
        a in arb_json(),
        b in arb_json(),
        inside in any::<bool>(),
    ) {
        let (a, b) = (a.to_string(), b.to_string());
        let line = match inside {
            true => format!(r#"{{"kind":"submit","job":{{"{key}":{a},"steps":1,"{key}":{b}}}}}"#),
            false => format!(r#"{{"{key}":{a},"kind":"list","{key}":{b}}}"#),
        };
        let (_, e) = decode_request(line.as_bytes()).unwrap_err();
        prop_assert_eq!(e.code, ErrorCode::BadRequest, "{}", line);
        prop_assert!(e.message.contains(&format!("duplicate key {key:?}")), "{}: {}", line, e.message);
    }

    /// Integer ids within ±(2^53 - 1) come back as the same number; others are refused.
    #[test]
    fn integer_ids_are_echoed_exactly_or_refused(id in prop_oneof![
        -(1i128 << 53)..(1i128 << 53),
        any::<i128>(),
        ((1i128 << 53) - 2)..((1i128 << 53) + 2),
    ]) {
        let line = format!(r#"{{"id":{id},"kind":"hello"}}"#);
        match decode_request(line.as_bytes()) {
            Ok(env) => {
                prop_assert!(id.unsigned_abs() < 1 << 53, "{} accepted", id);
                prop_assert_eq!(env.id.unwrap().to_string(), id.to_string());
            }
            Err((back, e)) => {
                prop_assert!(id.unsigned_abs() >= 1 << 53, "{} refused: {}", id, e.message);
                prop_assert_eq!(back, None);
                prop_assert!(e.message.starts_with("`id` must be"), "{}", e.message);
            }
        }
    }

    /// A job (or a replay's processing) that is not an object is refused, whatever it holds.
    #[test]
    fn a_job_must_be_an_object(v in arb_json(), replay in any::<bool>()) {
        prop_assume!(!v.is_object());
        let line = match replay {
            true => serde_json::json!({"kind": "replay", "session": "s", "processing": v}),
            false => serde_json::json!({"kind": "submit", "job": v}),
        };
        let (_, e) = decode_request(&serde_json::to_vec(&line).unwrap()).unwrap_err();
        prop_assert_eq!(e.code, ErrorCode::BadRequest);
        prop_assert!(e.message.contains("must be a JSON object"), "{}", e.message);
    }
}

fn arb_json() -> impl Strategy<Value = Value> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::from),
        any::<i64>().prop_map(Value::from),
        any::<f64>()
            .prop_filter("finite", |f| f.is_finite())
            .prop_map(Value::from),
        prop_oneof![
            Just("submit".to_string()),
            Just("status".to_string()),
            Just("cancel".to_string()),
            Just("replay".to_string()),
            "[a-z]{0,8}",
        ]
        .prop_map(Value::from),
    ];
    leaf.prop_recursive(3, 24, 6, |inner| {
        prop_oneof![
            proptest::collection::vec(inner.clone(), 0..4).prop_map(Value::from),
            proptest::collection::btree_map(
                prop_oneof![
                    Just("kind".to_string()),
                    Just("job".to_string()),
                    Just("job_id".to_string()),
                    Just("id".to_string()),
                    Just("v".to_string()),
                    Just("steps".to_string()),
                    Just("step_um".to_string()),
                    "[a-z_]{1,6}",
                ],
                inner,
                0..5
            )
            .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    })
}

struct Conn {
    r: BufReader<UnixStream>,
    w: UnixStream,
}

impl Conn {
    fn send(&mut self, bytes: &[u8]) -> Value {
        self.w.write_all(bytes).unwrap();
        self.w.write_all(b"\n").unwrap();
        let mut line = String::new();
        self.r.read_line(&mut line).unwrap();
        serde_json::from_str(&line).unwrap_or_else(|e| panic!("{e}: {line}"))
    }
}

#[test]
fn bad_requests_get_error_replies_and_the_connection_keeps_serving() {
    let sim = SimSettings {
        camera: CameraModel {
            width: 32,
            height: 24,
            supersample: 1,
            ..CameraModel::default()
        },
        ..SimSettings::default()
    };
    let mut d = Daemon::start(simulated(&sim).unwrap());
    let bg = &mut d.bg;
    // No group configured: the socket is its owner's alone (0660 only with [daemon] group).
    use std::os::unix::fs::PermissionsExt;
    let mode = std::fs::metadata(&bg.socket).unwrap().permissions().mode();
    assert_eq!(mode & 0o777, 0o600);
    let s = UnixStream::connect(&bg.socket).unwrap();
    let mut c = Conn {
        r: BufReader::new(s.try_clone().unwrap()),
        w: s,
    };
    let long = vec![b' '; MAX_LINE_BYTES + 1];
    let cases: Vec<(&[u8], &str, &str)> = vec![
        (b"{not json", "malformed", "not JSON"),
        (b"42", "malformed", "object"),
        (br#"{"id":1,"kind":"fly"}"#, "bad_request", "fly"),
        (br#"{"id":2,"kind":"status","job":3}"#, "bad_request", "job"),
        (
            br#"{"id":3,"kind":"cancel","job_id":"x"}"#,
            "bad_request",
            "invalid type",
        ),
        (br#"{"id":4,"v":9,"kind":"list"}"#, "version", "version 9"),
        (&long, "line_too_long", "limit"),
        (b"{\"kind\":\"list\xff\"}", "malformed", "UTF-8"),
        (
            br#"{"id":5,"kind":"submit","job":{"steps":3,"step_um":0}}"#,
            "rejected",
            "non-zero",
        ),
        (
            br#"{"id":6,"kind":"submit","job":{"steps":3,"step_um":1e6}}"#,
            "rejected",
            "soft limits",
        ),
        (
            br#"{"id":7,"kind":"submit","job":{"steps":3,"step_um":5,"speed":1}}"#,
            "bad_request",
            "speed",
        ),
        (
            br#"{"id":8,"kind":"submit","job":{"study":["case9"]}}"#,
            "bad_request",
            "case9",
        ),
        (
            br#"{"id":9,"kind":"cancel","job_id":99}"#,
            "not_found",
            "99",
        ),
        (
            br#"{"id":10,"kind":"result","job_id":99}"#,
            "not_found",
            "99",
        ),
        (
            br#"{"id":11,"kind":"move","stage":"axis","to_um":1e9}"#,
            "rejected",
            "outside the soft travel limits",
        ),
        (
            br#"{"id":12,"kind":"move","stage":"axis"}"#,
            "bad_request",
            "a move needs `to_um`",
        ),
        (
            br#"{"id":13,"kind":"move","stage":"axle","to_um":1}"#,
            "bad_request",
            "axle",
        ),
        (
            br#"{"id":14,"kind":"move","stage":"axis","by_um":"x"}"#,
            "bad_request",
            "invalid type",
        ),
        (
            br#"{"id":15,"kind":"pause","job_id":99}"#,
            "not_found",
            "99",
        ),
        (
            br#"{"id":16,"kind":"resume","job_id":99}"#,
            "not_found",
            "99",
        ),
        (
            br#"{"id":17,"kind":"resume_session","session":"nope"}"#,
            "not_found",
            "no session nope",
        ),
        (
            br#"{"id":18,"kind":"resume_session","session":"../x"}"#,
            "rejected",
            "not a session name",
        ),
    ];
    for (line, code, needle) in &cases {
        let r = c.send(line);
        assert_eq!(r["ok"], false, "{r}");
        assert_eq!(r["error"]["code"], *code, "{r}");
        let msg = r["error"]["message"].as_str().unwrap();
        assert!(msg.contains(needle), "{msg:?} should name {needle:?}");
    }
    // Nothing was queued or moved, and the same connection still answers.
    let r = c.send(br#"{"id":"last","kind":"status"}"#);
    assert_eq!(
        (r["ok"].as_bool(), &r["id"]),
        (Some(true), &Value::from("last"))
    );
    assert_eq!(r["result"]["running"], Value::Null);
    let r = c.send(br#"{"kind":"list"}"#);
    assert_eq!(r["result"]["sessions"], serde_json::json!([]));
    bg.stop().unwrap();
}
