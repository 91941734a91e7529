//! Hardware ownership and stops (signals) against the real `rigd` binary: a
//! second instance with the same config, the same data root, the same socket or the same
//! port is refused before it sends a byte or changes a file; nothing but a stale socket is
//! ever removed at the socket path; `rigctl hw` and `rigctl demo` honour the same locks;
//! SIGTERM, SIGINT and SIGHUP all stop cleanly; systemd hears READY=1 once the socket is
//! bound; logs carry no ANSI escapes off a terminal.

#![cfg(feature = "sim")] // the simulated rig and the GRBL emulator (default feature)

use crate::support::daemon::{capture_job, fast_grbl, submit, subscribe};
use crate::support::instances::{last_line, rigd_to_end, run_to_end, snapshot, Logged};
use rigd::cli::client::Client;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::lock::{device_lock_path, Holder, LockFile};
use rigd::session::{Session, SessionState};
use rigd::sim::grbl::GrblSim;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// A hardware-mode config: the GRBL emulator at `port` as [axis], a small sim camera, and
/// device locks in `dir/locks`.
fn write_config(dir: &Path, port: &Path) -> PathBuf {
    let text = format!(
        r#"
[axis]
driver = "grbl"
port = "{}"
soft_min_um = 0.0
soft_max_um = 100000.0
max_step_um = 100000.0
open_timeout_ms = 2000
[camera]
driver = "sim"
[camera.sim]
width = 48
height = 32
supersample = 2
frame_period_ms = 2.0
exposure_ms = 1.0
[daemon]
lock_dir = "{}"
"#,
        port.display(),
        dir.join("locks").display()
    );
    let p = dir.join("rig.toml");
    std::fs::write(&p, text).unwrap();
    p
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Wait until the emulator has heard nothing for 300 ms (the daemon is settling).
fn quiet(grbl: &GrblSim) -> u64 {
    let t = Instant::now();
    loop {
        let n = grbl.bytes_received();
        std::thread::sleep(Duration::from_millis(300));
        if grbl.bytes_received() == n {
            return n;
        }
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "the axis never went quiet"
        );
    }
}

/// Submit a job that sits in a 30 s settle after its first move; its id and session.
fn job_in_settle(c: &mut Client) -> (u64, String) {
    subscribe(c);
    let id = submit(c, capture_job(100.0, 2, 30_000));
    loop {
        match c.next_event().unwrap().body {
            EventBody::Started { session, .. } => return (id, session),
            other => assert!(!other.is_terminal(), "{other:?}"),
        }
    }
}

fn cancel_and_end(c: &mut Client, id: u64) -> EventBody {
    c.request(&Request::Cancel { job_id: id }).unwrap();
    loop {
        let e = c.next_event().unwrap();
        if e.job_id == id && e.body.is_terminal() {
            return e.body;
        }
    }
}

