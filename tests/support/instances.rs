//! The second-instance and signal tests around the real `rigd` binary: a daemon whose log goes to
//! a file, a second instance run to its (refused) end, signals, and a snapshot of a folder
//! (names, kinds, sizes, mtimes, contents) to show that nothing on disk changed.

use rigd::cli::client::Client;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant, SystemTime};

/// A `rigd` child whose stderr (RUST_LOG=info) goes to `log`; killed on drop.
pub struct Logged {
    pub child: Option<Child>,
    pub log: PathBuf,
}

impl Logged {
    /// Start `rigd ARGS` (extra environment `env`) and wait until it answers on `socket`.
    pub fn spawn(args: &[&str], env: &[(&str, &str)], socket: &Path, log: &Path) -> Logged {
        let child = Command::new(env!("CARGO_BIN_EXE_rigd"))
            .args(args)
            .env("RUST_LOG", "info")
            .envs(env.iter().copied())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(log).unwrap())
            .spawn()
            .unwrap();
        let mut me = Logged {
            child: Some(child),
            log: log.to_path_buf(),
        };
        let t = Instant::now();
        while Client::connect(socket).is_err() {
            if let Some(st) = me.child.as_mut().unwrap().try_wait().unwrap() {
                panic!("rigd exited with {st}: {}", me.log_text());
            }
            assert!(t.elapsed() < Duration::from_secs(20), "rigd did not start");
            std::thread::sleep(Duration::from_millis(20));
        }
        me
    }

    pub fn pid(&self) -> u32 {
        self.child.as_ref().expect("running").id()
    }

    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Send `sig` and wait (at most 20 s) for the exit.
    pub fn stop_with(&mut self, sig: i32) -> ExitStatus {
        let mut c = self.child.take().expect("running");
        // SAFETY: signalling our own child process.
        unsafe { libc::kill(c.id() as i32, sig) };
        wait_for(&mut c, Duration::from_secs(20))
    }
}

impl Drop for Logged {
    fn drop(&mut self) {
        if let Some(c) = self.child.as_mut() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

fn wait_for(c: &mut Child, limit: Duration) -> ExitStatus {
    let t = Instant::now();
    loop {
        if let Some(st) = c.try_wait().unwrap() {
            return st;
        }
        if t.elapsed() > limit {
            let _ = c.kill();
            let _ = c.wait();
            panic!("still running after {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Run `program ARGS` to its end (at most 20 s: a second instance must not start serving),
/// with `env` added; its status and stderr.
pub fn run_to_end(program: &str, args: &[&str], env: &[(&str, &str)]) -> (ExitStatus, String) {
    let err = tempfile::NamedTempFile::new().unwrap();
    let mut c = Command::new(program)
        .args(args)
        .env("RUST_LOG", "info")
        .envs(env.iter().copied())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(err.reopen().unwrap())
        .spawn()
        .unwrap();
    let st = wait_for(&mut c, Duration::from_secs(20));
    (st, std::fs::read_to_string(err.path()).unwrap())
}

/// Run the `rigd` binary to its end: see [`run_to_end`].
pub fn rigd_to_end(args: &[&str]) -> (ExitStatus, String) {
    run_to_end(env!("CARGO_BIN_EXE_rigd"), args, &[])
}

/// What a folder holds, recursively, without following symlinks: for each path, its kind,
/// size, mtime and (files, links) contents.
pub type Snapshot = BTreeMap<PathBuf, (String, u64, SystemTime, Vec<u8>)>;

pub fn snapshot(dir: &Path) -> Snapshot {
    let mut out = Snapshot::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            let m = std::fs::symlink_metadata(&p).unwrap();
            let t = m.file_type();
            let (kind, body) = if t.is_symlink() {
                (
                    "link",
                    std::fs::read_link(&p)
                        .unwrap()
                        .into_os_string()
                        .into_encoded_bytes(),
                )
            } else if t.is_dir() {
                todo.push(p.clone());
                ("dir", Vec::new())
            } else {
                ("file", std::fs::read(&p).unwrap())
            };
            out.insert(p, (kind.into(), m.len(), m.modified().unwrap(), body));
        }
    }
    out
}

/// The last non-empty line of a process's stderr (a refusal is one line).
pub fn last_line(stderr: &str) -> &str {
    stderr
        .lines()
        .rev()
        .find(|l| !l.trim().is_empty())
        .unwrap_or("")
}
