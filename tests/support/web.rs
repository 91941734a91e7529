//! The browser console as its tests drive it: a `rigd --sim` and a `rigctl web` as child
//! processes, raw HTTP requests to the gateway, and Debian's headless Chromium through
//! chromedriver (WebDriver, the fantoccini crate).

use crate::support::daemon::RigdProcess;
use std::ffi::OsStr;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub const CHROMIUM: &str = "/usr/bin/chromium";
pub const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// A child process killed when dropped.
pub struct Killed(pub Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `rigd --sim` (with `extra` arguments) and `rigctl web` on its socket.
pub struct Console {
    pub dir: tempfile::TempDir,
    pub rigd: RigdProcess,
    pub web: Killed,
    /// `http://127.0.0.1:PORT`
    pub base: String,
    pub port: u16,
    pub token: String,
}

impl Console {
    pub fn start(extra: &[&str]) -> Console {
        let dir = tempfile::tempdir().unwrap();
        let rigd = spawn_rigd(dir.path(), extra);
        let mut web = Command::new(env!("CARGO_BIN_EXE_rigctl"))
            .args(["web", "--socket"])
            .arg(dir.path().join("rigd.sock"))
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        let mut first = String::new();
        BufReader::new(web.stdout.take().unwrap())
            .read_line(&mut first)
            .unwrap();
        let url = first
            .split_whitespace()
            .find(|w| w.starts_with("http://"))
            .unwrap_or_else(|| panic!("no URL in {first:?}"))
            .to_string();
        let (base, token) = url.split_once("/?token=").unwrap();
        let port = base.rsplit(':').next().unwrap().parse().unwrap();
        Console {
            rigd,
            web: Killed(web),
            base: base.to_string(),
            port,
            token: token.to_string(),
            dir,
        }
    }

    /// The URL `rigctl web` printed.
    pub fn url(&self) -> String {
        format!("{}/?token={}", self.base, self.token)
    }

    pub fn socket(&self) -> PathBuf {
        self.dir.path().join("rigd.sock")
    }

    /// `kill -9` the daemon.
    pub fn kill_rigd(&mut self) {
        self.rigd.kill_9();
    }

    /// A new daemon on the same socket and data root.
    pub fn start_rigd(&mut self) {
        let _ = std::fs::remove_file(self.socket());
        self.rigd = spawn_rigd(self.dir.path(), &[]);
    }
}

fn spawn_rigd(dir: &Path, extra: &[&str]) -> RigdProcess {
    let socket = dir.join("rigd.sock");
    let data = dir.join("data");
    let mut args: Vec<&OsStr> = vec![
        "--sim".as_ref(),
        "--socket".as_ref(),
        socket.as_os_str(),
        "--data-root".as_ref(),
        data.as_os_str(),
    ];
    args.extend(extra.iter().map(|a| OsStr::new(*a)));
    RigdProcess::spawn(&args, &socket)
}

/// One HTTP/1.1 exchange over a fresh connection: the status and the body (as text).
pub fn http(port: u16, head: &str, body: &str) -> (u16, String) {
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let req = format!(
        "{head}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    s.write_all(req.as_bytes()).unwrap();
    let mut out = Vec::new();
    let mut buf = [0u8; 65536];
    loop {
        let n = s.read(&mut buf).unwrap_or(0);
        out.extend_from_slice(&buf[..n]);
        // An upgraded WebSocket stays open and streams: its head is the whole answer.
        let switched = out.starts_with(b"HTTP/1.1 101") && out.windows(4).any(|w| w == b"\r\n\r\n");
        if n == 0 || switched {
            break;
        }
    }
    let text = String::from_utf8_lossy(&out).into_owned();
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no HTTP status in {text:?}"));
    let body = text.split_once("\r\n\r\n").map(|x| x.1).unwrap_or("");
    (status, body.to_string())
}

/// Why the browser tests cannot run here, if they cannot.
pub fn no_browser() -> Option<String> {
    [CHROMIUM, CHROMEDRIVER]
        .iter()
        .find(|p| !Path::new(p).exists())
        .map(|p| format!("{p} is absent (Debian: apt-get install chromium chromium-driver)"))
}

/// chromedriver on a free port and a headless Chromium session through it.
pub struct Browser {
    pub client: fantoccini::Client,
    _driver: Group,
    _profile: tempfile::TempDir,
}

/// A child started as the leader of its own process group; the whole group killed when
/// dropped. chromedriver's Chromium (a browser and its renderers) is in that group: killing
/// chromedriver alone leaves the browser running, a page still polling its gateway.
pub struct Group(Child);

impl Drop for Group {
    fn drop(&mut self) {
        let pgid = nix::unistd::Pid::from_raw(self.0.id() as i32);
        let _ = nix::sys::signal::killpg(pgid, nix::sys::signal::Signal::SIGKILL);
        let _ = self.0.wait();
    }
}

impl Browser {
    pub async fn start() -> Browser {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let driver = Command::new(CHROMEDRIVER)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .process_group(0)
            .spawn()
            .unwrap();
        let driver = Group(driver);
        let t = Instant::now();
        while TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(
                t.elapsed() < Duration::from_secs(20),
                "chromedriver did not start"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        let profile = tempfile::tempdir().unwrap();
        let args = [
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-dev-shm-usage",
            "--window-size=1400,1900",
        ]
        .iter()
        .map(|a| a.to_string())
        .chain([format!("--user-data-dir={}", profile.path().display())])
        .collect::<Vec<_>>();
        let mut caps = serde_json::Map::new();
        caps.insert(
            "goog:chromeOptions".into(),
            serde_json::json!({"binary": CHROMIUM, "args": args}),
        );
        let client = fantoccini::ClientBuilder::new(
            hyper_util::client::legacy::connect::HttpConnector::new(),
        )
        .capabilities(caps)
        .connect(&format!("http://127.0.0.1:{port}"))
        .await
        .expect("a Chromium session through chromedriver");
        Browser {
            client,
            _driver: driver,
            _profile: profile,
        }
    }

    /// The value of a JavaScript expression in the page.
    pub async fn js(&self, expr: &str) -> serde_json::Value {
        self.client
            .execute(&format!("return ({expr});"), vec![])
            .await
            .unwrap_or_else(|e| panic!("{expr}: {e}"))
    }

    /// Wait until `expr` is truthy in the page (at most `secs`); its value.
    pub async fn until(&self, expr: &str, secs: u64) -> serde_json::Value {
        let t = Instant::now();
        loop {
            let v = self.js(expr).await;
            let truthy = !matches!(&v, serde_json::Value::Null | serde_json::Value::Bool(false))
                && v != serde_json::json!(0)
                && v != serde_json::json!("");
            if truthy {
                return v;
            }
            if t.elapsed() > Duration::from_secs(secs) {
                let shot = self.screenshot("timeout").await;
                panic!("timed out after {secs} s waiting for `{expr}` (page: {shot})");
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Click the element with this CSS selector.
    pub async fn click(&self, css: &str) {
        self.client
            .find(fantoccini::Locator::Css(css))
            .await
            .unwrap_or_else(|e| panic!("{css}: {e}"))
            .click()
            .await
            .unwrap_or_else(|e| panic!("clicking {css}: {e}"));
    }

    /// Set an input's value.
    pub async fn set(&self, id: &str, value: &str) {
        let js = format!(
            "document.getElementById({}).value = {}; return true;",
            serde_json::json!(id),
            serde_json::json!(value)
        );
        self.client.execute(&js, vec![]).await.unwrap();
    }

    /// Save the page as target/web-console/NAME.png; its path.
    pub async fn screenshot(&self, name: &str) -> String {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("web-console");
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(format!("{name}.png"));
        match self.client.screenshot().await {
            Ok(png) => std::fs::write(&path, png).unwrap(),
            Err(e) => return format!("no screenshot: {e}"),
        }
        path.display().to_string()
    }
}
