//! `rigd --config FILE`: the daemon's rig built from a config's sections through `rig::from_config`.
//! With every driver "sim" the stages and the camera are one `SimRig`, so a job's frames and
//! interferometer readings follow the axis.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{
    assert_finished, capture_job, config, fast_grbl, run_job, subscribe, Daemon, RigdProcess,
    SIM_RIG_SMALL,
};
use rigd::acquisition::{JobSpec, StageKind};
use rigd::daemon::protocol::Request;
use rigd::rig::from_config;
use rigd::session::SessionState;
use std::time::Instant;

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

#[test]
fn a_sim_config_runs_a_job_whose_interferometer_follows_the_axis() {
    let dir = tempfile::tempdir().unwrap();
    let rig = from_config(&config(dir.path(), SIM_RIG)).unwrap();
    assert_eq!(rig.info.mode, rigd::rig::RigMode::Sim);
    assert_eq!(rig.info.axis_limits_um, [0.0, 100_000.0]);
    assert_eq!(rig.info.frame_size, (64, 48));
    assert!(rig.piezo.is_none(), "no [piezo] section: no piezo");
    let d = Daemon::start_in(rig, dir);
    let mut c = d.subscribed();
    let job = JobSpec {
        start_um: Some(2_000.0),
        step_um: Some(500.0),
        steps: Some(4),
        process: false,
        ..JobSpec::default()
    };
    let (_, ev) = run_job(&mut c, job);
    let s = d.session(&ev);
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
    let Err(e) = from_config(&config(dir.path(), text)) else {
        panic!("a rig without a camera was built")
    };
    assert!(e.to_string().contains("[camera]"), "{e}");
}

/// A hardware rig: the axis is a GRBL controller (the emulator on a pseudo-terminal, driven
/// over the real serialport path) and the camera a separate one. Its scan start and image
/// direction come from the config, and a job without `start_um` starts there.
#[test]
fn a_hardware_rig_takes_its_scan_start_and_axis_direction_from_the_config() {
    let (axis, grbl) = fast_grbl();
    let dir = tempfile::tempdir().unwrap();
    let text = format!(
        "[axis]\ndriver = \"grbl\"\nport = \"{}\"\nsoft_min_um = -2000.0\nsoft_max_um = 100000.0\n\
         max_step_um = 100000.0\nfeed_um_s = 50000.0\ndefault_start_um = 7250.0\n\
         [camera]\ndriver = \"sim\"\n[camera.sim]\nwidth = 48\nheight = 32\nsupersample = 2\n\
         frame_period_ms = 2.0\nexposure_ms = 1.0\n\
         [pipeline]\naxis_dir = [0.0, -1.0]\n",
        grbl.path().display()
    );
    let rig = from_config(&config(dir.path(), &text)).unwrap();
    assert_eq!(rig.info.mode, rigd::rig::RigMode::Hardware);
    assert_eq!(rig.info.default_start_um, 7_250.0);
    assert_eq!(rig.info.axis_dir, [0.0, -1.0]);
    // What a plan checks a job's moves against: the section's limits and step, no settle.
    let bounds = rig.info.bounds(StageKind::Axis).unwrap();
    assert_eq!(bounds.limits_um, [-2_000.0, 100_000.0]);
    assert_eq!(
        (bounds.max_step_um, bounds.settle_ms),
        (Some(100_000.0), None)
    );
    assert!(rig.info.bounds(StageKind::Piezo).is_none(), "no [piezo]");
    let d = Daemon::start_in(rig, dir);
    let mut c = d.client();
    let hello = c.request(&Request::Hello {}).unwrap();
    assert_eq!(hello["rig"]["default_start_um"], 7_250.0);
    subscribe(&mut c);
    let job = capture_job(100.0, 2, 0);
    let (_, ev) = run_job(&mut c, job);
    assert_finished(&ev);
    let s = d.session(&ev);
    let commanded: Vec<f64> = s.steps.iter().map(|r| r.position_um).collect();
    assert_eq!(commanded, vec![7_250.0, 7_350.0]);
    assert_eq!(s.manifest.rig.axis_dir, [0.0, -1.0]);
    // The controller really took the axis there.
    assert!((axis.position_at(Instant::now()) - 7_350.0).abs() < 1e-6);
}

/// `rigd --config FILE` reads FILE once for its rig and its `[daemon]` settings, under the
/// command line's: a file without a `[daemon]` table is fine when the command line says where.
#[test]
fn rigd_takes_its_socket_and_data_root_from_the_command_line_over_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, socket, data) = (
        dir.path().join("rig.toml"),
        dir.path().join("cli.sock"),
        dir.path().join("cli-data"),
    );
    std::fs::write(&cfg, SIM_RIG_SMALL).unwrap();
    let args = [
        "--config".as_ref(),
        cfg.as_os_str(),
        "--socket".as_ref(),
        socket.as_os_str(),
        "--data-root".as_ref(),
        data.as_os_str(),
    ];
    let _rigd = RigdProcess::spawn(&args, &socket);
    let hello = rigd::cli::client::Client::connect(&socket)
        .unwrap()
        .request(&Request::Hello {})
        .unwrap();
    assert_eq!(hello["rig"]["mode"], "sim");
    assert_eq!(hello["data_root"], data.display().to_string());
}

/// `rigctl hw` honours the device locks rigd holds with the same config (`[daemon]
/// lock_dir`), and names the daemon: its pid and `[daemon] socket`.
#[test]
fn rigctl_hw_refuses_while_rigd_holds_the_configs_port() {
    let dir = tempfile::tempdir().unwrap();
    let (_axis, grbl) = fast_grbl();
    let (cfg, socket, data) = (
        dir.path().join("rig.toml"),
        dir.path().join("file.sock"),
        dir.path().join("data"),
    );
    // SIM_RIG_SMALL's camera with the emulator as a GRBL axis.
    let camera = &SIM_RIG_SMALL[SIM_RIG_SMALL.find("[camera]").unwrap()..];
    let text = format!(
        "[axis]\ndriver = \"grbl\"\nport = \"{}\"\nsoft_min_um = 0.0\nsoft_max_um = 1000.0\n\
         max_step_um = 1000.0\n{camera}[daemon]\nsocket = \"{}\"\nlock_dir = \"{}\"\n",
        grbl.path().display(),
        socket.display(),
        dir.path().join("locks").display()
    );
    std::fs::write(&cfg, text).unwrap();
    let args = [
        "--config".as_ref(),
        cfg.as_os_str(),
        "--data-root".as_ref(),
        data.as_os_str(),
    ];
    let rigd = RigdProcess::spawn(&args, &socket);
    let pid = rigd.0.as_ref().unwrap().id();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(["hw", "--config"])
        .arg(&cfg)
        .arg("position")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    let held = format!("is held by rigd (pid {pid}, socket {}", socket.display());
    assert!(stderr.contains(&held), "{stderr}");
}
