//! Files as an adversary writes them, read by the real `rigd` and `rigctl`: a session's
//! steps.csv and manifest with numbers no clock or formatter holds, a chain of resumed
//! sessions that names itself, earlier frames of the wrong size or cut short, a folder whose
//! frames are a symlink to /dev/zero, a FIFO or a huge image, a copied session reprocessed.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::adversary::{capture_job, follow, rss_kb, Line, Rigd, Spawn};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// A daemon (all-sim rig, 48x32 frames) and `n` finished sessions of `frames` frames.
fn with_sessions(dir: &Path, n: usize, frames: u32) -> (Rigd, Vec<String>) {
    let d = Spawn::new(env!("CARGO_BIN_EXE_rigd"), dir).start();
    let mut c = d.client();
    c.request(r#"{"kind": "subscribe"}"#);
    let names = (0..n)
        .map(|_| {
            let id = c.request(&capture_job(frames, 0, "rec"))["result"]["job_id"]
                .as_u64()
                .unwrap();
            let end = follow(&mut c, id).pop().unwrap();
            assert_eq!(end["event"], "finished", "{end}");
            end["session"].as_str().unwrap().to_string()
        })
        .collect();
    (d, names)
}

fn edit_json(path: &Path, f: impl FnOnce(&mut Value)) {
    let mut v: Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(path, serde_json::to_vec_pretty(&v).unwrap()).unwrap();
}

/// Replace column `col` of steps.csv's data row `row` (0-based) with `value`.
fn edit_steps(session: &Path, row: usize, col: &str, value: &str) {
    let path = session.join("steps.csv");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    let at = lines[0].split(',').position(|h| h == col).unwrap();
    let mut cells: Vec<String> = lines[row + 1].split(',').map(String::from).collect();
    cells[at] = value.into();
    lines[row + 1] = cells.join(",");
    std::fs::write(&path, lines.join("\n") + "\n").unwrap();
}

fn job_of(reply: &Value) -> u64 {
    reply["result"]["job_id"]
        .as_u64()
        .unwrap_or_else(|| panic!("{reply}"))
}

#[test]
fn hostile_frame_times_and_manifest_dates_are_refused_and_the_daemon_serves_on() {
    let dir = tempfile::tempdir().unwrap();
    let (d, names) = with_sessions(dir.path(), 2, 3);
    edit_steps(&d.data.join(&names[0]), 1, "t_unix_s", "1e300");
    let mut c = d.client();
    let r = c.request(&format!(
        r#"{{"kind": "replay", "session": "{}"}}"#,
        names[0]
    ));
    assert_eq!(r["ok"], false, "{r}");
    let msg = r["error"]["message"].as_str().unwrap();
    assert!(msg.contains("row 2: t_unix_s 1e300 is outside"), "{msg}");
    // The manifest's date no formatter writes: list and status answer at once.
    edit_json(&d.data.join(&names[1]).join("manifest.json"), |m| {
        m["created_unix_s"] = serde_json::json!(1e300)
    });
    let t = Instant::now();
    let list = c.request(r#"{"kind": "list"}"#);
    assert_eq!(list["ok"], true, "{list}");
    let status = c.request(r#"{"kind": "status"}"#);
    assert_eq!(status["ok"], true, "{status}");
    assert!(t.elapsed() < Duration::from_secs(5));
    // The job engine is not wedged: a job runs to its end.
    c.request(r#"{"kind": "subscribe"}"#);
    let id = job_of(&c.request(&capture_job(2, 0, "after")));
    assert_eq!(follow(&mut c, id).pop().unwrap()["event"], "finished");
}

/// A cancelled session of 10 frames that took `taken` of them.
fn cancelled_session(c: &mut Line, taken: u32) -> (u64, String) {
    let id = job_of(&c.request(&capture_job(10, 80, "partial")));
    loop {
        let e = c.read().unwrap();
        if e["event"] == "step" && e["job_id"] == id && e["index"] == taken - 1 {
            break;
        }
    }
    c.request(&format!(r#"{{"kind": "cancel", "job_id": {id}}}"#));
    let end = follow(c, id).pop().unwrap();
    (id, end["session"].as_str().unwrap().to_string())
}

/// `resume_session` of `name`: the reply; the job it queued (if any) is cancelled.
fn resume(c: &mut Line, name: &str) -> Value {
    let r = c.request(&format!(
        r#"{{"kind": "resume_session", "session": "{name}"}}"#
    ));
    if let Some(id) = r["result"]["job_id"].as_u64() {
        c.request(&format!(r#"{{"kind": "cancel", "job_id": {id}}}"#));
        follow(c, id);
    }
    r
}

#[test]
fn a_self_resuming_session_is_refused_at_once_in_bounded_memory() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(env!("CARGO_BIN_EXE_rigd"), dir.path()).start();
    let mut c = d.client();
    c.request(r#"{"kind": "subscribe"}"#);
    let (_, name) = cancelled_session(&mut c, 3);
    let s = d.data.join(&name);
    edit_json(&s.join("manifest.json"), |m| {
        m["plan"]["first_index"] = 2.into();
        m["resumed_from"] = serde_json::json!({"session": name, "first_index": 2});
    });
    // ~50 MB of rows, as the attack had.
    let text = std::fs::read_to_string(s.join("steps.csv")).unwrap();
    let row = text.lines().nth(1).unwrap().to_string();
    let mut big = text.clone();
    for _ in 0..50_000_000 / (row.len() + 1) {
        big.push_str(&row);
        big.push('\n');
    }
    std::fs::write(s.join("steps.csv"), big).unwrap();
    let t = Instant::now();
    let r = resume(&mut c, &name);
    let took = t.elapsed();
    assert_eq!(r["error"]["code"], "rejected", "{r}");
    let msg = r["error"]["message"].as_str().unwrap();
    assert!(
        msg.contains("already in its chain") && msg.contains("a cycle"),
        "{msg}"
    );
    assert!(took < Duration::from_secs(5), "{took:?}");
    let (_, peak_kb) = rss_kb(d.pid());
    println!(
        "rigd peak RSS after the self-resuming attack: {} MB",
        peak_kb / 1024
    );
    assert!(peak_kb < 512 * 1024, "{peak_kb} kB");
}

/// A PNG of `w` x `h` black pixels.
fn png(w: u32, h: u32) -> Vec<u8> {
    let mut v = Vec::new();
    image::RgbImage::new(w, h)
        .write_to(&mut std::io::Cursor::new(&mut v), image::ImageFormat::Png)
        .unwrap();
    v
}

#[test]
fn resume_retakes_an_earlier_frame_of_the_wrong_size_or_cut_short() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(env!("CARGO_BIN_EXE_rigd"), dir.path()).start();
    let mut c = d.client();
    c.request(r#"{"kind": "subscribe"}"#);
    let (_, name) = cancelled_session(&mut c, 6);
    let frames = d.data.join(&name).join("frames");
    // Frame 3 cut short: frames 0..3 are kept.
    let f3 = frames.join("000003.png");
    let bytes = std::fs::read(&f3).unwrap();
    std::fs::write(&f3, &bytes[..bytes.len() - 20]).unwrap();
    let r = resume(&mut c, &name);
    assert_eq!(r["result"]["resumed_from"]["first_index"], 3, "{r}");
    // Frame 1 of another size: only frame 0 is kept.
    std::fs::write(frames.join("000001.png"), png(40, 30)).unwrap();
    let r = resume(&mut c, &name);
    assert_eq!(r["result"]["resumed_from"]["first_index"], 1, "{r}");
}

/// A `rigctl process` folder of 3 frames of the small board.
fn folder(dir: &Path) -> PathBuf {
    let f = dir.join("scan");
    crate::support::write_folder(
        &f,
        &crate::support::small_board(),
        &crate::support::small_camera(),
        [310.0, 150.0],
        154.8,
        3,
        7,
    );
    f
}

/// `rigctl ARGS`, its status, stderr and its peak RSS (kB): the rusage `wait4` gives for
/// this child alone (the test process runs other tests, and their children, beside it).
// `wait4` reaps the child, which clippy cannot see.
#[allow(clippy::zombie_processes)]
fn rigctl_rss(args: &[&std::ffi::OsStr]) -> (bool, String, u64) {
    use std::io::Read;
    use std::os::unix::process::ExitStatusExt;
    let mut child = Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(args)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t = Instant::now();
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    let (mut status, mut u): (libc::c_int, libc::rusage) = (0, unsafe { std::mem::zeroed() });
    // SAFETY: reaps this child (std's `Child` is not waited on after) and fills `u`.
    let pid = unsafe { libc::wait4(child.id() as libc::pid_t, &mut status, 0, &mut u) };
    assert_eq!(pid, child.id() as libc::pid_t, "wait4");
    assert!(t.elapsed() < Duration::from_secs(60));
    let ok = std::process::ExitStatus::from_raw(status).success();
    (ok, err, u.ru_maxrss as u64)
}

#[test]
fn offline_readers_refuse_symlinked_fifo_and_huge_frames_quickly() {
    let dir = tempfile::tempdir().unwrap();
    let f = folder(dir.path());
    let frame = |i: u32| f.join("frames").join(format!("{i:04}.png"));
    let board = dir.path().join("small.toml");
    std::fs::write(&board, crate::support::SMALL_BOARD).unwrap();
    let process = |what: &str| {
        let args = [
            "process".as_ref(),
            f.as_os_str(),
            "--board".as_ref(),
            board.as_os_str(),
        ];
        let (ok, err, rss) = rigctl_rss(&args);
        println!("rigctl process, {what}: peak RSS {} MB", rss / 1024);
        assert!(!ok, "{what}: {err}");
        assert!(rss < 512 * 1024, "{what}: {rss} kB");
        err
    };
    std::fs::remove_file(frame(1)).unwrap();
    std::os::unix::fs::symlink("/dev/zero", frame(1)).unwrap();
    let err = process("a frame symlinked to /dev/zero");
    assert!(
        err.contains("0001.png") && err.contains("symbolic link"),
        "{err}"
    );
    std::fs::remove_file(frame(1)).unwrap();
    nix_mkfifo(&frame(1));
    let err = process("a FIFO as a frame");
    assert!(
        err.contains("0001.png") && err.contains("not a regular file"),
        "{err}"
    );
    std::fs::remove_file(frame(1)).unwrap();
    // 30000 x 30000 declared by a small file, as frame 0.
    std::fs::copy(frame(2), frame(1)).unwrap();
    std::fs::write(frame(0), declared_png(30_000, 30_000)).unwrap();
    let err = process("a 30000x30000 frame 0");
    assert!(
        err.contains("0000.png") && err.contains("30000x30000"),
        "{err}"
    );
    // Frame 1 of another size than frame 0's.
    std::fs::copy(frame(2), frame(0)).unwrap();
    std::fs::write(frame(1), png(100, 50)).unwrap();
    let err = process("a frame of another size");
    assert!(
        err.contains("0001.png: size 100x50 px differs from the run's first frame's, 300x200 px"),
        "{err}"
    );
    // `rigctl calibrate` reads the same way.
    std::fs::remove_file(frame(0)).unwrap();
    nix_mkfifo(&frame(0));
    let (ok, err, _) = rigctl_rss(&[
        "calibrate".as_ref(),
        f.as_os_str(),
        "--scale-um-per-px".as_ref(),
        "774".as_ref(),
        "--board".as_ref(),
        board.as_os_str(),
        "--out".as_ref(),
        dir.path().join("cal.json").as_os_str(),
    ]);
    assert!(!ok && err.contains("not a regular file"), "{err}");
}

fn nix_mkfifo(p: &Path) {
    let c = std::ffi::CString::new(p.as_os_str().as_encoded_bytes()).unwrap();
    // SAFETY: a valid C path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
}

/// A small PNG declaring `w` x `h` 8-bit RGB: its signature, IHDR, a token IDAT and IEND
/// (the pixels are never there: a decoder must refuse it from the header).
fn declared_png(w: u32, h: u32) -> Vec<u8> {
    let mut v = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8], data: &[u8]| {
        v.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let start = v.len();
        v.extend_from_slice(kind);
        v.extend_from_slice(data);
        let crc = crc32fast::hash(&v[start..]);
        v.extend_from_slice(&crc.to_be_bytes());
    };
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);
    chunk(b"IHDR", &ihdr);
    chunk(b"IDAT", &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01]);
    chunk(b"IEND", &[]);
    v
}

#[test]
fn a_reprocessed_copy_of_a_session_is_indexed_under_its_own_name() {
    let dir = tempfile::tempdir().unwrap();
    let rig = rigd::rig::simulated(&crate::support::daemon::small_board_sim(dir.path())).unwrap();
    let d = crate::support::daemon::Daemon::start_in(rig, dir);
    let mut c = d.subscribed();
    let job = rigd::acquisition::JobSpec {
        step_um: Some(154.8),
        steps: Some(3),
        k: Some(1),
        settle_ms: 0,
        ..rigd::acquisition::JobSpec::default()
    };
    let (_, ev) = crate::support::daemon::run_job(&mut c, job);
    crate::support::daemon::assert_finished(&ev);
    let name = crate::support::daemon::session_name(&ev);
    let copy = d.data.join("copy-of-it");
    crate::support::daemon::copy_dir(&d.data.join(&name), &copy);
    let out = Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .arg("reprocess")
        .arg(&copy)
        .args(["--k", "2", "--combine", "interp"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(["results", "--data-root"])
        .arg(&d.data)
        .output()
        .unwrap();
    let csv = String::from_utf8_lossy(&out.stdout).into_owned();
    let rows: Vec<&str> = csv.lines().filter(|l| l.contains(",interp-k2,")).collect();
    assert_eq!(rows.len(), 2, "two targets: {csv}");
    assert!(
        rows.iter().all(|r| r.starts_with("copy-of-it,")),
        "the copy's rows are filed under its own name: {csv}"
    );
}
