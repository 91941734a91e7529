//! The interferometer log end to end: the simulated XL-80 writes its log live, the daemon
//! follows the file (the hardware path), the session records the samples covering the job,
//! each frame's reading comes from them, and replay gives the recorded readings back.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{
    assert_finished, capture_job, run_job, run_request, submit, subscribe, Daemon, RigdProcess,
};
use rigd::acquisition::{JobRegistration, JobSpec, Processing};
use rigd::cli::client::Client;
use rigd::config::Config;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::rig::from_config;
use rigd::rig::LogSample;
use rigd::rig::{simulated, SimSettings};
use rigd::session::{Session, SessionState, INTERFEROMETER_HEADER};
use rigd::sim::grbl::{GrblSim, GrblSimOptions};
use rigd::sim::motion::AxisParams;
use rigd::sim::xl80::{LiveOptions, LogFormat};
use rigd::sim::{CameraModel, SimRig, SimRigConfig};
use std::path::Path;
use std::sync::Arc;

/// The sim XL-80's reading noise (Xl80Params::default), µm RMS.
const NOISE_UM: f64 = 0.2;

/// A small fast `rigd --sim` rig looking at the small two-target board.
fn sim_settings(dir: &Path) -> SimSettings {
    crate::support::daemon::small_board_sim(dir)
}

/// The reading at `t`, linear between the recorded samples around it (written here again,
/// independently of the daemon's).
fn reading_at(samples: &[LogSample], t: f64) -> f64 {
    let i = samples
        .iter()
        .position(|s| s.t_unix_s >= t)
        .unwrap_or_else(|| panic!("no sample at or after {t}"));
    assert!(i > 0, "no sample before {t}");
    let (a, b) = (samples[i - 1], samples[i]);
    a.position_um + (t - a.t_unix_s) / (b.t_unix_s - a.t_unix_s) * (b.position_um - a.position_um)
}

/// Checks every session with a log must pass: the file, its header, its clock, and each
/// frame's reading read from it. Returns the samples.
fn check_log(s: &Session, rate_hz: f64) -> Vec<LogSample> {
    let text = std::fs::read_to_string(s.dir.join("interferometer.csv")).unwrap();
    assert!(text.starts_with(INTERFEROMETER_HEADER), "{text:.80}");
    let samples = s.interferometer_samples().unwrap();
    assert!(samples.len() > 5, "{} samples", samples.len());
    let dts: Vec<f64> = samples
        .windows(2)
        .map(|w| w[1].t_unix_s - w[0].t_unix_s)
        .collect();
    if let Some(i) = dts.iter().position(|&d| d <= 0.0) {
        let around = &samples[i.saturating_sub(2)..(i + 3).min(samples.len())];
        panic!(
            "sample times must increase: at sample {i} of {}: {around:?}",
            samples.len()
        );
    }
    let period = 1.0 / rate_hz;
    let mean_dt = dts.iter().sum::<f64>() / dts.len() as f64;
    assert!(
        (mean_dt - period).abs() < 0.01 * period,
        "{mean_dt} s apart"
    );
    // The samples cover the job: from its start to past its last frame.
    assert!(samples[0].t_unix_s >= s.manifest.created_unix_s - 0.5);
    assert!(samples[0].t_unix_s <= s.steps[0].t_unix_s);
    for r in &s.steps {
        let x = r.interferometer_um.expect("every frame has a reading");
        let want = reading_at(&samples, r.t_unix_s);
        assert!(
            (x - want).abs() < 1e-6,
            "frame {}: {x} vs log {want}",
            r.index
        );
    }
    samples
}