#[test]
fn a_second_instance_sends_no_byte_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let (_axis, grbl) = fast_grbl();
    let cfg = write_config(dir.path(), &grbl.path());
    let (sock, data) = (dir.path().join("a.sock"), dir.path().join("data"));
    let first = Logged::spawn(
        &[
            "--config",
            s(&cfg),
            "--socket",
            s(&sock),
            "--data-root",
            s(&data),
        ],
        &[],
        &sock,
        &dir.path().join("first.log"),
    );
    let pid = first.pid();
    let mut c = Client::connect(&sock).unwrap();
    let (id, session) = job_in_settle(&mut c);
    let bytes = quiet(&grbl);
    let before = snapshot(&data);
    let held_by = format!("is held by rigd (pid {pid}, socket {}", sock.display());
    let port = grbl.path();
    let [b, c_sock, d] = ["b.sock", "c.sock", "d.sock"].map(|n| dir.path().join(n));
    let other_data = dir.path().join("other-data");
    let rigd = env!("CARGO_BIN_EXE_rigd");
    let rigctl = env!("CARGO_BIN_EXE_rigctl");
    // (program, args, what the one line names)
    let attempts: Vec<(&str, Vec<&str>, String)> = vec![
        (
            rigd,
            vec![
                "--config",
                s(&cfg),
                "--socket",
                s(&sock),
                "--data-root",
                s(&data),
            ],
            format!("socket {} {held_by}", sock.display()),
        ),
        (
            rigd,
            vec![
                "--config",
                s(&cfg),
                "--socket",
                s(&b),
                "--data-root",
                s(&data),
            ],
            // The port's lock comes before the data root's.
            format!("[axis] port {} {held_by}", port.display()),
        ),
        (
            rigd,
            vec![
                "--config",
                s(&cfg),
                "--socket",
                s(&c_sock),
                "--data-root",
                s(&other_data),
            ],
            format!("[axis] port {} {held_by}", port.display()),
        ),
        (
            rigd,
            vec!["--sim", "--socket", s(&d), "--data-root", s(&data)],
            format!("data root {} {held_by}", data.display()),
        ),
        (
            rigd,
            vec!["--sim", "--socket", s(&sock), "--data-root", s(&other_data)],
            format!("socket {} {held_by}", sock.display()),
        ),
        (
            rigctl,
            vec!["hw", "--config", s(&cfg), "position"],
            format!("[axis] port {} {held_by}", port.display()),
        ),
    ];
    for (program, args, names) in &attempts {
        let (st, stderr) = run_to_end(program, args, &[]);
        assert!(!st.success(), "{args:?} started: {stderr}");
        assert_eq!(
            stderr.trim().lines().count(),
            1,
            "{args:?}: one line: {stderr}"
        );
        assert!(
            last_line(&stderr).contains(names.as_str()),
            "{args:?}: {stderr}"
        );
        assert_eq!(
            grbl.bytes_received(),
            bytes,
            "{args:?} talked to the controller"
        );
        assert!(snapshot(&data) == before, "{args:?} changed the data root");
        assert!(!other_data.exists(), "{args:?} created its data root");
    }
    // The first daemon never noticed: its job is still in its settle and cancels normally.
    assert!(matches!(
        cancel_and_end(&mut c, id),
        EventBody::Cancelled { .. }
    ));
    let m = Session::open(&data.join(&session)).unwrap().manifest;
    assert_eq!(m.state, SessionState::Cancelled, "{:?}", m.reason);
}

#[test]
fn rigd_honours_a_lock_taken_by_rigctl_hw() {
    let dir = tempfile::tempdir().unwrap();
    let (_axis, grbl) = fast_grbl();
    let cfg = write_config(dir.path(), &grbl.path());
    // What `rigctl hw` holds while it talks to the axis (this test process is its holder).
    let locks = dir.path().join("locks");
    std::fs::create_dir_all(&locks).unwrap();
    let me = Holder::me("rigctl hw", None, None);
    let real = std::fs::canonicalize(grbl.path()).unwrap();
    let _held = LockFile::acquire(&device_lock_path(&locks, &real), "port", &me, "").unwrap();
    let (sock, data) = (dir.path().join("a.sock"), dir.path().join("data"));
    let (st, stderr) = rigd_to_end(&[
        "--config",
        s(&cfg),
        "--socket",
        s(&sock),
        "--data-root",
        s(&data),
    ]);
    assert!(!st.success());
    let pid = std::process::id();
    assert!(
        last_line(&stderr).contains(&format!(
            "[axis] port {} is held by rigctl hw (pid {pid}",
            real.display()
        )),
        "{stderr}"
    );
    assert_eq!(grbl.bytes_received(), 0, "rigd opened the port");
    assert!(!sock.exists());
}

