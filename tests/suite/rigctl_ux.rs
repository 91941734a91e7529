//! rigctl as a new user meets it: the real `rigctl` and `rigd` binaries against a
//! `rigd --sim` on a temporary socket. Status and list as tables with start, elapsed and
//! ETA; submit's results table and absolute session path; negative numbers; one-repeat
//! studies; messages without Rust internals; every argument with a help text.

#![cfg(feature = "sim")] // rigd --sim

use crate::support::daemon::RigdProcess;
use clap::CommandFactory;
use std::path::Path;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

fn rigctl(socket: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(args)
        .env("RIGD_SOCKET", socket)
        .output()
        .unwrap()
}

fn ok(out: &Output) -> String {
    assert!(
        out.status.success(),
        "stdout:\n{}\nstderr:\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout.clone()).unwrap()
}

fn err(out: &Output) -> String {
    assert!(
        !out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    String::from_utf8(out.stderr.clone()).unwrap()
}

fn json(socket: &Path, args: &[&str]) -> serde_json::Value {
    serde_json::from_str(&ok(&rigctl(socket, args))).unwrap()
}

/// What a person must not read: Debug forms of Rust values.
fn assert_no_internals(text: &str) {
    for bad in [
        "Some(", "None", "NotFound", "Rejected", "NaN", "[-1.0", "Fit,", "Interp",
    ] {
        assert!(!text.contains(bad), "{bad:?} in:\n{text}");
    }
}

/// A daemon on the simulated rig in a temporary folder.
fn sim() -> (tempfile::TempDir, std::path::PathBuf, RigdProcess) {
    let dir = tempfile::tempdir().unwrap();
    let socket = dir.path().join("rigd.sock");
    let rigd = RigdProcess::spawn_sim(&socket, &dir.path().join("data"));
    (dir, socket, rigd)
}

#[test]
fn every_argument_of_every_subcommand_has_a_help_text() {
    fn walk(cmd: &clap::Command, path: &str, missing: &mut Vec<String>) {
        for a in cmd.get_arguments() {
            let builtin = matches!(a.get_id().as_str(), "help" | "version");
            if !builtin && a.get_help().is_none() && a.get_long_help().is_none() {
                missing.push(format!("{path} {}", a.get_id()));
            }
        }
        for sub in cmd.get_subcommands() {
            if sub.get_about().is_none() && sub.get_name() != "help" {
                missing.push(format!("{path} {} (the subcommand)", sub.get_name()));
            }
            walk(sub, &format!("{path} {}", sub.get_name()), missing);
        }
    }
    let mut missing = Vec::new();
    walk(&rigd::cli::Cli::command(), "rigctl", &mut missing);
    assert!(missing.is_empty(), "no help text: {missing:#?}");
}

#[test]
fn status_and_list_show_start_elapsed_and_eta_of_running_and_queued_jobs() {
    let (_dir, socket, _rigd) = sim();
    // 40 frames settling 150 ms each (>= 6 s), and one queued behind it.
    let args = [
        "submit",
        "--steps",
        "40",
        "--step-um",
        "50",
        "--settle-ms",
        "150",
    ];
    let first: u64 = ok(&rigctl(&socket, &[&args[..], &["--detach"]].concat()))
        .trim()
        .parse()
        .unwrap();
    let queued = [
        "submit",
        "--steps",
        "5",
        "--step-um",
        "-50",
        "--start-um",
        "20000",
    ];
    let second: u64 = ok(&rigctl(
        &socket,
        &[&queued[..], &["--detach", "--label", "next"]].concat(),
    ))
    .trim()
    .parse()
    .unwrap();
    // Until the running job has measured its own pace (a few frames).
    let t = Instant::now();
    let st = loop {
        let st = json(&socket, &["status", "--json"]);
        if st["running"]["eta_basis"] == "measured" {
            break st;
        }
        assert!(t.elapsed() < Duration::from_secs(30), "{st}");
        std::thread::sleep(Duration::from_millis(100));
    };
    let run = &st["running"];
    assert_eq!(run["job_id"], first);
    let started = run["started_at"].as_str().unwrap();
    assert!(
        started.len() == 20 && started.ends_with('Z') && started.as_bytes()[10] == b'T',
        "{started}"
    );
    let (elapsed, eta, frame_s) = (
        run["elapsed_s"].as_f64().unwrap(),
        run["eta_s"].as_f64().unwrap(),
        run["frame_s"].as_f64().unwrap(),
    );
    let left = 40 - run["frames_done"].as_u64().unwrap();
    // Each frame settles 150 ms: the measured pace holds that, and the ETA the frames left.
    assert!((0.15..1.0).contains(&frame_s), "{run}");
    assert!(
        elapsed > 0.0 && eta <= left as f64 * frame_s + 1e-9,
        "{run}"
    );
    assert!(eta >= (left as f64 - 1.0) * frame_s, "{run}");
    let q = &st["queued_jobs"][0];
    assert_eq!(
        (q["job_id"].as_u64(), q["state"].as_str()),
        (Some(second), Some("queued"))
    );
    let starts_in = q["starts_in_s"].as_f64().unwrap();
    assert!((starts_in - eta).abs() < 1.0, "{q} vs {run}");
    assert!(q["eta_s"].as_f64().unwrap() > starts_in, "{q}");
    assert!(q["expected_start_at"].as_str().unwrap().ends_with('Z'));
    assert!(q.get("started_at").is_none(), "{q}");

    // `status` and `list` as people read them: aligned tables, no JSON.
    let text = ok(&rigctl(&socket, &["status"]));
    assert!(text.starts_with("rig: busy (job"), "{text}");
    assert_no_internals(&text);
    assert!(!text.contains('{'), "{text}");
    assert_aligned(&text, &["running", "queued"]);
    let one = ok(&rigctl(&socket, &["status", &first.to_string()]));
    assert!(one.contains("running") && one.contains("this job"), "{one}");
    let list = ok(&rigctl(&socket, &["list"]));
    assert_aligned(&list, &["running", "queued"]);
    assert!(list.contains("next"), "the label: {list}");
    let listed = json(&socket, &["list", "--json"]);
    assert_eq!(listed["jobs"][0]["job_id"], second);
    assert!(listed["jobs"][0]["eta_s"].as_f64().is_some());
    for id in [second, first] {
        ok(&rigctl(&socket, &["cancel", &id.to_string()]));
    }
}

/// In the jobs table of `text` (the block whose header starts "job"), every column head
/// starts where the cells below it do (right-aligned numbers end where their head ends).
fn assert_aligned(text: &str, states: &[&str]) {
    let lines: Vec<&str> = text.lines().collect();
    let h = lines
        .iter()
        .position(|l| l.trim_start().starts_with("job ") && l.contains("state"))
        .unwrap_or_else(|| panic!("no jobs table in:\n{text}"));
    let head = lines[h];
    let col = head.find("state").unwrap();
    let frames_end = head.find("frames").unwrap() + "frames".len();
    for s in states {
        let row = lines[h + 1..]
            .iter()
            .take_while(|l| !l.is_empty())
            .find(|l| l.contains(s))
            .unwrap_or_else(|| panic!("no {s} row in:\n{text}"));
        assert_eq!(row.find(s), Some(col), "state column:\n{text}");
        let frames = row[col..].split_whitespace().nth(1).unwrap();
        let end = row.find(frames).unwrap() + frames.len();
        assert_eq!(end, frames_end, "frames column:\n{text}");
    }
}

#[test]
fn submit_ends_with_a_results_table_and_the_sessions_absolute_path() {
    let (dir, socket, _rigd) = sim();
    // A negative step without `=`, as a new user types it.
    let out = rigctl(
        &socket,
        &[
            "submit",
            "--step-um",
            "-50",
            "--steps",
            "3",
            "--start-um",
            "5000",
        ],
    );
    let text = ok(&out);
    assert_no_internals(&text);
    let lines: Vec<&str> = text.lines().collect();
    assert!(
        lines[0].starts_with("case") && lines[0].contains("dx µm"),
        "{text}"
    );
    // The sim board's twelve targets, one line each; one repeat: no spread (—).
    let rows: Vec<&&str> = lines.iter().filter(|l| l.starts_with("scan ")).collect();
    assert_eq!(rows.len(), 12, "{text}");
    let f = rows
        .iter()
        .find(|l| l.split_whitespace().nth(1) == Some("F"))
        .unwrap();
    let cells: Vec<&str> = f.split_whitespace().collect();
    let dx: f64 = cells[3].parse().unwrap();
    assert!((dx - 5000.0).abs() < 20.0, "target F is 5 mm off: {f}");
    assert_eq!(cells[5], "—", "{f}");
    let session = lines
        .last()
        .unwrap()
        .strip_prefix("session: ")
        .unwrap_or_else(|| panic!("{text}"));
    let session = Path::new(session);
    assert!(session.is_absolute(), "{text}");
    let data = std::fs::canonicalize(dir.path().join("data")).unwrap();
    assert_eq!(
        std::fs::canonicalize(session.parent().unwrap()).unwrap(),
        data
    );
    assert!(session.join("result.json").is_file());
    // u, the board's nominal and the bias are columns; the calibration is named.
    assert!(
        lines[0].contains("u dx") && lines[0].contains("bias dx"),
        "{text}"
    );
    // Uncalibrated: u is the global scale's 2 % of the offset's length, and the scatter's.
    let u: f64 = cells[7].parse().unwrap();
    let dy: f64 = cells[4].parse().unwrap();
    assert!((u - 0.02 * dx.hypot(dy)).abs() < 5.0, "u of F: {f}");
    let bias: f64 = cells[11].parse().unwrap();
    assert!(
        (dx - cells[9].parse::<f64>().unwrap() - bias).abs() < 0.1,
        "{f}"
    );
    assert!(text.contains("calibration: none applied"), "{text}");

    // A bare submit names the flags it needs, not the protocol's fields.
    let e = err(&rigctl(&socket, &["submit"]));
    assert!(
        e.contains("--steps N --step-um UM") && e.contains("--study"),
        "{e}"
    );
    // Error codes as the wire spells them.
    let e = err(&rigctl(&socket, &["status", "99"]));
    assert_eq!(e.trim(), "rigctl: rigd: not_found: no job 99");
}

#[test]
fn a_one_repeat_study_fetches_its_tables_with_dashes_for_the_spread() {
    let (_dir, socket, _rigd) = sim();
    let text = ok(&rigctl(
        &socket,
        &["submit", "--study", "case1,case2", "--repeats", "1"],
    ));
    assert!(text.contains("case2"), "{text}");
    let listed = json(&socket, &["list", "--json"]);
    let id = listed["jobs"][0]["job_id"].as_u64().unwrap();
    let tables = ok(&rigctl(&socket, &["fetch", &id.to_string(), "--tables"]));
    assert!(
        tables.contains("Table 3") && tables.contains('—'),
        "{tables}"
    );
    assert_no_internals(&tables);
}

#[test]
fn rigd_takes_socket_and_data_root_from_flags_with_a_config_without_a_daemon_table() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("rig.toml"),
        crate::support::daemon::SIM_RIG_SMALL,
    )
    .unwrap();
    let socket = dir.path().join("s.sock");
    let child = Command::new(env!("CARGO_BIN_EXE_rigd"))
        .current_dir(dir.path())
        .args(["--config", "rig.toml", "--socket"])
        .arg(&socket)
        .args(["--data-root", "relative-data"])
        .env("RUST_LOG", "warn")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut rigd = RigdProcess(Some(child));
    let t = Instant::now();
    while rigd::cli::client::Client::connect(&socket).is_err() {
        if let Some(status) = rigd.0.as_mut().unwrap().try_wait().unwrap() {
            let out = rigd.take().wait_with_output().unwrap();
            panic!(
                "rigd exited {status}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        assert!(t.elapsed() < Duration::from_secs(20), "rigd did not start");
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut c = rigd::cli::client::Client::connect(&socket).unwrap();
    let hello = c
        .request(&rigd::daemon::protocol::Request::Hello {})
        .unwrap();
    // Reported absolute, though given relative to rigd's working folder.
    let root = std::fs::canonicalize(dir.path())
        .unwrap()
        .join("relative-data");
    let got = std::fs::canonicalize(hello["data_root"].as_str().unwrap()).unwrap();
    assert!(Path::new(hello["data_root"].as_str().unwrap()).is_absolute());
    assert_eq!(got, root);
}

#[test]
fn hw_without_a_config_says_why_once() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("none.toml");
    let e = err(&rigctl(
        &dir.path().join("s"),
        &["hw", "--config", missing.to_str().unwrap(), "probe"],
    ));
    assert_eq!(e.matches("No such file or directory").count(), 1, "{e}");
}

#[test]
fn the_demo_keeps_its_report_and_drops_its_frames_unless_told_to_keep_them() {
    let dir = tempfile::tempdir().unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .current_dir(dir.path())
        .env("TMPDIR", tmp.path())
        .args(["demo", "--camera", "ideal", "--repeats", "1"])
        .output()
        .unwrap();
    let text = ok(&out);
    assert_no_internals(&text);
    // The first screen leads with the calibration's verdict; its parameters wait for
    // `--verbose`.
    let first = text.lines().next().unwrap_or_default();
    assert!(
        first.starts_with("calibration cal-") && first.contains("the field model fits the scan to"),
        "{text}"
    );
    assert!(text
        .lines()
        .nth(1)
        .unwrap_or_default()
        .contains("`--verbose` prints its parameters"));
    let report = text
        .lines()
        .find_map(|l| l.strip_prefix("Report: "))
        .unwrap_or_else(|| panic!("{text}"));
    let report = Path::new(report.split(" (").next().unwrap());
    assert!(report.is_absolute() && report.is_file(), "{text}");
    let session = report.parent().unwrap();
    let demo_root = std::fs::canonicalize(dir.path().join("rigd-demo")).unwrap();
    assert_eq!(
        std::fs::canonicalize(session.parent().unwrap()).unwrap(),
        demo_root
    );
    assert!(session.join("result.json").is_file() && session.join("steps.csv").is_file());
    assert!(!session.join("frames").exists(), "the frames were kept");
    // The calibration's session too.
    let sessions = std::fs::read_dir(&demo_root)
        .unwrap()
        .map(|e| e.unwrap().path());
    let kept: Vec<_> = sessions.filter(|s| s.join("frames").exists()).collect();
    assert!(kept.is_empty(), "frames kept in {kept:?}");
    // Its socket and the socket's lock went with it.
    let left: Vec<_> = std::fs::read_dir(tmp.path()).unwrap().collect();
    assert!(left.is_empty(), "left in TMPDIR: {left:?}");
}

/// `rigctl submit` following a long job, its stderr lines on a channel.
fn submit_followed(socket: &Path) -> (std::process::Child, std::sync::mpsc::Receiver<String>) {
    use std::io::BufRead;
    let mut child = Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args([
            "submit",
            "--steps",
            "400",
            "--step-um",
            "50",
            "--settle-ms",
            "50",
        ])
        .env("RIGD_SOCKET", socket)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let stderr = child.stderr.take().unwrap();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stderr).lines() {
            let Ok(line) = line else { return };
            if tx.send(line).is_err() {
                return;
            }
        }
    });
    (child, rx)
}

