//! Plumbing for the adversarial tests and `benches/adversarial.rs`: the `rigd` binary as a
//! child with its own config, open-file limit and a log file for its stderr; what /proc says
//! about it; clients that misbehave.

use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::UnixStream;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A small fast all-sim rig (48x32 frames every 2 ms) for `rigd --config`.
pub const SMALL_SIM_RIG: &str = r#"
[axis]
driver = "sim"
soft_min_um = 0.0
soft_max_um = 100000.0
max_step_um = 100000.0
[camera]
driver = "sim"
[camera.sim]
width = 48
height = 32
supersample = 2
frame_period_ms = 2.0
exposure_ms = 1.0
"#;

/// A `rigd` child; killed (SIGKILL) on drop if still running.
pub struct Rigd {
    pub child: Option<Child>,
    pub socket: PathBuf,
    pub data: PathBuf,
    /// Where its stderr goes.
    pub log: PathBuf,
}

/// How to start one.
pub struct Spawn<'a> {
    pub bin: PathBuf,
    pub dir: &'a Path,
    /// The rig sections of its config (the `[daemon]` section is added).
    pub rig_toml: &'a str,
    /// More `[daemon]` keys, one a line.
    pub daemon_toml: &'a str,
    /// The child's RLIMIT_NOFILE (soft and hard).
    pub nofile: Option<u64>,
    /// `--sim` instead of the config's rig.
    pub sim: bool,
    pub rust_log: Option<&'a str>,
}

impl<'a> Spawn<'a> {
    pub fn new(bin: impl Into<PathBuf>, dir: &'a Path) -> Spawn<'a> {
        Spawn {
            bin: bin.into(),
            dir,
            rig_toml: SMALL_SIM_RIG,
            daemon_toml: "",
            nofile: None,
            sim: false,
            rust_log: None,
        }
    }

    pub fn start(self) -> Rigd {
        let socket = self.dir.join("rigd.sock");
        let data = self.dir.join("data");
        let log = self.dir.join("rigd.stderr");
        let config = self.dir.join("rig.toml");
        let text = format!(
            "{}\n[daemon]\nsocket = {:?}\ndata_root = {:?}\n{}\n",
            if self.sim { "" } else { self.rig_toml },
            socket.display().to_string(),
            data.display().to_string(),
            self.daemon_toml
        );
        std::fs::write(&config, text).unwrap();
        let mut cmd = Command::new(&self.bin);
        cmd.arg("--config").arg(&config);
        if self.sim {
            cmd.arg("--sim");
        }
        match self.rust_log {
            Some(l) => cmd.env("RUST_LOG", l),
            None => cmd.env_remove("RUST_LOG"),
        };
        let err = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log)
            .unwrap();
        cmd.stdout(Stdio::null()).stderr(Stdio::from(err));
        if let Some(n) = self.nofile {
            // SAFETY: setrlimit is async-signal-safe; nothing else runs between fork and exec.
            unsafe {
                cmd.pre_exec(move || {
                    let lim = libc::rlimit {
                        rlim_cur: n,
                        rlim_max: n,
                    };
                    match libc::setrlimit(libc::RLIMIT_NOFILE, &lim) {
                        0 => Ok(()),
                        _ => Err(std::io::Error::last_os_error()),
                    }
                });
            }
        }
        let child = cmd.spawn().unwrap();
        let r = Rigd {
            child: Some(child),
            socket,
            data,
            log,
        };
        let t = Instant::now();
        while UnixStream::connect(&r.socket).is_err() {
            assert!(
                t.elapsed() < Duration::from_secs(30),
                "rigd did not start: {}",
                std::fs::read_to_string(&r.log).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        r
    }
}

impl Rigd {
    pub fn pid(&self) -> u32 {
        self.child.as_ref().expect("running").id()
    }

    /// SIGTERM and wait.
    pub fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            unsafe { libc::kill(c.id() as i32, libc::SIGTERM) };
            let _ = c.wait();
        }
    }

