//! `rigctl hw` end to end: the real binary, a config file, and the simulated hardware (the
//! GRBL emulator on a pseudo-terminal through the real serialport path; the sim camera).

#![cfg(feature = "sim")] // the simulated rig (default feature)

use rigd::sim::grbl::{GrblSim, GrblSimOptions};
use rigd::sim::motion::{Axis, AxisParams};
use std::path::Path;
use std::process::Command;
use std::sync::Arc;
use std::time::{Duration, Instant};

fn rigctl(config: &Path, args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .arg("hw")
        .arg("--config")
        .arg(config)
        .args(args)
        .output()
        .expect("run rigctl");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// A small sim camera (fast to render) and the paper's board.
const SIM_CAMERA: &str = r#"
[camera]
driver = "sim"
frame_timeout_ms = 5000
[camera.sim]
width = 160
height = 96
scale_um_per_px = 6000.0
supersample = 2
"#;

fn write_config(dir: &Path, text: &str) -> std::path::PathBuf {
    let p = dir.join("rigd.toml");
    // No daemon here: point the socket and the device locks into the temp dir.
    let text = format!(
        "{text}\n[daemon]\nsocket = \"{}\"\nlock_dir = \"{}\"\n",
        dir.join("rigd.sock").display(),
        dir.join("locks").display()
    );
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn grab_writes_a_png_from_the_sim_camera() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_config(dir.path(), SIM_CAMERA);
    let out = dir.path().join("frame.png");
    let (ok, stdout, stderr) = rigctl(&cfg, &["grab", out.to_str().unwrap()]);
    assert!(ok, "stdout: {stdout}\nstderr: {stderr}");
    assert!(stdout.contains("160x96"), "{stdout}");
    let img = image::open(&out).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (160, 96));
    // The board is in view: red ink and white paper, not a blank frame.
    let reddish = img
        .pixels()
        .filter(|p| p[0] > p[1].saturating_add(60))
        .count();
    let whitish = img.pixels().filter(|p| p[1] > 150).count();
    assert!(
        reddish > 20 && whitish > 1000,
        "red {reddish}, white {whitish}"
    );
}

#[test]
fn move_and_position_against_the_grbl_emulator() {
    let axis = Arc::new(Axis::new(AxisParams {
        position_error_rms_um: 0.0,
        ..AxisParams::default()
    }));
    let sim = GrblSim::spawn(
        Arc::clone(&axis),
        GrblSimOptions {
            boot_delay: Duration::from_millis(50),
            ..GrblSimOptions::default()
        },
        None,
    )
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_config(
        dir.path(),
        &format!(
            "[axis]\ndriver = \"grbl\"\nport = \"{}\"\nsoft_min_um = 0.0\nsoft_max_um = 10000.0\nmax_step_um = 2000.0\nmove_timeout_ms = 10000\n",
            sim.path().display()
        ),
    );
    let (ok, stdout, stderr) = rigctl(&cfg, &["move-rel", "1500"]);
    assert!(ok, "stdout: {stdout}\nstderr: {stderr}");
    assert!(stdout.contains("-> 1500.000 µm"), "{stdout}");
    // The emulator's axis really went there.
    assert!((axis.position_at(Instant::now()) - 1500.0).abs() < 1e-6);
    let (ok, stdout, stderr) = rigctl(&cfg, &["move-abs", "500"]);
    assert!(ok, "stdout: {stdout}\nstderr: {stderr}");
    assert!((axis.position_at(Instant::now()) - 500.0).abs() < 1e-6);
    let (ok, stdout, _) = rigctl(&cfg, &["position"]);
    assert!(ok);
    assert!(stdout.contains("idle at 500.000 µm"), "{stdout}");
    // Beyond the soft limits: refused before anything moves.
    let (ok, _, stderr) = rigctl(&cfg, &["move-abs", "-100"]);
    assert!(!ok);
    assert!(stderr.contains("-100"), "{stderr}");
    let (ok, _, stderr) = rigctl(&cfg, &["move-rel", "5000"]);
    assert!(!ok);
    assert!(stderr.to_lowercase().contains("step"), "{stderr}");
    assert!((axis.position_at(Instant::now()) - 500.0).abs() < 1e-6);
}

#[test]
fn probe_reports_every_section() {
    let dir = tempfile::tempdir().unwrap();
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/xl80/steps.rtx");
    let cfg = write_config(
        dir.path(),
        &format!(
            "[axis]\ndriver = \"sim\"\nsoft_min_um = 0.0\nsoft_max_um = 1000.0\nmax_step_um = 100.0\n{SIM_CAMERA}\n[xl80]\npath = \"{}\"\nformat = \"rtx\"\n",
            fixture.display()
        ),
    );
    let (ok, stdout, stderr) = rigctl(&cfg, &["probe"]);
    assert!(ok, "stdout: {stdout}\nstderr: {stderr}");
    assert!(stdout.contains("axis    ok"), "{stdout}");
    assert!(
        stdout.contains("piezo   -       no [piezo] section"),
        "{stdout}"
    );
    assert!(
        stdout.contains("camera  ok") && stdout.contains("160x96"),
        "{stdout}"
    );
    assert!(
        stdout.contains("xl80    ok") && stdout.contains("320 readings"),
        "{stdout}"
    );
    let (ok, stdout, _) = rigctl(&cfg, &["xl80"]);
    assert!(ok);
    assert!(
        stdout.contains("at 50 Hz") && stdout.contains("axis: X"),
        "{stdout}"
    );
}