/// The first stderr line containing `what`, within 20 s.
fn line_with(rx: &std::sync::mpsc::Receiver<String>, what: &str) -> String {
    let t0 = Instant::now();
    while let Some(left) = Duration::from_secs(20).checked_sub(t0.elapsed()) {
        match rx.recv_timeout(left) {
            Ok(l) if l.contains(what) => return l,
            Ok(_) => {}
            Err(_) => break,
        }
    }
    panic!("no line with {what:?} on rigctl's stderr");
}

fn interrupt(child: &std::process::Child) {
    let pid = nix::unistd::Pid::from_raw(child.id() as i32);
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGINT).unwrap();
}

#[test]
fn ctrl_c_on_submit_says_the_job_goes_on_and_a_second_one_cancels_it() {
    let (_dir, socket, _rigd) = sim();
    let (mut child, rx) = submit_followed(&socket);
    let queued = line_with(&rx, "queued");
    let id: u64 = queued.split_whitespace().nth(1).unwrap().parse().unwrap();
    interrupt(&child);
    let said = line_with(&rx, "keeps running");
    assert!(said.contains(&format!("rigctl cancel {id}")), "{said}");
    interrupt(&child);
    line_with(&rx, &format!("cancelling job {id}"));
    let status = child.wait().unwrap();
    assert!(!status.success());
    let st = json(&socket, &["status", &id.to_string(), "--json"]);
    assert_eq!(st["state"], "cancelled", "{st}");
}

