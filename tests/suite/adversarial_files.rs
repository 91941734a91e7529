//! Files against the real `rigd` binary: symlinks planted in the data root (a
//! session folder, a `.manifest.json.tmp`, a frame, a temporary) are never followed by
//! recovery or by a replay; leftover temporaries are removed at recovery; the socket is
//! 0600 without a group and 0660 with one.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{capture_job, run_job, session_name, subscribe};
use crate::support::instances::Logged;
use rigd::cli::client::Client;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::session::Manifest;
use rigd::session::{self, Session, SessionState, MANIFEST};
use std::os::unix::fs::{symlink, PermissionsExt};
use std::path::{Path, PathBuf};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A data root with `n` finished 3-frame sessions, recorded by a real `rigd --sim` that has
/// stopped again; their names.
fn recorded_sessions(dir: &Path, n: usize) -> Vec<String> {
    let (sock, data) = (dir.join("rec.sock"), dir.join("data"));
    let args = ["--sim", "--socket", s(&sock), "--data-root", s(&data)];
    let mut d = Logged::spawn(&args, &[], &sock, &dir.join("rec.log"));
    let mut c = Client::connect(&sock).unwrap();
    subscribe(&mut c);
    let names = (0..n)
        .map(|_| session_name(&run_job(&mut c, capture_job(100.0, 3, 0)).1))
        .collect();
    assert!(d.stop_with(libc::SIGTERM).success());
    names
}

/// Rewrite a session's manifest as if its daemon had died mid-job.
fn mark_running(dir: &Path) {
    let mut m: Manifest = Session::open(dir).unwrap().manifest;
    m.state = SessionState::Running;
    session::write_atomic(&dir.join(MANIFEST), &serde_json::to_vec_pretty(&m).unwrap()).unwrap();
}

fn start(dir: &Path) -> (Logged, PathBuf) {
    let (sock, data) = (dir.join("a.sock"), dir.join("data"));
    let args = ["--sim", "--socket", s(&sock), "--data-root", s(&data)];
    (
        Logged::spawn(&args, &[], &sock, &dir.join("rigd.log")),
        sock,
    )
}

#[test]
fn recovery_never_writes_through_planted_symlinks_and_removes_leftovers() {
    let dir = tempfile::tempdir().unwrap();
    let outside = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let names = recorded_sessions(dir.path(), 2);
    // Session A stays, left `running`, with a `.manifest.json.tmp` symlinked to a file
    // outside, leftover temporaries (kill -9 mid-write) and one symlinked out.
    let a = data.join(&names[0]);
    mark_running(&a);
    let victim = outside.path().join("victim.json");
    std::fs::write(&victim, b"precious").unwrap();
    symlink(&victim, a.join(".manifest.json.tmp")).unwrap();
    std::fs::write(a.join("frames/.000001.png.tmp"), b"half a png").unwrap();
    std::fs::write(a.join(".steps.csv.tmp"), b"index,posi").unwrap();
    let victim_png = outside.path().join("victim.png");
    std::fs::write(&victim_png, b"outside").unwrap();
    let planted_tmp = a.join("frames/.000002.png.tmp");
    symlink(&victim_png, &planted_tmp).unwrap();
    // Session B moves outside, `running`, and a symlink to it is planted in the data root.
    let b_out = outside.path().join("b");
    std::fs::rename(data.join(&names[1]), &b_out).unwrap();
    mark_running(&b_out);
    let b_link = data.join(&names[1]);
    symlink(&b_out, &b_link).unwrap();
    let b_manifest = std::fs::read(b_out.join(MANIFEST)).unwrap();

    let (d, sock) = start(dir.path());
    // Outside the data root nothing changed.
    assert_eq!(std::fs::read(&victim).unwrap(), b"precious");
    assert_eq!(std::fs::read(&victim_png).unwrap(), b"outside");
    assert_eq!(std::fs::read(b_out.join(MANIFEST)).unwrap(), b_manifest);
    // A is marked incomplete in a real file; its leftovers are gone, the planted link kept.
    let ma = std::fs::symlink_metadata(a.join(MANIFEST)).unwrap();
    assert!(ma.file_type().is_file());
    assert_eq!(
        Session::open(&a).unwrap().manifest.state,
        SessionState::Incomplete
    );
    assert!(!a.join("frames/.000001.png.tmp").exists());
    assert!(!a.join(".steps.csv.tmp").exists());
    assert!(!a.join(".manifest.json.tmp").exists());
    assert!(std::fs::symlink_metadata(&planted_tmp)
        .unwrap()
        .file_type()
        .is_symlink());
    // Each skipped entry is logged with its path and why.
    let log = d.log_text();
    for p in [&b_link, &planted_tmp] {
        assert!(
            log.lines()
                .any(|l| l.contains("skipped at recovery") && l.contains(s(p))),
            "{p:?} not logged: {log}"
        );
    }
    // B is no session of this daemon's.
    let list = Client::connect(&sock)
        .unwrap()
        .request(&Request::List {
            limit: None,
            before: None,
        })
        .unwrap();
    let listed: Vec<&str> = list["sessions"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|s| s["name"].as_str())
        .collect();
    assert_eq!(listed, [names[0].as_str()], "{list}");
}