#[test]
fn probe_fails_when_a_device_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_config(
        dir.path(),
        "[axis]\ndriver = \"grbl\"\nport = \"/dev/nonexistent-tty\"\nsoft_min_um = 0.0\nsoft_max_um = 1000.0\nmax_step_um = 100.0\n",
    );
    let (ok, stdout, stderr) = rigctl(&cfg, &["probe"]);
    assert!(!ok);
    assert!(
        stdout.contains("axis    FAILED") && stdout.contains("/dev/nonexistent-tty"),
        "{stdout}"
    );
    assert!(stderr.contains("1 failed: axis"), "{stderr}");
}

#[test]
fn bad_config_and_running_daemon_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_config(dir.path(), "[axis]\ndriver = \"grbl\"\nspeed = 3\n");
    let (ok, _, stderr) = rigctl(&cfg, &["position"]);
    assert!(!ok);
    assert!(
        stderr.contains("rigd.toml") && stderr.contains("speed"),
        "{stderr}"
    );
    // A daemon holds the axis port's lock (this test process stands in for it): refused
    // before the port is opened, naming the holder.
    let port = "/dev/nonexistent-tty-rigctl-hw";
    let cfg = write_config(
        dir.path(),
        &format!("[axis]\ndriver = \"grbl\"\nport = \"{port}\"\nsoft_min_um = 0.0\nsoft_max_um = 1.0\nmax_step_um = 1.0\n"),
    );
    let locks = dir.path().join("locks");
    std::fs::create_dir_all(&locks).unwrap();
    let me = rigd::lock::Holder::me("rigd", Some(&dir.path().join("rigd.sock")), None);
    let lock = rigd::lock::device_lock_path(&locks, Path::new(port));
    let _held = rigd::lock::LockFile::acquire(&lock, "port", &me, "").unwrap();
    let (ok, _, stderr) = rigctl(&cfg, &["position"]);
    assert!(!ok);
    let pid = std::process::id();
    assert!(
        stderr.contains(&format!("[axis] port {port} is held by rigd (pid {pid}")),
        "{stderr}"
    );
    // Commands that open no serial port take no port lock: the XL-80 summary still runs.
    let (_, _, stderr) = rigctl(&cfg, &["xl80"]);
    assert!(!stderr.contains("is held by"), "{stderr}");
}

#[test]
fn piezo_moves_over_gcs() {
    use rigd::sim::gcs::{GcsSim, GcsSimOptions};
    let piezo = Arc::new(Axis::new(rigd::sim::rig::default_piezo()));
    let sim = GcsSim::spawn(Arc::clone(&piezo), GcsSimOptions::default(), None).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_config(
        dir.path(),
        &format!(
            "[piezo]\ndriver = \"gcs\"\nport = \"{}\"\nsoft_min_um = 0.0\nsoft_max_um = 100.0\nmax_step_um = 100.0\n",
            sim.path().display()
        ),
    );
    let (ok, stdout, stderr) = rigctl(&cfg, &["--piezo", "move-abs", "42.5"]);
    assert!(ok, "stdout: {stdout}\nstderr: {stderr}");
    assert!(stdout.starts_with("piezo: "), "{stdout}");
    // The flexure's closed loop is good to ~0.01 µm.
    assert!((piezo.position_at(Instant::now()) - 42.5).abs() < 0.1);
    // No [axis] section: the axis commands say so.
    let (ok, _, stderr) = rigctl(&cfg, &["position"]);
    assert!(!ok);
    assert!(stderr.contains("no [axis] section"), "{stderr}");
}

#[test]
fn sim_rig_camera_sees_the_axis_move() {
    use rigd::hw::{Camera, Stage};
    let dir = tempfile::tempdir().unwrap();
    let cfg = write_config(
        dir.path(),
        &format!("[axis]\ndriver = \"sim\"\nsoft_min_um = 0.0\nsoft_max_um = 100000.0\nmax_step_um = 100000.0\n{SIM_CAMERA}"),
    );
    let cfg = rigd::config::Config::load(cfg).unwrap();
    let mut hw = rigd::rig::sim::open_sim_rig(&cfg).unwrap();
    assert_eq!(hw.camera.size(), (160, 96));
    let t = Duration::from_secs(5);
    // Horizontal shift between two frames: the integer lag that best aligns their column
    // profiles of the green channel (the red ink is darkest in green).
    let profile = |img: &image::RgbImage| -> Vec<f64> {
        (0..img.width())
            .map(|x| {
                (0..img.height())
                    .map(|y| f64::from(img.get_pixel(x, y)[1]))
                    .sum()
            })
            .collect()
    };
    let shift = |a: &image::RgbImage, b: &image::RgbImage| -> i32 {
        let (pa, pb) = (profile(a), profile(b));
        let n = pa.len() as i32;
        (-20..=20)
            .min_by(|&l1, &l2| {
                let ssd = |lag: i32| {
                    let pairs: Vec<f64> = (20..n - 20)
                        .map(|x| pb[x as usize] - pa[(x - lag) as usize])
                        .collect();
                    pairs.iter().map(|d| d * d).sum::<f64>() / pairs.len() as f64
                };
                ssd(l1).total_cmp(&ssd(l2))
            })
            .unwrap()
    };
    let a = hw
        .camera
        .grab_fresh(std::time::SystemTime::now(), t)
        .unwrap();
    let b = hw
        .camera
        .grab_fresh(std::time::SystemTime::now(), t)
        .unwrap();
    // 10 px at 6000 µm/px.
    hw.axis.move_rel(60_000.0).unwrap();
    hw.axis.wait_settled(t).unwrap();
    let c = hw
        .camera
        .grab_fresh(std::time::SystemTime::now(), t)
        .unwrap();
    assert_eq!(shift(&a.image, &b.image), 0, "still frames");
    // The camera rides the axis: the scene moves 10 px the other way.
    assert_eq!(shift(&b.image, &c.image).abs(), 10, "after the move");
    // Soft limits come from [axis].
    assert!(hw.axis.move_abs(200_000.0).is_err());
}