#[test]
fn nothing_but_a_stale_socket_is_removed_at_the_socket_path() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let start = |sock: &Path| rigd_to_end(&["--sim", "--socket", s(sock), "--data-root", s(&data)]);
    // A regular file, a symlink to one, a folder: each refused, each left as it was.
    let file = dir.path().join("file.sock");
    std::fs::write(&file, b"not a socket").unwrap();
    let link = dir.path().join("link.sock");
    std::os::unix::fs::symlink(&file, &link).unwrap();
    let folder = dir.path().join("folder.sock");
    std::fs::create_dir(&folder).unwrap();
    for (p, kind) in [
        (&file, "a regular file"),
        (&link, "a symbolic link"),
        (&folder, "a folder"),
    ] {
        let (st, stderr) = start(p);
        assert!(!st.success());
        assert!(
            last_line(&stderr).contains(&format!(
                "socket {}: exists and is {kind}: left alone",
                p.display()
            )),
            "{stderr}"
        );
    }
    assert_eq!(std::fs::read(&file).unwrap(), b"not a socket");
    assert_eq!(std::fs::read_link(&link).unwrap(), file);
    assert!(folder.is_dir());
    // A live socket of a daemon that takes no lock (an older rigd): refused, naming its pid.
    let live = dir.path().join("live.sock");
    let listener = std::os::unix::net::UnixListener::bind(&live).unwrap();
    let (st, stderr) = start(&live);
    assert!(!st.success());
    let pid = std::process::id();
    assert!(
        last_line(&stderr).contains(&format!("another daemon (pid {pid}) is listening on it")),
        "{stderr}"
    );
    // Once nobody listens the socket is stale, and only then replaced.
    drop(listener);
    let mut d = Logged::spawn(
        &["--sim", "--socket", s(&live), "--data-root", s(&data)],
        &[],
        &live,
        &dir.path().join("rigd.log"),
    );
    assert!(d.stop_with(libc::SIGTERM).success());
    assert!(
        d.log_text().contains("removing a stale socket"),
        "{}",
        d.log_text()
    );
}

#[test]
fn demo_never_submits_to_a_daemon_it_did_not_start() {
    let dir = tempfile::tempdir().unwrap();
    let (sock, data) = (dir.path().join("a.sock"), dir.path().join("data"));
    let _daemon = Logged::spawn(
        &["--sim", "--socket", s(&sock), "--data-root", s(&data)],
        &[],
        &sock,
        &dir.path().join("rigd.log"),
    );
    let demo_data = dir.path().join("demo");
    let args = [
        "demo",
        "--socket",
        s(&sock),
        "--data-root",
        s(&demo_data),
        "--repeats",
        "1",
    ];
    let (st, stderr) = run_to_end(env!("CARGO_BIN_EXE_rigctl"), &args, &[]);
    assert!(!st.success());
    assert!(
        last_line(&stderr).contains(&format!("socket {} is held by rigd", sock.display())),
        "{stderr}"
    );
    assert!(!demo_data.exists(), "the demo started before refusing");
    // The daemon that was there ran nothing.
    let list = Client::connect(&sock)
        .unwrap()
        .request(&Request::List {
            limit: None,
            before: None,
        })
        .unwrap();
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(0), "{list}");
    assert_eq!(list["sessions"].as_array().map(Vec::len), Some(0), "{list}");
}

