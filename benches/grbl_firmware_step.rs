//! The step interval of a job on GRBL 1.1h's own firmware (tests/support/firmware.rs), with
//! the sim camera: 20 frames at 100 µm (25 motor steps at the firmware's 250 steps/mm), settle
//! 50 ms, no processing. From the session's steps.csv: the median interval between frames'
//! exposures against the move's planned time at the firmware's `$110`/`$120`, plus the settle
//! and the median grab. Also the `?` polls a second over the job, counted on the wire.
//!
//! `cargo bench --bench grbl_firmware_step` (figures in docs/performance.md). The firmware's
//! simulated clock keeps real time only on a quiet machine.

#[path = "../tests/support/firmware.rs"]
#[allow(dead_code)]
mod firmware;
#[path = "support/job.rs"]
#[allow(dead_code)]
mod job;
#[path = "../tests/support/skip.rs"]
mod skip;

use rigd::acquisition::JobSpec;
use rigd::cli::client::Client;
use rigd::config::{Config, DaemonSettings};
use rigd::daemon::protocol::Request;
use rigd::daemon::server::Background;
use rigd::daemon::session::Session;
use std::time::Instant;

const STEP_UM: f64 = 100.0;
const SETTLE_MS: u64 = 50;

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn rig_toml(port: &str) -> String {
    format!(
        "[axis]\ndriver = \"grbl\"\nport = \"{port}\"\nsoft_min_um = -50000.0\n\
         soft_max_um = 50000.0\nmax_step_um = 50000.0\ndefault_start_um = 0.0\n\
         [camera]\ndriver = \"sim\"\n[camera.sim]\nwidth = 48\nheight = 32\nsupersample = 1\n\
         frame_period_ms = 2.0\nexposure_ms = 1.0\n"
    )
}

fn main() {
    let Some(fw) = firmware::Firmware::start("grbl_firmware_step") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::from_toml_str(&rig_toml(&fw.port), &dir.path().join("rig.toml")).unwrap();
    let rig = rigd::rig::from_config(&cfg).unwrap();
    let machine = rig.info.axis_machine.clone().expect("$$ read at connect");
    let data = dir.path().join("data");
    let settings = DaemonSettings {
        socket: dir.path().join("rigd.sock"),
        group: None,
        data_root: data.clone(),
        ..DaemonSettings::default()
    };
    let _bg = Background::start(settings, rig).unwrap();
    let mut c = Client::connect(&dir.path().join("rigd.sock")).unwrap();
    c.request(&Request::Subscribe { job_id: None }).unwrap();
    let polls_before = fw.sent().iter().filter(|&&b| b == b'?').count();
    let t0 = Instant::now();
    let job = JobSpec {
        step_um: Some(STEP_UM),
        steps: Some(20),
        settle_ms: SETTLE_MS,
        process: false,
        ..JobSpec::default()
    };
    let id = c.request(&Request::Submit { job }).unwrap()["job_id"]
        .as_u64()
        .unwrap();
    let session = job::finished(&mut c, id);
    let secs = t0.elapsed().as_secs_f64();
    let polls = fw.sent().iter().filter(|&&b| b == b'?').count() - polls_before;
    let s = Session::open(&data.join(session)).unwrap();
    let mut intervals: Vec<f64> = s
        .steps
        .windows(2)
        .map(|w| (w[1].t_unix_s - w[0].t_unix_s) * 1e3)
        .collect();
    let mut grabs: Vec<f64> = s.steps.iter().skip(1).map(|r| r.grab_ms).collect();
    let planned_ms = machine.move_time(STEP_UM, 10_000.0).as_secs_f64() * 1e3;
    let expected = planned_ms + SETTLE_MS as f64 + median(&mut grabs);
    let interval = median(&mut intervals);
    println!("GRBL 1.1h firmware, 20 frames at {STEP_UM} µm, settle {SETTLE_MS} ms");
    println!("planned move {planned_ms:.1} ms + settle + grab = {expected:.1} ms");
    println!(
        "median step interval {interval:.1} ms: {:+.1} % of that",
        100.0 * (interval - expected) / expected
    );
    println!(
        "status polls: {polls} in {secs:.1} s ({:.2} Hz)",
        polls as f64 / secs
    );
}
