//! `rigd --config FILE`: the daemon's rig built from a config's sections through `hw::open`.
//! With every driver "sim" the stages and the camera are one `SimRig`, so a job's frames and
//! interferometer readings follow the axis.

use rigd::cli::client::Client;
use rigd::config::Config;
use rigd::daemon::hwrig::rig_from_config;
use rigd::daemon::protocol::{EventBody, JobSpec, Request};
use rigd::daemon::server::Background;
use rigd::daemon::session::{Session, SessionState};
use rigd::daemon::DaemonSettings;
use std::path::Path;

const SIM_RIG: &str = r#"
[axis]
driver = "sim"
soft_min_um = 0.0
soft_max_um = 100000.0
max_step_um = 100000.0
[axis.sim]
max_speed_um_s = 50000.0
accel_um_s2 = 2000000.0
position_error_rms_um = 2.0
hard_min_um = -5000.0
hard_max_um = 300000.0
seed = 1
[camera]
driver = "sim"
frame_timeout_ms = 5000
[camera.sim]
width = 64
height = 48
scale_um_per_px = 6000.0
supersample = 2
frame_period_ms = 2.0
exposure_ms = 1.0
"#;

fn config(dir: &Path, text: &str) -> Config {
    Config::from_toml_str(text, &dir.join("rig.toml")).unwrap()
}

#[test]
fn a_sim_config_runs_a_job_whose_interferometer_follows_the_axis() {
    let dir = tempfile::tempdir().unwrap();
    let rig = rig_from_config(&config(dir.path(), SIM_RIG)).unwrap();
    assert_eq!(rig.info.mode, "sim");
    assert_eq!(rig.info.axis_limits_um, [0.0, 100_000.0]);
    assert_eq!(rig.info.frame_size, (64, 48));
    assert!(rig.piezo.is_none(), "no [piezo] section: no piezo");
    let data = dir.path().join("data");
    let settings = DaemonSettings {
        socket: dir.path().join("rigd.sock"),
        group: None,
        data_root: data.clone(),
    };
    let bg = Background::start(settings, rig).unwrap();
    let mut c = Client::connect(&bg.socket).unwrap();
    c.request(&Request::Subscribe { job_id: None }).unwrap();
    let job = JobSpec {
        start_um: Some(2_000.0),
        step_um: Some(500.0),
        steps: Some(4),
        process: false,
        ..JobSpec::default()
    };
    let id = c.request(&Request::Submit { job }).unwrap()["job_id"]
        .as_u64()
        .unwrap();
    let mut session = None;
    loop {
        let e = c.next_event().unwrap();
        if e.job_id != id {
            continue;
        }
        if let EventBody::Started { session: s, .. } = &e.body {
            session = Some(s.clone());
        }
        if e.body.is_terminal() {
            break;
        }
    }
    let s = Session::open(&data.join(session.unwrap())).unwrap();
    assert_eq!(s.manifest.state, SessionState::Finished, "{:?}", s.manifest);
    assert_eq!(s.steps.len(), 4);
    for (i, st) in s.steps.iter().enumerate() {
        let want = 2_000.0 + 500.0 * i as f64;
        assert_eq!(st.position_um, want);
        // The axis' positioning error is 2 µm RMS: the true position is within 5 sigma.
        let ifm = st.interferometer_um.expect("an interferometer reading");
        assert!((ifm - want).abs() < 10.0, "step {i}: {ifm} vs {want}");
    }
}

#[test]
fn a_config_without_a_camera_is_refused_naming_the_section() {
    let dir = tempfile::tempdir().unwrap();
    let text = SIM_RIG.split("[camera]").next().unwrap();
    let Err(e) = rig_from_config(&config(dir.path(), text)) else {
        panic!("a rig without a camera was built")
    };
    assert!(e.to_string().contains("[camera]"), "{e}");
}