#[test]
fn one_ctrl_c_on_submit_detaches_and_the_job_runs_on() {
    let (_dir, socket, _rigd) = sim();
    let (mut child, rx) = submit_followed(&socket);
    let queued = line_with(&rx, "queued");
    let id: u64 = queued.split_whitespace().nth(1).unwrap().parse().unwrap();
    interrupt(&child);
    line_with(&rx, "keeps running");
    line_with(&rx, &format!("detached from job {id}"));
    assert_eq!(child.wait().unwrap().code(), Some(130));
    let st = json(&socket, &["status", &id.to_string(), "--json"]);
    assert_eq!(st["state"], "running", "{st}");
    ok(&rigctl(&socket, &["cancel", &id.to_string()]));
}

#[test]
fn numbers_that_mean_nothing_are_refused_naming_the_flag() {
    let bogus = Path::new("/nonexistent/rigd.sock");
    for (args, flag, says) in [
        (
            &["submit", "--steps", "20", "--step-um", "NaN"][..],
            "--step-um",
            "not a finite number",
        ),
        (
            &["submit", "--steps", "-20", "--step-um", "50"][..],
            "--steps",
            "-20",
        ),
        (
            &[
                "submit",
                "--steps",
                "2",
                "--step-um",
                "5",
                "--start-um",
                "inf",
            ][..],
            "--start-um",
            "not a finite number",
        ),
        (
            &["move", "--by-um", "NaN"][..],
            "--by-um",
            "not a finite number",
        ),
    ] {
        let e = err(&rigctl(bogus, args));
        assert!(e.contains(flag) && e.contains(says), "{args:?}: {e}");
        assert!(!e.contains("unexpected argument"), "{args:?}: {e}");
    }
}

