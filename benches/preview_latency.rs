//! The live view's goal: grab-to-client latency at most one frame period on the
//! sim at 30 fps while a job runs, and the job's step interval unchanged within 2 %.
//!
//! `rigd --sim`'s rig with its camera at 30 fps (1280x720, exposure 10 ms); jobs of 40
//! frames at 50 µm, settle 20 ms, processed at k = 10, alternately with no live view and
//! with a client following `preview` at 30 fps (scale 0.5). Per job: the median interval
//! between the frames' exposure times (the session's steps.csv). Per preview event of the
//! job's frames: the client's receive time minus the frame's exposure end (exposure start
//! `t_unix_s` + exposure): grab to client, detection, rendering, PNG and the socket
//! included.
//!
//! `cargo bench --bench preview_latency` (figures in docs/performance.md).

#[path = "support/job.rs"]
mod support;

use rigd::cli::client::Client;
use rigd::config::DaemonSettings;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::daemon::server::Background;
use rigd::rig::{simulated, SimSettings};
use rigd::sim::CameraModel;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

const PAIRS: usize = 3;
const PERIOD_MS: f64 = 1000.0 / 30.0;
const EXPOSURE_MS: f64 = 10.0;

fn quantile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[((v.len() - 1) as f64 * q).round() as usize]
}

fn now_s() -> f64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64()
}

/// One job; its median step interval, ms, and its id.
fn one_job(c: &mut Client, data: &Path) -> (f64, u64) {
    let (id, _, mut iv) = support::forty_frames(c, data);
    (quantile(&mut iv, 0.5), id)
}

/// Follow `preview` at 30 fps until `stop`: (job id, latency ms) of every event.
fn viewer(socket: &Path, stop: Arc<AtomicBool>, out: Arc<Mutex<Vec<(u64, f64)>>>) {
    let mut c = Client::connect(socket).unwrap();
    c.request(&Request::Preview {
        max_fps: 30.0,
        scale: Some(0.5),
        crop: None,
    })
    .unwrap();
    while !stop.load(Ordering::SeqCst) {
        let e = c.next_event().unwrap();
        let t = now_s();
        if let EventBody::Preview(f) = e.body {
            let ms = (t - f.t_unix_s) * 1e3 - EXPOSURE_MS;
            out.lock().unwrap().push((e.job_id, ms));
        }
    }
}

fn main() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let socket = dir.path().join("rigd.sock");
    let settings = DaemonSettings {
        socket: socket.clone(),
        group: None,
        data_root: data.clone(),
        ..DaemonSettings::default()
    };
    let sim = SimSettings::default();
    let rig = simulated(&SimSettings {
        camera: CameraModel {
            frame_period_ms: PERIOD_MS,
            exposure_ms: EXPOSURE_MS,
            ..sim.camera.clone()
        },
        ..sim
    })
    .unwrap();
    let _bg = Background::start(settings, rig).unwrap();
    let mut c = Client::connect(&socket).unwrap();
    c.request(&Request::Subscribe { job_id: None }).unwrap();
    println!("preview latency, rigd --sim rig at 30 fps (1280x720), 40 frames at 50 µm, settle 20 ms, k = 10");
    println!("pair  interval_ms (no view)  interval_ms (preview 30 fps)  change_%");
    let (mut plain, mut viewed, mut lat) = (Vec::new(), Vec::new(), Vec::new());
    for p in 0..PAIRS {
        let (a, _) = one_job(&mut c, &data);
        let stop = Arc::new(AtomicBool::new(false));
        let got = Arc::new(Mutex::new(Vec::new()));
        let v = {
            let (s, stop, got) = (socket.clone(), stop.clone(), got.clone());
            std::thread::spawn(move || viewer(&s, stop, got))
        };
        let (b, id) = one_job(&mut c, &data);
        stop.store(true, Ordering::SeqCst);
        v.join().unwrap();
        lat.extend(
            got.lock()
                .unwrap()
                .iter()
                .filter(|(j, _)| *j == id)
                .map(|(_, ms)| *ms),
        );
        println!("{p:>4}  {a:>21.1}  {b:>28.1}  {:>8.2}", 100.0 * (b - a) / a);
        plain.push(a);
        viewed.push(b);
    }
    let (a, b) = (quantile(&mut plain, 0.5), quantile(&mut viewed, 0.5));
    println!(
        "median step interval: {a:.1} ms without, {b:.1} ms with the preview ({:+.2} %)",
        100.0 * (b - a) / a
    );
    let n = lat.len();
    println!(
        "grab-to-client latency over {n} preview events of the jobs' frames: median {:.1} ms, p95 {:.1} ms, max {:.1} ms (frame period {PERIOD_MS:.1} ms)",
        quantile(&mut lat, 0.5),
        quantile(&mut lat, 0.95),
        quantile(&mut lat, 1.0)
    );
}