/// Pooled standard deviation of the samples in the last `window_s` before each frame (the
/// axis is settled there): the interferometer's noise.
fn settled_noise_um(samples: &[LogSample], s: &Session, window_s: f64) -> f64 {
    let (mut ss, mut dof) = (0.0, 0usize);
    for r in &s.steps {
        let v: Vec<f64> = samples
            .iter()
            .filter(|x| x.t_unix_s <= r.t_unix_s && x.t_unix_s > r.t_unix_s - window_s)
            .map(|x| x.position_um)
            .collect();
        if v.len() < 2 {
            continue;
        }
        let m = v.iter().sum::<f64>() / v.len() as f64;
        ss += v.iter().map(|x| (x - m).powi(2)).sum::<f64>();
        dof += v.len() - 1;
    }
    assert!(dof >= 10, "too few settled samples ({dof} dof)");
    (ss / dof as f64).sqrt()
}

#[test]
fn a_sim_job_records_the_live_log_and_reads_each_frame_from_it() {
    let dir = tempfile::tempdir().unwrap();
    let settings = sim_settings(dir.path());
    let d = Daemon::start_in(simulated(&settings).unwrap(), dir);
    let mut c = d.subscribed();
    let job = capture_job(100.0, 8, 60);
    let (_, ev) = run_job(&mut c, job);
    let s = d.session(&ev);
    assert_eq!(s.manifest.state, SessionState::Finished);
    // The manifest names the source log and its facts.
    let src = s.manifest.interferometer.as_ref().expect("a log source");
    assert_eq!(src.format, "csv");
    assert_eq!(src.um_per_unit, Some(1000.0), "the sim's CSV is in mm");
    assert_eq!(src.sample_rate_hz, Some(1000.0));
    assert!(
        src.date.is_some() && src.path.contains("rigd-sim-xl80"),
        "{src:?}"
    );
    assert!(src.fields.iter().any(|(k, _)| k == "Serial No"), "{src:?}");
    // The sim dates its capture on a whole second: the log clock is the PC's, and the
    // estimate says so (less the writer's delay of a few ms).
    assert!(src.clock.starts_with("estimated"), "{src:?}");
    assert!((-0.03..=0.001).contains(&src.log_minus_pc_s), "{src:?}");
    let samples = check_log(&s, 1000.0);
    // Events carry the same reading as steps.csv.
    let from_events: Vec<Option<f64>> = ev
        .iter()
        .filter_map(|e| match e {
            EventBody::Step {
                interferometer_um, ..
            } => Some(*interferometer_um),
            _ => None,
        })
        .collect();
    assert_eq!(from_events.len(), s.steps.len());
    for (e, r) in from_events.iter().zip(&s.steps) {
        // JSON numbers come back within an ulp or two (serde_json's default float parsing).
        assert!((e.unwrap() - r.interferometer_um.unwrap()).abs() < 1e-9);
    }
    // The laser sees the axis' true position: within its positioning error (2 µm RMS) of
    // where the controller says it is, but not exactly there.
    let d_um: Vec<f64> = s
        .steps
        .iter()
        .map(|r| r.interferometer_um.unwrap() - r.axis_um)
        .collect();
    assert!(d_um.iter().all(|d| d.abs() < 10.0), "{d_um:?}");
    let rms = (d_um.iter().map(|d| d * d).sum::<f64>() / d_um.len() as f64).sqrt();
    assert!(
        rms > 0.5,
        "interferometer = axis ({rms} µm RMS): not measured"
    );
    // While the axis is settled the log scatters by the XL-80's noise.
    let noise = settled_noise_um(&samples, &s, 0.05);
    assert!(
        (0.5 * NOISE_UM..1.6 * NOISE_UM).contains(&noise),
        "settled noise {noise} µm"
    );
}

