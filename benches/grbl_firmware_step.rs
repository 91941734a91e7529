//! The step interval of a job on GRBL 1.1h's own firmware (tests/support/firmware.rs), with
//! the sim camera: 20 frames at 100 µm (25 motor steps at the firmware's 250 steps/mm), settle
//! 50 ms, no processing. From the session's steps.csv: the median interval between frames'
//! exposures, against the same move timed on the bare protocol (`G91 G1 X0.1 F600` and
//! `G4 P0` written at once, until both `ok`s: the least any driver can take on this firmware)
//! plus the settle and the median grab. Also the move's planned time at the firmware's
//! `$110`/`$120`, and the `?` polls a second over the job, counted on the wire.
//!
//! `cargo bench --bench grbl_firmware_step` (figures in docs/performance.md). grbl-sim
//! simulates the AVR tick by tick and keeps real time only on a fast core: the bare move
//! shows how much slower than planned its clock runs here.

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
use rigd::session::Session;
use std::time::Instant;

const STEP_UM: f64 = 100.0;
const SETTLE_MS: u64 = 50;

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// The median time of ten 100 µm moves on the bare protocol, ms.
fn bare_move_ms(port: &str) -> f64 {
    let mut c = firmware::RawClient::open(port);
    while c.line(std::time::Duration::from_millis(1500)).is_some() {}
    let within = std::time::Duration::from_secs(30);
    let mut times: Vec<f64> = (0..10)
        .map(|_| {
            let t = Instant::now();
            c.send(b"G91 G1 X0.1 F600\nG4 P0\n");
            c.until(|l| l == "ok", within);
            c.until(|l| l == "ok", within);
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    // Back where the job's scan starts.
    c.send(b"G90 G0 X0\nG4 P0\n");
    c.until(|l| l == "ok", within);
    c.until(|l| l == "ok", within);
    median(&mut times)
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
    let bare_ms = bare_move_ms(&fw.port);
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
    let expected = bare_ms + SETTLE_MS as f64 + median(&mut grabs);
    let interval = median(&mut intervals);
    println!("GRBL 1.1h firmware, 20 frames at {STEP_UM} µm, settle {SETTLE_MS} ms");
    println!(
        "the move: planned {planned_ms:.1} ms; on the bare protocol {bare_ms:.1} ms \
         (the simulated clock at {:.2}x real time)",
        planned_ms / bare_ms
    );
    println!("bare move + settle + grab = {expected:.1} ms");
    println!(
        "median step interval {interval:.1} ms: {:+.1} % of that",
        100.0 * (interval - expected) / expected
    );
    println!(
        "status polls: {polls} in {secs:.1} s ({:.2} Hz)",
        polls as f64 / secs
    );
}