#[test]
fn a_replay_never_reads_a_frame_through_a_symlink() {
    let dir = tempfile::tempdir().unwrap();
    let outside = tempfile::tempdir().unwrap();
    let names = recorded_sessions(dir.path(), 1);
    let sdir = dir.path().join("data").join(&names[0]);
    // A valid PNG outside (a copy of the frame) stands in for frame 1.
    let frame = sdir.join("frames/000001.png");
    let out_png = outside.path().join("000001.png");
    std::fs::rename(&frame, &out_png).unwrap();
    symlink(&out_png, &frame).unwrap();
    let (_d, sock) = start(dir.path());
    let mut c = Client::connect(&sock).unwrap();
    subscribe(&mut c);
    let req = Request::Replay {
        session: names[0].clone(),
        processing: Default::default(),
    };
    let (_, events) = crate::support::daemon::run_request(&mut c, &req);
    match events.last() {
        Some(EventBody::Failed { reason, .. }) => {
            assert!(
                reason.contains("000001.png: a symbolic link: not followed"),
                "{reason}"
            )
        }
        other => panic!("the replay read through the symlink: {other:?}"),
    }
    // A session folder that is itself a symlink cannot be replayed either.
    let link = dir.path().join("data").join("20990101T000000Z-job99");
    symlink(&sdir, &link).unwrap();
    let req = Request::Replay {
        session: "20990101T000000Z-job99".into(),
        processing: Default::default(),
    };
    assert!(c.request(&req).is_err());
}

#[test]
fn the_socket_is_0600_without_a_group_and_0660_with_one() {
    let dir = tempfile::tempdir().unwrap();
    let (mut d, sock) = start(dir.path());
    let mode = std::fs::metadata(&sock).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode, 0o600, "{mode:o}");
    assert!(d.stop_with(libc::SIGTERM).success());
    // With [daemon] group (gid 0's group exists on every Linux): group read-write.
    let group = nix::unistd::Group::from_gid(0.into())
        .unwrap()
        .unwrap()
        .name;
    let cfg = dir.path().join("rig.toml");
    std::fs::write(&cfg, format!("[daemon]\ngroup = \"{group}\"\n")).unwrap();
    let data = dir.path().join("data");
    let args = [
        "--sim",
        "--config",
        s(&cfg),
        "--socket",
        s(&sock),
        "--data-root",
        s(&data),
    ];
    let mut d = Logged::spawn(&args, &[], &sock, &dir.path().join("g.log"));
    let mode = std::fs::metadata(&sock).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode, 0o660, "{mode:o}");
    assert!(d.stop_with(libc::SIGTERM).success());
}
