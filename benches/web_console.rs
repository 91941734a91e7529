//! The browser console's goals (docs/console.md): live view in headless Chromium at ≥ 10 fps
//! with grab-to-paint latency ≤ 150 ms (median), idle and during a job; a job's step interval
//! with the page open and watching within 2 % of the same job without it; the gateway's
//! memory with 10 open tabs; a WebSocket client that never reads is dropped, not buffered.
//!
//! A real `rigd --sim` (1280x720) and `rigctl web` as child processes, Debian's Chromium
//! through chromedriver. Latency is the page's: the time the `<img>` finished loading the
//! frame minus the frame's exposure start (`t_unix_s`), so it includes the exposure, the
//! daemon's analysis and PNG, the gateway, the WebSocket and the browser's decode.
//!
//! `cargo bench --bench web_console` (figures in docs/performance.md). `WEB_BENCH_TABS_S`
//! sets how long the 10 tabs stay open (default 120 s).

#[path = "../tests/support/mod.rs"]
mod support;

use rigd::cli::client::Client;
use rigd::daemon::protocol::Request;
use std::io::{Read, Write};
use std::time::{Duration, Instant};
use support::web::{Browser, Console};

fn quantile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// The gateway's resident memory, MB.
fn rss_mb(pid: u32) -> f64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let kb: f64 = s
        .lines()
        .find(|l| l.starts_with("VmRSS:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .unwrap();
    kb / 1024.0
}

/// Frames painted a second and the page's latencies over `secs` seconds.
async fn watch(b: &Browser, secs: u64) -> (f64, Vec<f64>) {
    let f0 = b.js("rig.frames").await.as_f64().unwrap();
    let t = Instant::now();
    let mut lat = Vec::new();
    while t.elapsed() < Duration::from_secs(secs) {
        tokio::time::sleep(Duration::from_secs(2)).await;
        // The last 50 paints' latencies; every 2 s at ≤ 15 fps they do not overlap much.
        let v = b.js("rig.latencies.slice(-30)").await;
        lat.extend(v.as_array().unwrap().iter().filter_map(|x| x.as_f64()));
    }
    let f1 = b.js("rig.frames").await.as_f64().unwrap();
    ((f1 - f0) / t.elapsed().as_secs_f64(), lat)
}

/// One 40-frame job (50 µm, settle 20 ms, k = 10) through the socket; its median step
/// interval, ms, from its session's exposure times.
fn one_job(c: &Console) -> f64 {
    let mut client = Client::connect(&c.socket()).unwrap();
    support::daemon::subscribe(&mut client);
    let job = rigd::acquisition::JobSpec {
        step_um: Some(50.0),
        steps: Some(40),
        k: Some(10),
        settle_ms: 20,
        ..Default::default()
    };
    let (_, ev) = support::daemon::run_job(&mut client, job);
    let s = support::daemon::session_of(&c.dir.path().join("data"), &ev);
    let t: Vec<f64> = s.steps.iter().map(|r| r.t_unix_s).collect();
    let mut iv: Vec<f64> = t.windows(2).map(|w| (w[1] - w[0]) * 1e3).collect();
    quantile(&mut iv, 0.5)
}

async fn live_view(b: &Browser, c: &Console) {
    b.client.goto(&c.url()).await.unwrap();
    b.until("rig.frames >= 10", 30).await;
    let (fps, mut lat) = watch(b, 20).await;
    println!(
        "idle: {fps:.1} fps painted, grab to paint median {:.0} ms, p95 {:.0} ms ({} frames)",
        quantile(&mut lat, 0.5),
        quantile(&mut lat, 0.95),
        lat.len()
    );
}

async fn step_interval(b: &Browser, c: &Console) {
    let (mut without, mut with) = (Vec::new(), Vec::new());
    for _ in 0..2 {
        b.client.goto("about:blank").await.unwrap();
        without.push(tokio::task::block_in_place(|| one_job(c)));
        b.client.goto(&c.url()).await.unwrap();
        b.until("rig.frames >= 5", 30).await;
        let f0 = b.js("rig.frames").await.as_f64().unwrap();
        let t = Instant::now();
        with.push(tokio::task::block_in_place(|| one_job(c)));
        let f1 = b.js("rig.frames").await.as_f64().unwrap();
        let (mut lat, fps) = (
            b.js("rig.latencies.slice()").await,
            (f1 - f0) / t.elapsed().as_secs_f64(),
        );
        let mut lat: Vec<f64> = lat
            .as_array_mut()
            .unwrap()
            .iter()
            .filter_map(|x| x.as_f64())
            .collect();
        println!(
            "during the job: {fps:.1} fps painted, grab to paint median {:.0} ms",
            quantile(&mut lat, 0.5)
        );
    }
    let (a, b) = (quantile(&mut without, 0.5), quantile(&mut with, 0.5));
    println!(
        "step interval: {a:.1} ms without the page, {b:.1} ms with it watching ({:+.2} %; runs {without:.1?} / {with:.1?})",
        100.0 * (b - a) / a
    );
}

async fn ten_tabs(b: &Browser, c: &Console) {
    let secs: u64 = std::env::var("WEB_BENCH_TABS_S")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(120);
    let pid = c.web.0.id();
    let start = rss_mb(pid);
    for _ in 0..9 {
        let w = b.client.new_window(true).await.unwrap();
        b.client.switch_to_window(w.handle).await.unwrap();
        b.client.goto(&c.url()).await.unwrap();
    }
    let t = Instant::now();
    let mut samples = Vec::new();
    while t.elapsed() < Duration::from_secs(secs) {
        tokio::time::sleep(Duration::from_secs(10)).await;
        samples.push(rss_mb(pid));
    }
    let max = samples.iter().cloned().fold(0.0, f64::max);
    println!(
        "10 tabs for {secs} s: gateway RSS {start:.1} MB before, {:.1} MB after 10 s, {:.1} MB at the end, max {max:.1} MB",
        samples[0],
        samples[samples.len() - 1]
    );
}

/// Three WebSocket clients that never read: the gateway's memory, and whether it closed them.
fn stalled_readers(c: &Console) {
    let pid = c.web.0.id();
    let before = rss_mb(pid);
    let mut socks: Vec<std::net::TcpStream> = (0..3)
        .map(|_| {
            let mut s = std::net::TcpStream::connect(("127.0.0.1", c.port)).unwrap();
            write!(
                s,
                "GET /ws?token={} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\nConnection: Upgrade\r\nUpgrade: websocket\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\r\n",
                c.token, c.port
            )
            .unwrap();
            s
        })
        .collect();
    std::thread::sleep(Duration::from_secs(30));
    let during = rss_mb(pid);
    // Whatever the kernel buffered, then the end of the stream: the gateway dropped them.
    let mut closed = 0;
    for s in &mut socks {
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let mut sink = Vec::new();
        if s.read_to_end(&mut sink).is_ok() {
            closed += 1;
        }
    }
    println!(
        "3 WebSocket clients that never read, 30 s: gateway RSS {before:.1} -> {during:.1} MB; {closed} of 3 closed by the gateway"
    );
}

fn main() {
    if let Some(why) = support::web::no_browser() {
        println!("web_console bench: {why}");
        return;
    }
    let c = Console::start(&[]);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    let _ = Client::connect(&c.socket())
        .unwrap()
        .request(&Request::Hello {});
    println!("web console: rigd --sim (1280x720, a frame every 5 ms), rigctl web, headless Chromium; page preview 15 fps at scale 0.5");
    rt.block_on(async {
        let b = Browser::start().await;
        live_view(&b, &c).await;
        step_interval(&b, &c).await;
        ten_tabs(&b, &c).await;
    });
    stalled_readers(&c);
}