#[test]
fn registration_interferometer_uses_the_readings_and_replays_the_same() {
    let dir = tempfile::tempdir().unwrap();
    let settings = sim_settings(dir.path());
    let d = Daemon::start_in(simulated(&settings).unwrap(), dir);
    let mut c = d.subscribed();
    let job = JobSpec {
        step_um: Some(154.8),
        steps: Some(5),
        k: Some(5),
        settle_ms: 30,
        registration: Some(JobRegistration::Interferometer),
        ..JobSpec::default()
    };
    let (live, ev) = run_job(&mut c, job);
    assert_finished(&ev);
    let live_s = d.session(&ev);
    let live_log = check_log(&live_s, 1000.0);
    let result = |c: &mut Client, id| c.request(&Request::Result { job_id: id }).unwrap();
    let a = result(&mut c, live);
    let objects = &a["result"]["runs"][0]["result"]["objects"];
    assert!(
        objects.as_array().is_some_and(|o| o.len() == 2),
        "both targets measured: {a}"
    );

    // Replay: the recorded readings, the same result, the recorded log carried over.
    let replay = |c: &mut Client, registration| {
        run_request(
            c,
            &Request::Replay {
                session: live_s.manifest.name.clone(),
                processing: Processing {
                    registration,
                    ..Processing::default()
                },
            },
        )
    };
    let (rid, rev) = replay(&mut c, None);
    let rs = d.session(&rev);
    assert_eq!(
        rs.manifest.job.registration,
        Some(JobRegistration::Interferometer)
    );
    let ifm =
        |s: &Session| -> Vec<Option<f64>> { s.steps.iter().map(|r| r.interferometer_um).collect() };
    assert_eq!(ifm(&rs), ifm(&live_s));
    assert_eq!(result(&mut c, rid)["result"]["runs"], a["result"]["runs"]);
    let src = rs.manifest.interferometer.as_ref().unwrap();
    assert_eq!(
        src.replayed_from.as_deref(),
        Some(live_s.manifest.name.as_str())
    );
    let replay_log = rs.interferometer_samples().unwrap();
    assert!(!replay_log.is_empty() && replay_log.len() <= live_log.len());
    assert_eq!(replay_log[..], live_log[..replay_log.len()]);

    // The pipeline registered the frames by the readings: its per-step positions are the
    // interferometer's, and a replay registered by the commanded positions gets those.
    let used = |r: &serde_json::Value| -> Vec<f64> {
        r["result"]["runs"][0]["result"]["steps"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["position_um"].as_f64().unwrap())
            .collect()
    };
    for (u, r) in used(&a).iter().zip(&live_s.steps) {
        assert!(
            (u - r.interferometer_um.unwrap()).abs() < 1e-9,
            "{u} vs {r:?}"
        );
    }
    let (cid, _) = replay(&mut c, Some(JobRegistration::Commanded));
    let commanded: Vec<f64> = live_s.steps.iter().map(|r| r.position_um).collect();
    assert_eq!(used(&result(&mut c, cid)), commanded);
    assert_ne!(used(&a), commanded, "the readings equal the commands");
}

