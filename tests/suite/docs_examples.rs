//! The JSON examples of the docs are what the daemon speaks: every ```json block in docs/
//! and README.md parses; every request in them (an object with `kind`), and every job
//! fragment (an object with `plan` or `calibrate`, sent as a submit's `job`), is sent to a
//! simulated rig's daemon, which neither calls it malformed nor names a field it lacks.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::Daemon;
use rigd::rig::simulated;
use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};

/// (file, line, the block's JSON values) of every ```json block.
fn json_blocks() -> Vec<(String, usize, Vec<Value>)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files: Vec<PathBuf> = std::fs::read_dir(root.join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .collect();
    files.push(root.join("README.md"));
    files.sort();
    let mut out = Vec::new();
    for f in files {
        let text = std::fs::read_to_string(&f).unwrap();
        let name = f.file_name().unwrap().to_string_lossy().into_owned();
        let mut rest = text.as_str();
        while let Some(i) = rest.find("```json\n") {
            let body = &rest[i + 8..];
            let end = body.find("```").expect("a closed block");
            let line = text[..text.len() - rest.len() + i].lines().count() + 2;
            let values: Result<Vec<Value>, _> = serde_json::Deserializer::from_str(&body[..end])
                .into_iter::<Value>()
                .collect();
            let values = values.unwrap_or_else(|e| panic!("{name}:{line}: not JSON: {e}"));
            assert!(!values.is_empty(), "{name}:{line}: an empty block");
            out.push((name.clone(), line, values));
            rest = &body[end + 3..];
        }
    }
    out
}

/// A connection speaking raw lines.
struct Line {
    r: BufReader<UnixStream>,
    w: UnixStream,
}

impl Line {
    fn connect(socket: &Path) -> Line {
        let s = UnixStream::connect(socket).unwrap();
        Line {
            r: BufReader::new(s.try_clone().unwrap()),
            w: s,
        }
    }

    /// Send `v` and read its reply, events skipped.
    fn request(&mut self, v: &Value) -> Value {
        self.w.write_all(format!("{v}\n").as_bytes()).unwrap();
        loop {
            let mut line = String::new();
            assert!(
                self.r.read_line(&mut line).unwrap() > 0,
                "the daemon hung up"
            );
            let reply: Value = serde_json::from_str(&line).unwrap();
            if reply["type"] == "reply" {
                return reply;
            }
        }
    }
}

/// The request a docs value stands for, if any.
fn as_request(v: &Value) -> Option<Value> {
    if v.get("kind").is_some() {
        return Some(v.clone());
    }
    let job_part = v.get("plan").is_some() || v.get("calibrate").is_some();
    job_part.then(|| json!({"v": 1, "kind": "submit", "job": v}))
}

#[test]
fn every_json_example_parses_and_every_request_in_them_is_understood() {
    let blocks = json_blocks();
    let values: usize = blocks.iter().map(|(_, _, v)| v.len()).sum();
    assert!(
        blocks.len() >= 10 && values >= 15,
        "{} blocks",
        blocks.len()
    );
    let dir = tempfile::tempdir().unwrap();
    let rig = simulated(&crate::support::daemon::small_board_sim(dir.path())).unwrap();
    let d = Daemon::start_in(rig, dir);
    let mut c = Line::connect(&d.bg.socket);
    let mut sent = 0;
    for (file, line, vs) in &blocks {
        for v in vs.iter().filter_map(as_request) {
            let reply = c.request(&v);
            let code = reply["error"]["code"].as_str().unwrap_or("");
            assert!(
                !matches!(code, "malformed" | "bad_request" | "version"),
                "{file}:{line}: {v}\n  answered {reply}"
            );
            if let Some(id) = reply["result"]["job_id"].as_u64() {
                c.request(&json!({"v": 1, "kind": "cancel", "job_id": id}));
            }
            sent += 1;
        }
    }
    assert!(sent >= 5, "only {sent} requests in the docs");
}