    /// SIGKILL and wait.
    pub fn kill_9(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    pub fn log_lines(&self) -> usize {
        std::fs::read(&self.log)
            .map(|b| b.iter().filter(|&&c| c == b'\n').count())
            .unwrap_or(0)
    }

    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    pub fn client(&self) -> Line {
        Line::connect(&self.socket)
    }
}

impl Drop for Rigd {
    fn drop(&mut self) {
        self.kill_9();
    }
}

/// CPU time the process has used (user + system), from /proc/PID/stat.
pub fn cpu_time(pid: u32) -> Duration {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    // Fields after the command (which may hold spaces) start after the last ')'.
    let rest = stat.rsplit_once(')').map(|r| r.1).unwrap_or("");
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: u64 = [11, 12]
        .iter()
        .filter_map(|&i| f.get(i).and_then(|v| v.parse::<u64>().ok()))
        .sum();
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as u64;
    Duration::from_millis(ticks * 1000 / hz)
}

/// (VmRSS, VmHWM) in kB, from /proc/PID/status.
pub fn rss_kb(pid: u32) -> (u64, u64) {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let field = |name: &str| {
        s.lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

pub fn open_fds(pid: u32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd"))
        .map(|d| d.count())
        .unwrap_or(0)
}

/// A line-at-a-time client with a read deadline.
pub struct Line {
    pub r: BufReader<UnixStream>,
    pub w: UnixStream,
}

impl Line {
    pub fn connect(socket: &Path) -> Line {
        let s = UnixStream::connect(socket).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
        Line {
            r: BufReader::new(s.try_clone().unwrap()),
            w: s,
        }
    }

    pub fn send(&mut self, line: &str) {
        self.w.write_all(line.as_bytes()).unwrap();
        self.w.write_all(b"\n").unwrap();
    }

    /// The next line as JSON; `None` at the end of the connection.
    pub fn read(&mut self) -> Option<serde_json::Value> {
        let mut line = String::new();
        match self.r.read_line(&mut line) {
            Ok(0) | Err(_) => None,
            Ok(_) => Some(serde_json::from_str(&line).unwrap_or_else(|e| panic!("{e}: {line}"))),
        }
    }

    /// Send and read the reply (skipping events).
    pub fn request(&mut self, line: &str) -> serde_json::Value {
        self.send(line);
        loop {
            let v = self.read().expect("a reply");
            if v["type"] == "reply" {
                return v;
            }
        }
    }

    /// Everything left until the server closes the connection (or `deadline` passes):
    /// (lines, whether the server closed it).
    pub fn drain(&mut self, deadline: Duration) -> (Vec<serde_json::Value>, bool) {
        self.w.set_read_timeout(Some(deadline)).unwrap();
        let mut all = Vec::new();
        let mut bytes = Vec::new();
        let closed = match self.r.read_to_end(&mut bytes) {
            Ok(_) => true,
            Err(e) => e.kind() == std::io::ErrorKind::ConnectionReset,
        };
        for l in bytes.split(|&b| b == b'\n').filter(|l| !l.is_empty()) {
            if let Ok(v) = serde_json::from_slice(l) {
                all.push(v);
            }
        }
        (all, closed)
    }
}

/// This process's soft open-file limit raised to at least `n` (up to the hard limit): the
/// flood's client ends are fds here too.
pub fn raise_fd_limit(n: u64) {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    unsafe {
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) == 0 && lim.rlim_cur < n {
            lim.rlim_cur = n.min(lim.rlim_max);
            libc::setrlimit(libc::RLIMIT_NOFILE, &lim);
        }
    }
}

/// Open `n` connections and leave them idle; the ones the kernel refuses are left out.
pub fn idle_flood(socket: &Path, n: usize) -> Vec<UnixStream> {
    (0..n)
        .filter_map(|_| UnixStream::connect(socket).ok())
        .collect()
}

/// A capture-only job of `steps` frames 10 µm apart, settling `settle_ms`, as JSON.
pub fn capture_job(steps: u32, settle_ms: u64, label: &str) -> String {
    serde_json::json!({
        "kind": "submit",
        "job": {"steps": steps, "step_um": 10.0, "settle_ms": settle_ms, "process": false, "label": label},
    })
    .to_string()
}

/// Follow job `id` on a subscribed connection to its terminal event; all its events.
pub fn follow(c: &mut Line, id: u64) -> Vec<serde_json::Value> {
    let mut v = Vec::new();
    loop {
        let e = c.read().expect("an event");
        if e["type"] != "event" || e["job_id"].as_u64() != Some(id) {
            continue;
        }
        let end = matches!(
            e["event"].as_str(),
            Some("finished" | "failed" | "cancelled")
        );
        v.push(e);
        if end {
            return v;
        }
    }
}