#[test]
fn a_missing_session_or_folder_is_named_once_with_its_cause_once() {
    let bogus = Path::new("/nonexistent/rigd.sock");
    for args in [
        &["export", "/nonexistent/session-x", "--format", "ome-tiff"][..],
        &["reprocess", "/nonexistent/session-x"],
        &["process", "/nonexistent/session-x"],
        &["report", "/nonexistent/session-x"],
    ] {
        let cmd = args[0];
        let e = err(&rigctl(bogus, args));
        assert!(e.contains("/nonexistent/session-x"), "{cmd}: {e}");
        let causes =
            e.matches("No such file or directory").count() + e.matches("no such folder").count();
        assert_eq!(causes, 1, "{cmd}: {e}");
        assert!(!e.contains("cannot list the frames folder"), "{cmd}: {e}");
    }
}

#[test]
fn info_shows_the_rig_a_number_depends_on() {
    let (dir, socket, _rigd) = sim();
    let text = ok(&rigctl(&socket, &["info"]));
    for want in [
        "rig ",
        "sim",
        "scale",
        "µm/px",
        "frame",
        "axis limits",
        "axis controller",
    ] {
        assert!(text.contains(want), "{want:?} in:\n{text}");
    }
    let root = std::fs::canonicalize(dir.path().join("data")).unwrap();
    assert!(text.contains(&root.display().to_string()), "{text}");
    assert_no_internals(&text);
    assert!(text.contains("sim: ideal"), "{text}");
    let v = json(&socket, &["hello", "--json"]);
    assert_eq!(v["data_root"].as_str(), Some(root.to_str().unwrap()), "{v}");
}

#[test]
fn rigd_sim_takes_a_camera_profile_and_only_with_sim() {
    let dir = tempfile::tempdir().unwrap();
    let socket = dir.path().join("rigd.sock");
    let _rigd = RigdProcess::spawn(
        &[
            "--sim".as_ref(),
            "--camera".as_ref(),
            "webcam".as_ref(),
            "--socket".as_ref(),
            socket.as_os_str(),
            "--data-root".as_ref(),
            dir.path().join("data").as_os_str(),
        ],
        &socket,
    );
    let v = json(&socket, &["info", "--json"]);
    assert_eq!(v["rig"]["camera"], "sim: webcam", "{v}");
    let out = Command::new(env!("CARGO_BIN_EXE_rigd"))
        .args(["--camera", "webcam", "--socket"])
        .arg(dir.path().join("other.sock"))
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && e.contains("--camera needs --sim"),
        "{e}"
    );
}
