//! GRBL 1.1h's own firmware (`../shared/peers/grbl`: gnea/grbl compiled for this machine by
//! grbl-sim) on a pseudo-terminal, for tests of rigd against the real controller. Its
//! `build.sh` builds it once per test binary into `target/grbl-firmware`; its
//! `pty_bridge.py` runs it on a pty and logs the traffic both ways.
//!
//! Where it cannot run (no peers folder, no cc, make or python3), [`Firmware::start`] says
//! `SKIPPED` and returns None; under `CI=1` it panics instead, so CI cannot skip it in
//! silence. One firmware runs at a time ([`Firmware::start`] holds a lock until the
//! firmware is dropped): its simulated clock needs a core of its own to keep real time.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Mutex, MutexGuard, OnceLock};
use std::time::{Duration, Instant};

/// The firmware running on a pty; killed (with its bridge) on drop.
pub struct Firmware {
    bridge: Bridge,
    /// The client's end of the pty (`/dev/pts/N`).
    pub port: String,
    work: tempfile::TempDir,
    _one_at_a_time: MutexGuard<'static, ()>,
}

fn peers() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/peers/grbl")
}

fn has(tool: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {tool}")])
        .stdout(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// The firmware's executable, built on first use; Err says why it cannot be.
fn executable() -> &'static Result<PathBuf, String> {
    static EXE: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    EXE.get_or_init(|| {
        let build = peers().join("build.sh");
        if !build.exists() {
            return Err(format!("{} is missing", build.display()));
        }
        if let Some(t) = ["cc", "make", "python3"].into_iter().find(|t| !has(t)) {
            return Err(format!("{t} is not installed"));
        }
        let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/grbl-firmware");
        let exe = out.join("grbl/grbl-sim/grbl_sim.exe");
        if exe.exists() {
            return Ok(exe);
        }
        let built = Command::new("sh")
            .arg(&build)
            .arg(&out)
            .output()
            .map_err(|e| format!("running build.sh: {e}"))?;
        if !built.status.success() || !exe.exists() {
            return Err(format!(
                "build.sh failed: {}",
                String::from_utf8_lossy(&built.stderr)
            ));
        }
        Ok(exe)
    })
}

impl Firmware {
    /// Start the firmware with its default settings (a fresh EEPROM), or None where this
    /// machine cannot run it (not under CI).
    pub fn start(test: &str) -> Option<Firmware> {
        Firmware::start_with(test, &[])
    }

    /// [`start`](Self::start), with `$N=V` settings stored in its EEPROM first (the firmware
    /// is restarted so it boots with them).
    pub fn start_with(test: &str, settings: &[&str]) -> Option<Firmware> {
        let exe = match executable() {
            Ok(exe) => exe,
            Err(why) if std::env::var_os("CI").is_some() => panic!("{test}: {why}"),
            Err(why) => {
                super::skip::skipped(test, &format!("GRBL firmware: {why}"));
                return None;
            }
        };
        static ONE: Mutex<()> = Mutex::new(());
        let guard = ONE.lock().unwrap_or_else(|p| p.into_inner());
        let work = tempfile::tempdir().unwrap();
        let mut fw = Firmware::spawn(exe, work, guard);
        if !settings.is_empty() {
            fw.store(settings);
            let Firmware {
                bridge,
                work,
                _one_at_a_time: guard,
                ..
            } = fw;
            drop(bridge);
            fw = Firmware::spawn(exe, work, guard);
        }
        Some(fw)
    }

    fn spawn(exe: &Path, work: tempfile::TempDir, guard: MutexGuard<'static, ()>) -> Firmware {
        use std::os::unix::process::CommandExt;
        let pathfile = work.path().join("port");
        let _ = std::fs::remove_file(&pathfile);
        let bridge = Command::new("python3")
            .arg(peers().join("pty_bridge.py"))
            .arg(exe)
            .arg(work.path())
            .arg(&pathfile)
            .process_group(0)
            .stdin(Stdio::null())
            .spawn()
            .expect("python3 runs pty_bridge.py");
        let t0 = Instant::now();
        while !pathfile.exists() {
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "no pty from pty_bridge.py"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        let port = std::fs::read_to_string(&pathfile).unwrap();
        Firmware {
            bridge: Bridge(bridge, work.path().join("traffic.log")),
            port,
            work,
            _one_at_a_time: guard,
        }
    }

    /// Write settings through a raw line client, each answered `ok`.
    fn store(&self, settings: &[&str]) {
        let mut c = RawClient::open(&self.port);
        c.until(|l| l.starts_with("Grbl "), Duration::from_secs(5));
        for s in settings {
            c.send(format!("{s}\n").as_bytes());
            c.until(|l| l == "ok", Duration::from_secs(5));
        }
    }

    /// Everything sent to the firmware (`>` lines of the bridge's log, unquoted).
    pub fn sent(&self) -> Vec<u8> {
        self.traffic(b'>')
    }

    /// Everything the firmware sent.
    pub fn received(&self) -> Vec<u8> {
        self.traffic(b'<')
    }

    fn traffic(&self, tag: u8) -> Vec<u8> {
        let log = std::fs::read(self.work.path().join("traffic.log")).unwrap_or_default();
        let mut out = Vec::new();
        for line in log.split(|&b| b == b'\n') {
            if line.first() == Some(&tag) {
                out.extend(unquote(&line[1..]));
            }
        }
        out
    }
}

/// `pty_bridge.py` in its own process group, killed with the firmware it started on drop.
struct Bridge(Child, PathBuf);

impl Drop for Bridge {
    fn drop(&mut self) {
        if std::thread::panicking() {
            show_traffic_end(&self.1);
        }
        // killpg itself: procps's `kill -KILL -PGID` may read the group as a signal number
        // and kill(-1) instead.
        let group = nix::unistd::Pid::from_raw(self.0.id() as i32);
        let _ = nix::sys::signal::killpg(group, nix::sys::signal::Signal::SIGKILL);
        let _ = self.0.wait();
    }
}

/// A Python bytes literal's repr (`b'ok\r\n'`) back to its bytes.
fn unquote(repr: &[u8]) -> Vec<u8> {
    let s = String::from_utf8_lossy(repr);
    let body = s.trim();
    let body = &body[2..body.len().saturating_sub(1)];
    let mut out = Vec::new();
    let mut chars = body.chars();
    while let Some(c) = chars.next() {
        if c != '\\' {
            out.extend(c.to_string().bytes());
            continue;
        }
        match chars.next() {
            Some('r') => out.push(b'\r'),
            Some('n') => out.push(b'\n'),
            Some('t') => out.push(b'\t'),
            Some('x') => {
                let hex: String = chars.by_ref().take(2).collect();
                out.push(u8::from_str_radix(&hex, 16).unwrap_or(0));
            }
            Some(other) => out.extend(other.to_string().bytes()),
            None => {}
        }
    }
    out
}

/// A line client on a serial port (the firmware's pty or an emulator's), for scripts.
pub struct RawClient {
    port: Box<dyn serialport::SerialPort>,
    buf: Vec<u8>,
}

impl RawClient {
    pub fn open(path: &str) -> RawClient {
        let port = serialport::new(path, 115_200)
            .timeout(Duration::from_millis(20))
            .open()
            .unwrap_or_else(|e| panic!("opening {path}: {e}"));
        RawClient {
            port,
            buf: Vec::new(),
        }
    }

    pub fn send(&mut self, bytes: &[u8]) {
        use std::io::Write;
        self.port.write_all(bytes).unwrap();
        self.port.flush().unwrap();
    }

    /// The next line (without `\r\n`) within `within`, or None.
    pub fn line(&mut self, within: Duration) -> Option<String> {
        use std::io::Read;
        let end = Instant::now() + within;
        loop {
            if let Some(i) = self.buf.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = self.buf.drain(..=i).collect();
                return Some(String::from_utf8_lossy(&line).trim_end().to_string());
            }
            if Instant::now() >= end {
                return None;
            }
            let mut tmp = [0u8; 256];
            match self.port.read(&mut tmp) {
                Ok(n) => self.buf.extend_from_slice(&tmp[..n]),
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                Err(e) => panic!("reading: {e}"),
            }
        }
    }

    /// Lines up to and including the first that `last` accepts (panics after `within`).
    pub fn until(&mut self, last: impl Fn(&str) -> bool, within: Duration) -> Vec<String> {
        let end = Instant::now() + within;
        let mut lines = Vec::new();
        loop {
            let left = end.saturating_duration_since(Instant::now());
            let l = self
                .line(left)
                .unwrap_or_else(|| panic!("no closing line within {within:?} after {lines:?}"));
            let done = last(&l);
            lines.push(l);
            if done {
                return lines;
            }
        }
    }
}

/// A failing test shows the end of the traffic, which its temporary folder takes away.
fn show_traffic_end(log: &Path) {
    let log = std::fs::read(log).unwrap_or_default();
    let text = String::from_utf8_lossy(&log);
    let lines: Vec<&str> = text.lines().collect();
    eprintln!("the last of the firmware's traffic:");
    for l in &lines[lines.len().saturating_sub(60)..] {
        eprintln!("  {l}");
    }
}