#[test]
fn sighup_sigint_and_sigterm_all_stop_cleanly() {
    for (sig, name) in [
        (libc::SIGHUP, "SIGHUP"),
        (libc::SIGINT, "SIGINT"),
        (libc::SIGTERM, "SIGTERM"),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let (sock, data) = (dir.path().join("a.sock"), dir.path().join("data"));
        let args = ["--sim", "--socket", s(&sock), "--data-root", s(&data)];
        let mut d = Logged::spawn(&args, &[], &sock, &dir.path().join("rigd.log"));
        let mut c = Client::connect(&sock).unwrap();
        let (_, session) = job_in_settle(&mut c);
        let t = Instant::now();
        let st = d.stop_with(sig);
        assert!(st.success(), "{name}: {st}");
        // The job was in a 30 s settle: it stopped at once, not after it.
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "{name}: {:?}",
            t.elapsed()
        );
        assert!(!sock.exists(), "{name}: the socket is left behind");
        let m = Session::open(&data.join(&session)).unwrap().manifest;
        assert_eq!(m.state, SessionState::Cancelled, "{name}: {:?}", m.reason);
        assert!(
            d.log_text().contains(&format!("signal=\"{name}\"")),
            "{}",
            d.log_text()
        );
        // The locks went with the daemon: the same socket and data root serve again.
        let mut again = Logged::spawn(&args, &[], &sock, &dir.path().join("again.log"));
        assert!(again.stop_with(libc::SIGTERM).success());
    }
}

#[test]
fn systemd_hears_ready_once_the_socket_is_bound_and_logs_are_plain() {
    let dir = tempfile::tempdir().unwrap();
    let notify = dir.path().join("notify");
    let rx = std::os::unix::net::UnixDatagram::bind(&notify).unwrap();
    rx.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    let (sock, data) = (dir.path().join("a.sock"), dir.path().join("data"));
    let log = dir.path().join("rigd.log");
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_rigd"))
        .args(["--sim", "--socket", s(&sock), "--data-root", s(&data)])
        .env("RUST_LOG", "info")
        .env("NOTIFY_SOCKET", &notify)
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let mut d = Logged {
        child: Some(child),
        log,
    };
    let mut buf = [0u8; 256];
    let n = rx.recv(&mut buf).expect("READY=1 within 20 s");
    assert_eq!(&buf[..n], b"READY=1");
    // Ready means serving: the socket answers at once.
    Client::connect(&sock).expect("bound before READY=1");
    assert!(d.stop_with(libc::SIGTERM).success());
    let n = rx.recv(&mut buf).unwrap();
    assert_eq!(&buf[..n], b"STOPPING=1");
    // stderr is a file here: no colour codes in what journald would store.
    let text = d.log_text();
    assert!(text.contains("rigd listening"), "{text}");
    assert!(!text.contains('\x1b'), "ANSI escapes in the log: {text:?}");
}

/// Below rigd's own locks, the port itself is opened exclusively by the real serialport
/// path: TIOCEXCL on the tty (which root bypasses) and an `flock` on it (which root does not).
#[test]
fn the_daemons_port_is_opened_with_tiocexcl_and_an_flock() {
    use std::os::fd::AsRawFd;
    use std::os::unix::fs::OpenOptionsExt;
    let dir = tempfile::tempdir().unwrap();
    let (_axis, grbl) = fast_grbl();
    let cfg = write_config(dir.path(), &grbl.path());
    let (sock, data) = (dir.path().join("a.sock"), dir.path().join("data"));
    let args = [
        "--config",
        s(&cfg),
        "--socket",
        s(&sock),
        "--data-root",
        s(&data),
    ];
    let _d = Logged::spawn(&args, &[], &sock, &dir.path().join("rigd.log"));
    // Root may still open the tty (TIOCEXCL does not stop root); it reads the tty's flag.
    let f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .custom_flags(libc::O_NOCTTY | libc::O_NONBLOCK)
        .open(grbl.path())
        .unwrap();
    let mut excl: libc::c_int = 0;
    // SAFETY: TIOCGEXCL writes one int through the pointer; the fd is open.
    let r = unsafe { libc::ioctl(f.as_raw_fd(), libc::TIOCGEXCL, &mut excl) };
    assert_eq!(
        (r, excl),
        (0, 1),
        "TIOCEXCL is not set on the daemon's port"
    );
    // SAFETY: flock on an open fd.
    let r = unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
    let errno = std::io::Error::last_os_error().raw_os_error();
    assert_eq!(
        (r, errno),
        (-1, Some(libc::EWOULDBLOCK)),
        "the port is not flock'ed"
    );
}
