//! SimRig from a TOML config: the axis and the piezo both move what the camera sees, and the
//! rig's live XL-80 log records the motion.

mod common;
use common::*;
use rigd_sim::xl80::LogFormat;
use rigd_sim::{Board, SimRig, SimRigConfig};
use std::time::{Duration, Instant};

const TIMEOUT: Duration = Duration::from_secs(5);

#[test]
fn axis_and_piezo_move_the_image_and_the_log_follows() {
    let board = Board::paper();
    let cam = quiet(small_cam());
    let origin = origin_centring(&board, &cam, "A");
    let text = format!(
        "seed = 3\norigin_um = [{}, {}]\n[camera]\n{}\n[axis]\nposition_error_rms_um = 0.0\n[xl80]\nnoise_rms_um = 0.0\nsample_rate_hz = 200.0\n",
        origin[0],
        origin[1],
        toml::to_string(&cam).unwrap()
    );
    let cfg = SimRigConfig::parse(&text, "test.toml").unwrap();
    let mut rig = SimRig::start(cfg).unwrap();
    let dir = tempfile::tempdir().unwrap();
    rig.start_xl80_log(dir.path().join("log.csv"), LogFormat::Csv)
        .unwrap();
    let paper = board.paper_rgb[1] * cam.white_dn;
    let c0 = ink_centroid(
        &rig.camera
            .fresh_frame(Instant::now(), TIMEOUT)
            .unwrap()
            .image,
        paper,
    );

    // The piezo: 77.4 µm is a tenth of a pixel.
    let d = rig.piezo.command_move(77.4).unwrap();
    let f = rig.camera.fresh_frame(Instant::now() + d, TIMEOUT).unwrap();
    let c1 = ink_centroid(&f.image, paper);
    assert!(
        (c1[0] - c0[0] + 0.1).abs() < 0.01,
        "piezo moved the image {} px",
        c1[0] - c0[0]
    );
    assert!((c1[1] - c0[1]).abs() < 0.005);

    // The axis: 1548 µm, two pixels more.
    let d = rig.axis.command_move(1548.0).unwrap();
    let f = rig.camera.fresh_frame(Instant::now() + d, TIMEOUT).unwrap();
    let c2 = ink_centroid(&f.image, paper);
    assert!(
        (c2[0] - c0[0] + 2.1).abs() < 0.01,
        "axis + piezo moved {} px",
        c2[0] - c0[0]
    );
    assert!(
        (f.mean_los_um[0] - 1625.4).abs() < 0.1,
        "{:?}",
        f.mean_los_um
    );

    let log = rig.finish_xl80_log().unwrap().expect("a log was running");
    assert!(log.samples > 10);
    let text = std::fs::read_to_string(&log.path).unwrap();
    let last = text.trim_end().lines().last().unwrap();
    let mm: f64 = last.split(',').nth(2).unwrap().parse().unwrap();
    assert!(
        (mm - 1.6254).abs() < 5e-5,
        "the log ends at axis + piezo: {mm} mm"
    );
    assert!(rig.finish_xl80_log().unwrap().is_none());
}

#[test]
fn a_bad_config_is_an_error_naming_the_field() {
    let e = SimRigConfig::parse("[camera]\nwidht = 3\n", "rig.toml")
        .unwrap_err()
        .to_string();
    assert!(e.contains("rig.toml") && e.contains("widht"), "{e}");
    let cfg = SimRigConfig::parse("[camera]\nsupersample = 0\n", "rig.toml").unwrap();
    let e = SimRig::start(cfg).err().unwrap().to_string();
    assert!(e.contains("supersample"), "{e}");
}
