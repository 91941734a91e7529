//! A real disk-full mid-job: `rigd --sim` runs in its own mount namespace (`unshare`) with
//! its data root on a small tmpfs; once the job has captured a few frames the test fills
//! the tmpfs through `/proc/<pid>/root` (as another program on the machine would), so the
//! daemon's next frame write gets ENOSPC from the kernel. Needs root or unprivileged user
//! namespaces; without them the test prints `SKIPPED: <test>: <why>` on stderr, past the
//! output capture (with `CI` set and run as root it fails instead, so CI cannot skip it).

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{assert_frames_decode, capture_job, end_of, submit, subscribe};
use rigd::acquisition::JobSpec;
use rigd::cli::client::Client;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::session::{Session, SessionState};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn is_root() -> bool {
    // SAFETY: geteuid has no preconditions.
    unsafe { libc::geteuid() == 0 }
}

/// The unshare command that gives a private mount namespace in which we may mount.
fn isolation() -> Vec<&'static str> {
    if is_root() {
        vec!["unshare", "--mount"]
    } else {
        vec!["unshare", "--user", "--map-root-user", "--mount"]
    }
}

/// Can we mount a tmpfs in a private mount namespace here? `Err` says why not.
fn probe(dir: &Path) -> Result<(), String> {
    let mnt = dir.join("probe");
    std::fs::create_dir_all(&mnt).map_err(|e| e.to_string())?;
    let cmd = isolation();
    let out = Command::new(cmd[0])
        .args(&cmd[1..])
        .args(["sh", "-c", "mount -t tmpfs -o size=64k tmpfs \"$1\"", "sh"])
        .arg(&mnt)
        .output()
        .map_err(|e| format!("cannot run {}: {e}", cmd.join(" ")))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "`{} sh -c 'mount -t tmpfs …'` failed: {}",
            cmd.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

/// False (after saying `SKIPPED: <test>: …`) when the isolation tools are missing; panics
/// instead on CI as root, where they must work.
fn can_isolate(test: &str, dir: &Path) -> bool {
    match probe(dir) {
        Ok(()) => true,
        Err(why) if std::env::var_os("CI").is_some() && is_root() => {
            panic!("{test}: CI runs as root, so the disk-full test must run: {why}")
        }
        Err(why) => {
            crate::support::skip::skipped(
                test,
                &format!("a tmpfs in a private mount namespace is not available: {why}"),
            );
            false
        }
    }
}

/// A private mount namespace with a tmpfs of `size_mb` at `mnt`, in which a small
/// supervisor shell runs `rigd --sim` (data root on the tmpfs) and starts it again whenever
/// it exits, until told to stop: so the test can restart the daemon on the same tmpfs.
struct Namespace {
    shell: Child,
    mnt: PathBuf,
    socket: PathBuf,
    keep: PathBuf,
    pidfile: PathBuf,
}

impl Namespace {
    fn start(dir: &Path, size_mb: u32) -> Namespace {
        let mnt = dir.join("mnt");
        std::fs::create_dir_all(&mnt).unwrap();
        let (socket, keep, pidfile) = (
            dir.join("rigd.sock"),
            dir.join("keep-running"),
            dir.join("rigd.pid"),
        );
        std::fs::write(&keep, b"").unwrap();
        let cmd = isolation();
        let script = format!(
            "mount -t tmpfs -o size={size_mb}m tmpfs \"$1\" || exit 1\n\
             while [ -e \"$4\" ]; do\n\
               \"$2\" --sim --socket \"$3\" --data-root \"$1/data\" &\n\
               echo $! > \"$5.tmp\" && mv \"$5.tmp\" \"$5\"\n\
               wait $!\n\
             done\n"
        );
        let shell = Command::new(cmd[0])
            .args(&cmd[1..])
            .args(["sh", "-c", &script, "sh"])
            .arg(&mnt)
            .arg(env!("CARGO_BIN_EXE_rigd"))
            .arg(&socket)
            .arg(&keep)
            .arg(&pidfile)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        let mut ns = Namespace {
            shell,
            mnt,
            socket,
            keep,
            pidfile,
        };
        ns.wait_for_rigd(None);
        ns
    }

    fn rigd_pid(&self) -> Option<i32> {
        std::fs::read_to_string(&self.pidfile)
            .ok()?
            .trim()
            .parse()
            .ok()
    }

    /// Wait until a rigd other than `old` answers on the socket.
    fn wait_for_rigd(&mut self, old: Option<i32>) {
        let t = Instant::now();
        loop {
            if let Ok(Some(status)) = self.shell.try_wait() {
                panic!("the namespace's shell exited: {status}");
            }
            let pid = self.rigd_pid();
            if pid.is_some() && pid != old && Client::connect(&self.socket).is_ok() {
                return;
            }
            assert!(t.elapsed() < Duration::from_secs(30), "rigd did not start");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// `kill -9` the daemon; the supervisor starts a new one on the same tmpfs.
    fn restart_rigd(&mut self) -> Client {
        let old = self.rigd_pid().expect("rigd is running");
        let _ = std::fs::remove_file(&self.socket);
        // SAFETY: signalling a process this test started.
        unsafe { libc::kill(old, libc::SIGKILL) };
        self.wait_for_rigd(Some(old));
        Client::connect(&self.socket).unwrap()
    }

    /// The tmpfs as the daemon sees it, from outside its namespace.
    fn root(&self) -> PathBuf {
        PathBuf::from(format!("/proc/{}/root", self.shell.id()))
            .join(self.mnt.strip_prefix("/").unwrap())
    }

    fn client(&self) -> Client {
        Client::connect(&self.socket).unwrap()
    }
}

impl Drop for Namespace {
    /// Stop the supervisor, then the daemon; the namespace and its tmpfs go with them.
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.keep);
        if let Some(pid) = self.rigd_pid() {
            // SAFETY: signalling a process this test started.
            unsafe { libc::kill(pid, libc::SIGKILL) };
        }
        let _ = self.shell.kill();
        let _ = self.shell.wait();
    }
}

/// Fill the filesystem holding `dir` until the kernel says ENOSPC, then give back
/// `slack` bytes: room for a manifest, not for a frame.
fn fill(dir: &Path, slack: u64) -> PathBuf {
    let path = dir.join("filler");
    let mut f = std::fs::File::create(&path).unwrap();
    let chunk = vec![0x5a_u8; 64 * 1024];
    let mut written = 0u64;
    loop {
        match f.write(&chunk) {
            Ok(0) => break,
            Ok(n) => written += n as u64,
            Err(e) if e.raw_os_error() == Some(libc::ENOSPC) => break,
            Err(e) => panic!("filling {}: {e}", path.display()),
        }
    }
    f.set_len(written.saturating_sub(slack)).unwrap();
    f.sync_all().unwrap();
    path
}

/// Run a 16-frame capture job; once two frames are in, another program fills the disk at
/// `root` leaving `slack` bytes. The job must fail: its id, its session, the frames
/// reported, the filler file and the failure reason.
fn fill_mid_job(
    c: &mut Client,
    root: &Path,
    slack: u64,
) -> (u64, String, Vec<u32>, PathBuf, String) {
    subscribe(c);
    let id = submit(c, capture_job(50.0, 16, 100));
    let (mut session, mut reported, mut filler) = (String::new(), Vec::new(), None);
    let end = loop {
        let e = c.next_event().unwrap();
        if e.job_id != id {
            continue;
        }
        match e.body {
            EventBody::Started { session: s, .. } => session = s,
            EventBody::Step { index, .. } => {
                reported.push(index);
                if reported.len() == 2 {
                    filler = Some(fill(root, slack));
                }
            }
            b if b.is_terminal() => break b,
            _ => {}
        }
    };
    let filler = filler.expect("the job reached two frames");
    let EventBody::Failed { reason, .. } = end else {
        panic!("the job did not fail: {end:?}")
    };
    (id, session, reported, filler, reason)
}

fn frames_on_disk(s: &Session) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(s.dir.join("frames"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn a_disk_filling_up_mid_job_fails_it_cleanly_and_the_daemon_keeps_serving() {
    let dir = tempfile::tempdir().unwrap();
    if !can_isolate(
        "a_disk_filling_up_mid_job_fails_it_cleanly_and_the_daemon_keeps_serving",
        dir.path(),
    ) {
        return;
    }
    // The default sim camera: 1280x720 frames of ~2 MB as PNG.
    let ns = Namespace::start(dir.path(), 64);
    let root = ns.root();
    let data = root.join("data");
    assert!(data.is_dir(), "{} is not visible", data.display());

    let mut c = ns.client();
    // The pre-flight check: more frames than the tmpfs holds is refused before anything
    // moves, naming the free space.
    let too_many = JobSpec {
        step_um: Some(50.0),
        steps: Some(40),
        process: false,
        ..JobSpec::default()
    };
    let e = c
        .request(&Request::Submit { job: too_many })
        .unwrap_err()
        .to_string();
    assert!(e.contains("MB free"), "{e}");

    // Another program fills the disk once two frames are in.
    let (id, session, reported, filler, reason) = fill_mid_job(&mut c, &root, 256 * 1024);
    eprintln!("disk full after {} frames: {reason}", reported.len());
    assert!(reported.len() >= 2 && reported.len() < 16, "{reported:?}");
    // The reason says the disk is full and names the frame that could not be written.
    let missing = format!("frames/{:06}.png", reported.len());
    assert!(reason.starts_with("disk: session "), "{reason}");
    assert!(
        reason.contains("disk full") && reason.contains(&missing),
        "{reason}"
    );
    assert!(reason.contains("axis stopped at"), "{reason}");

    // The daemon keeps serving.
    let st = c.request(&Request::Status { job_id: Some(id) }).unwrap();
    assert_eq!(st["state"], "failed");
    assert_eq!(st["frames_done"].as_u64(), Some(reported.len() as u64));

    // The session: marked failed (the manifest fit in the slack), every reported frame
    // whole and in steps.csv, no partial file left behind.
    let s = Session::open(&data.join(&session)).unwrap();
    assert_eq!(s.manifest.state, SessionState::Failed);
    assert_eq!(s.manifest.reason.as_deref(), Some(reason.as_str()));
    assert_eq!(s.manifest.frames_captured as usize, reported.len());
    let rows: Vec<u32> = s.steps.iter().map(|r| r.index).collect();
    assert_eq!(rows, reported, "steps.csv rows are the frames reported");
    let names = frames_on_disk(&s);
    let want: Vec<String> = reported.iter().map(|i| format!("{i:06}.png")).collect();
    assert_eq!(names, want, "frames/ holds exactly the reported frames");
    assert_frames_decode(&s, (1280, 720));
    for f in [
        "manifest.json",
        "steps.csv",
        "interferometer.csv",
        "result.json",
    ] {
        assert!(s.dir.join(f).is_file(), "{f}");
        assert!(
            !s.dir.join(format!(".{f}.tmp")).exists(),
            "{f}'s temporary file is left"
        );
    }

    // While the disk is full even a short job is refused up front.
    let one = JobSpec {
        steps: Some(1),
        process: false,
        ..JobSpec::default()
    };
    let e = c
        .request(&Request::Submit { job: one.clone() })
        .unwrap_err()
        .to_string();
    assert!(e.contains("MB free"), "{e}");
    // Space freed: the daemon runs the next job.
    std::fs::remove_file(&filler).unwrap();
    let id = submit(&mut c, one);
    let ended = end_of(&mut c, id);
    assert!(matches!(ended, EventBody::Finished { .. }), "{ended:?}");
}

#[test]
fn a_disk_too_full_for_the_manifest_is_recovered_by_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    if !can_isolate(
        "a_disk_too_full_for_the_manifest_is_recovered_by_a_restart",
        dir.path(),
    ) {
        return;
    }
    let mut ns = Namespace::start(dir.path(), 64);
    let data = ns.root().join("data");
    let mut c = ns.client();
    // No slack at all: not even the manifest fits.
    let (id, session, reported, filler, reason) = fill_mid_job(&mut c, &ns.root(), 0);
    eprintln!("no room at all after {} frames: {reason}", reported.len());
    // The first reason is the first write of the next step that did not fit: its share of
    // the interferometer log (appended before the frame) or the frame itself.
    let missing = format!("frames/{:06}.png: disk full", reported.len());
    assert!(
        reason.starts_with("disk: session ")
            && (reason.contains(&missing) || reason.contains("interferometer.csv: disk full")),
        "{reason}"
    );
    let st = c.request(&Request::Status { job_id: Some(id) }).unwrap();
    assert_eq!(st["state"], "failed");

    let check = |s: &Session| {
        let rows: Vec<u32> = s.steps.iter().map(|r| r.index).collect();
        assert_eq!(rows, reported, "steps.csv rows are the frames reported");
        let want: Vec<String> = reported.iter().map(|i| format!("{i:06}.png")).collect();
        assert_eq!(
            frames_on_disk(s),
            want,
            "frames/ holds exactly the reported frames"
        );
        assert_frames_decode(s, (1280, 720));
    };
    // Whatever fit is whole; the manifest is the old one (`running`) or the final one.
    let s = Session::open(&data.join(&session)).unwrap();
    check(&s);
    let was = s.manifest.state;
    assert!(
        was == SessionState::Running || was == SessionState::Failed,
        "{was:?}"
    );

    // A restart while the disk is still full: the daemon starts and serves all the same.
    let mut c = ns.restart_rigd();
    c.request(&Request::Hello {}).unwrap();
    let s = Session::open(&data.join(&session)).unwrap();
    assert_eq!(s.manifest.state, was, "nothing could be written");
    check(&s);

    // Space back, restart again: a session left `running` is marked `incomplete`.
    std::fs::remove_file(&filler).unwrap();
    let mut c = ns.restart_rigd();
    let s = Session::open(&data.join(&session)).unwrap();
    let want = match was {
        SessionState::Running => SessionState::Incomplete,
        other => other,
    };
    assert_eq!(s.manifest.state, want);
    assert_eq!(s.manifest.frames_captured as usize, reported.len());
    check(&s);
    let listed = c
        .request(&Request::List {
            limit: None,
            before: None,
        })
        .unwrap();
    let entry = listed["sessions"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["name"] == session.as_str())
        .cloned()
        .unwrap();
    assert_eq!(entry["state"], serde_json::to_value(want).unwrap());
    // And it runs the next job.
    subscribe(&mut c);
    let one = JobSpec {
        steps: Some(1),
        process: false,
        ..JobSpec::default()
    };
    let id = submit(&mut c, one);
    let ended = end_of(&mut c, id);
    assert!(matches!(ended, EventBody::Finished { .. }), "{ended:?}");
}