/// The hardware path: GRBL over a pty, and `[xl80]` pointing at a log the sim's XL-80
/// writes live, as the laser software would (RTX, flushed ten times a second, dated on the
/// whole second before its start: the log clock lags the PC's by the start's fraction of a
/// second, which the daemon must estimate to put the readings at the frames).
#[test]
fn a_config_rig_follows_an_rtx_log_written_live() {
    let dir = tempfile::tempdir().unwrap();
    let mut sim = SimRig::start(SimRigConfig {
        axis: AxisParams {
            max_speed_um_s: 50_000.0,
            accel_um_s2: 2_000_000.0,
            position_error_rms_um: 0.0,
            ..AxisParams::default()
        },
        camera: CameraModel {
            width: 32,
            height: 24,
            supersample: 1,
            ..CameraModel::default()
        },
        ..SimRigConfig::default()
    })
    .unwrap();
    let grbl = GrblSim::spawn(Arc::clone(&sim.axis), GrblSimOptions::default(), None).unwrap();
    let log = dir.path().join("capture.rtx");
    sim.start_xl80_log_with(&log, LogFormat::Rtx, LiveOptions::default())
        .unwrap();
    let text = format!(
        r#"
[axis]
driver = "grbl"
port = "{port}"
soft_min_um = 0.0
soft_max_um = 100000.0
max_step_um = 100000.0
feed_um_s = 50000.0
[camera]
driver = "sim"
frame_timeout_ms = 5000
[camera.sim]
width = 32
height = 24
supersample = 1
frame_period_ms = 2.0
exposure_ms = 1.0
[xl80]
path = "capture.rtx"
format = "rtx"
rtx_unit = "mm"
poll_ms = 5
"#,
        port = grbl.path().display()
    );
    let cfg = Config::from_toml_str(&text, &dir.path().join("rig.toml")).unwrap();
    let rig = from_config(&cfg).unwrap();
    assert_eq!(rig.info.mode, rigd::rig::RigMode::Hardware);
    let d = Daemon::start(rig);
    let mut c = d.subscribed();
    let job = JobSpec {
        start_um: Some(2_000.0),
        step_um: Some(250.0),
        steps: Some(5),
        settle_ms: 50,
        process: false,
        ..JobSpec::default()
    };
    let (_, ev) = run_job(&mut c, job);
    let s = d.session(&ev);
    assert_eq!(s.manifest.state, SessionState::Finished, "{:?}", s.manifest);
    let src = s.manifest.interferometer.as_ref().unwrap();
    assert_eq!(
        (src.format.as_str(), src.um_per_unit),
        ("rtx", Some(1000.0))
    );
    assert!(src.path.ends_with("capture.rtx"), "{src:?}");
    assert_eq!(src.sample_rate_hz, Some(100.0));
    let samples = check_log(&s, 100.0);
    // No positioning error here: the reading is the commanded position within the noise.
    for r in &s.steps {
        let x = r.interferometer_um.unwrap();
        assert!(
            (x - r.position_um).abs() < 5.0 * NOISE_UM,
            "frame {}: {x} vs {}",
            r.index,
            r.position_um
        );
    }
    let noise = settled_noise_um(&samples, &s, 0.04);
    assert!((0.5 * NOISE_UM..1.6 * NOISE_UM).contains(&noise), "{noise}");
    drop(d);
    let started = sim.finish_xl80_log().unwrap().unwrap().started_sys;
    let frac = started
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .subsec_nanos() as f64
        * 1e-9;
    assert!(src.clock.starts_with("estimated"), "{src:?}");
    let est = src.log_minus_pc_s;
    assert!(
        (est + frac).abs() < 0.03 && est < -frac + 0.002,
        "log clock - PC clock estimated {est} s, true {}",
        -frac
    );
}

#[test]
fn kill_9_keeps_the_log_of_every_reported_frame() {
    let dir = tempfile::tempdir().unwrap();
    let (socket, data) = (dir.path().join("s.sock"), dir.path().join("data"));
    let mut child = RigdProcess::spawn_sim(&socket, &data);
    let mut c = Client::connect(&socket).unwrap();
    subscribe(&mut c);
    let job = capture_job(50.0, 400, 0);
    submit(&mut c, job);
    let (mut name, mut reported) = (String::new(), Vec::new());
    while reported.len() < 4 {
        match c.next_event().unwrap().body {
            EventBody::Started { session, .. } => name = session,
            EventBody::Step {
                index,
                interferometer_um,
                ..
            } => reported.push((index, interferometer_um.expect("a reading"))),
            other => assert!(!other.is_terminal(), "{other:?}"),
        }
    }
    child.kill_9();
    let s = Session::open(&data.join(&name)).unwrap();
    assert_eq!(s.manifest.state, SessionState::Running);
    // Every reported frame's reading can be read again from the samples on disk.
    let samples = s.interferometer_samples().unwrap();
    for (index, x) in reported {
        let r = &s.steps[index as usize];
        assert!(
            (r.interferometer_um.unwrap() - x).abs() < 1e-9,
            "{r:?} vs {x}"
        );
        let want = reading_at(&samples, r.t_unix_s);
        assert!((x - want).abs() < 1e-6, "frame {index}: {x} vs {want}");
    }
}
