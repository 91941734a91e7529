//! `rigctl process DIR`: the folder contract, run through the built binary on folders
//! rendered with the simulator.

use crate::support::*;
use rigd::sim::View;
use serde_json::Value;
use std::path::Path;
use std::process::{Command, Output};

fn rigctl(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .arg("process")
        .args(args)
        .output()
        .expect("rigctl runs")
}

/// `rigctl ARGS`, any subcommand.
fn rigctl_any(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(args)
        .output()
        .expect("rigctl runs")
}

fn ok_json(out: &Output) -> Value {
    assert!(
        out.status.success(),
        "rigctl failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("stdout is one JSON object")
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

const START_UM: [f64; 2] = [310.0, 150.0];

fn folder(n: usize, step_um: f64) -> tempfile::TempDir {
    let d = tempfile::tempdir().unwrap();
    write_folder(
        d.path(),
        &small_board(),
        &small_camera(),
        START_UM,
        step_um,
        n,
        7,
    );
    d
}

/// The object closest to `px` in the JSON output.
fn nearest(v: &Value, px: [f64; 2]) -> &Value {
    v["objects"]
        .as_array()
        .unwrap()
        .iter()
        .min_by(|a, b| {
            let d = |o: &Value| {
                let c = &o["centre_px"];
                (c[0].as_f64().unwrap() - px[0]).hypot(c[1].as_f64().unwrap() - px[1])
            };
            d(a).total_cmp(&d(b))
        })
        .unwrap()
}

#[test]
fn one_raw_frame_gives_centres_and_offsets_in_the_contracts_units() {
    let d = folder(1, 0.0);
    let dir = d.path().to_str().unwrap();
    let v = ok_json(&rigctl(&[dir, "--frames", "1", "--k", "1", "--json"]));
    let objs = v["objects"].as_array().unwrap();
    assert_eq!(objs.len(), 2, "{v}");
    let (board, cam) = (small_board(), small_camera());
    let view = View::at(START_UM);
    for t in &board.targets {
        let want = view.board_to_image(&cam, t.centre_um);
        let o = nearest(&v, want);
        let c = [
            o["centre_px"][0].as_f64().unwrap(),
            o["centre_px"][1].as_f64().unwrap(),
        ];
        // Measured: 0.003 px and 0.000 px (<= 0.004 px with other noise seeds); the fit's
        // σ is ~0.005 px per axis.
        assert!(
            (c[0] - want[0]).hypot(c[1] - want[1]) < 0.015,
            "{}: centre {c:?}, want {want:?}",
            t.name
        );
        let off = [
            o["offset_um"][0].as_f64().unwrap(),
            o["offset_um"][1].as_f64().unwrap(),
        ];
        // x right, y down: H's disk is right of its ring centre, V's below. The fit's σ is
        // ~3.5 µm per axis on one frame; measured errors: up to 6.2 µm (8.0 µm over seeds
        // 100-400).
        for a in 0..2 {
            assert!(
                (off[a] - t.offset_um[a]).abs() < 15.0,
                "{}: offset {off:?} µm, nominal {:?}",
                t.name,
                t.offset_um
            );
        }
    }
}

#[test]
fn averaged_job_names_targets_and_writes_16_bit_reconstructions() {
    let d = folder(6, 100.0);
    let board_file = d.path().join("small.toml");
    std::fs::write(&board_file, SMALL_BOARD).unwrap();
    let out = d.path().join("out");
    let dir = d.path().to_str().unwrap();
    let v = ok_json(&rigctl(&[
        dir,
        "--k",
        "5",
        "--estimator",
        "paper",
        "--board",
        board_file.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]));
    assert_eq!(v["frames"], 6);
    let mut names: Vec<&str> = v["objects"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| o["name"].as_str().expect("every target named"))
        .collect();
    names.sort();
    assert_eq!(names, ["H", "V"]);
    // The registration saw the camera step: 100 µm right = 0.129 px left per frame.
    let steps = v["steps"].as_array().unwrap();
    assert_eq!(steps.len(), 6);
    let last = steps[5]["image_shift_px"][0].as_f64().unwrap();
    // Measured: 0.016 px off (0.008-0.050 px over seeds 100-400).
    assert!((last + 500.0 / 774.0).abs() < 0.06, "last shift {last} px");
    // Image-registration residuals: measured up to 72 µm here
    // (up to 66 µm over seeds 100-400).
    for s in steps {
        assert!(s["residual_um"][0].as_f64().unwrap().abs() < 80.0, "{s}");
    }
    // Images: one 5x reconstruction per target, 16-bit; the result file beside them.
    let result: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("result.json")).unwrap()).unwrap();
    assert_eq!(result["objects"], v["objects"]);
    for n in ["H", "V"] {
        let img = image::open(out.join(format!("target-{n}.png"))).unwrap();
        assert_eq!(img.color(), image::ColorType::L16, "{n}");
        assert!(img.width() > 5 * 40, "{n}: {}", img.width());
    }
    assert!(
        std::fs::read_dir(&out).unwrap().all(|e| !e
            .unwrap()
            .file_name()
            .to_string_lossy()
            .ends_with(".tmp")),
        "no temporary file left"
    );
}

#[test]
fn frames_flag_uses_the_first_n_only() {
    let d = folder(3, 50.0);
    let v = ok_json(&rigctl(&[
        d.path().to_str().unwrap(),
        "--frames",
        "2",
        "--json",
    ]));
    assert_eq!(v["frames"], 2);
    assert_eq!(v["objects"][0]["frames"], 2);
}

fn assert_fails_naming(out: &Output, what: &[&str], out_dir: &Path) {
    assert!(!out.status.success(), "should fail");
    let e = stderr(out);
    for w in what {
        assert!(e.contains(w), "error should name {w:?}: {e}");
    }
    assert!(
        !out_dir.join("result.json").exists(),
        "no result on failure"
    );
}

#[test]
fn corrupt_png_is_named_and_nothing_is_written() {
    let d = folder(3, 50.0);
    std::fs::write(
        d.path().join("frames/0001.png"),
        b"\x89PNG\r\n\x1a\nnot really",
    )
    .unwrap();
    let out = d.path().join("out");
    let r = rigctl(&[
        d.path().to_str().unwrap(),
        "--k",
        "2",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_fails_naming(&r, &["0001.png", "PNG"], &out);
    assert!(!out.exists() || std::fs::read_dir(&out).unwrap().next().is_none());
}

#[test]
fn missing_frames_or_steps_are_named() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let r = rigctl(&[d.path().to_str().unwrap()]);
    assert_fails_naming(&r, &["frames"], &out);
    let d = folder(2, 50.0);
    std::fs::remove_file(d.path().join("steps.csv")).unwrap();
    let r = rigctl(&[d.path().to_str().unwrap()]);
    assert_fails_naming(&r, &["steps.csv"], &out);
}

#[test]
fn frame_of_another_size_is_named() {
    let d = folder(3, 50.0);
    image::RgbImage::from_pixel(200, 100, image::Rgb([200, 200, 200]))
        .save(d.path().join("frames/0002.png"))
        .unwrap();
    let out = d.path().join("out");
    let r = rigctl(&[d.path().to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert_fails_naming(&r, &["0002.png", "size"], &out);
}

#[test]
fn grey_png_is_refused_as_not_rgb() {
    let d = folder(2, 50.0);
    image::GrayImage::from_pixel(300, 200, image::Luma([200]))
        .save(d.path().join("frames/0001.png"))
        .unwrap();
    let r = rigctl(&[d.path().to_str().unwrap()]);
    assert_fails_naming(&r, &["0001.png", "8-bit RGB"], d.path());
}

#[test]
fn bad_steps_row_names_file_and_line() {
    let d = folder(3, 50.0);
    std::fs::write(
        d.path().join("steps.csv"),
        "index,position_um\n0,0\n1,fifty\n2,100\n",
    )
    .unwrap();
    let r = rigctl(&[d.path().to_str().unwrap()]);
    assert_fails_naming(&r, &["steps.csv", "line 3", "fifty"], d.path());
    std::fs::write(d.path().join("steps.csv"), "index,position_um\n0,0\n").unwrap();
    let r = rigctl(&[d.path().to_str().unwrap()]);
    assert_fails_naming(&r, &["steps.csv", "1 rows for 3 frames"], d.path());
}

#[test]
fn no_target_is_an_error_naming_the_frame() {
    let d = folder(2, 50.0);
    let blank = image::RgbImage::from_pixel(300, 200, image::Rgb([215, 213, 206]));
    blank.save(d.path().join("frames/0000.png")).unwrap();
    let out = d.path().join("out");
    let r = rigctl(&[d.path().to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert_fails_naming(&r, &["0000.png", "no target"], &out);
}

#[test]
fn bad_option_is_refused() {
    let d = folder(1, 0.0);
    let r = rigctl(&[d.path().to_str().unwrap(), "--k", "0"]);
    assert!(!r.status.success());
    assert!(stderr(&r).contains('k'), "{}", stderr(&r));
}

#[test]
fn options_out_of_the_pipelines_limits_are_refused_before_the_folder_is_read() {
    let missing = "/nonexistent/rigd-folder";
    let e = stderr(&rigctl(&[missing, "--k", "40"]));
    assert!(e.contains("`k` must be 1..=32, got 40"), "{e}");
    let r = rigctl(&[missing, "--axis-dir", "0,0"]);
    assert!(!r.status.success());
    let e = stderr(&r);
    assert!(
        e.contains("`axis_dir` must be a finite non-zero vector"),
        "{e}"
    );
    assert!(
        !e.contains("nonexistent"),
        "the folder is not looked at: {e}"
    );
}

/// `rigctl calibrate` and `process --calibration` refuse bad input with what and where: too few steps, no interferometer column, a
/// calibration of another frame size.
#[test]
fn calibrate_and_process_refuse_bad_input_by_name() {
    let d = tempfile::tempdir().unwrap();
    let few = d.path().join("few");
    write_folder(
        &few,
        &small_board(),
        &small_camera(),
        [310.0, 150.0],
        500.0,
        3,
        7,
    );
    let cal = d.path().join("cal.json");
    let (f, c) = (few.to_str().unwrap(), cal.to_str().unwrap());
    let out = rigctl_any(&["calibrate", f, "--scale-um-per-px", "774", "--out", c]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && !cal.exists());
    assert!(
        err.contains(f) && err.contains("3 steps: a calibration needs at least 5 frames"),
        "{err}"
    );
    let out = rigctl_any(&[
        "calibrate",
        f,
        "--scale-um-per-px",
        "774",
        "--out",
        c,
        "--registration",
        "interferometer",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("steps.csv") && err.contains("no interferometer_um column"),
        "{err}"
    );
    // A calibration of 1280x720 frames (the unit tests' synthetic scan, written by hand)
    // applied to 300x200 frames.
    let rec = serde_json::json!({
        "version": 1, "id": "cal-test", "date": "2026-12-02T19:00:00Z", "method": "commanded",
        "rig": null,
        "fingerprint": {"frame_size": [1280, 720], "scale_um_per_px": 774.0, "board": null},
        "scan": {"frames": 30, "step_um": 500.0, "travel_um": 14500.0, "piezo_travel_um": null},
        "reference_rel_u": 1e-4, "targets": [],
        "field": {"layout": "free", "model": {"centre_px": [639.5, 359.5],
            "norm_radius_px": 734.3, "a_px_per_um": [[0.001292, 0.0], [0.0, 0.001292]],
            "g_per_um": [0.0, 0.0], "k1": 0.0, "k2": 0.0},
            "covariance": vec![[0.0; 8]; 8], "parameters": [], "stage_dir_rad": 3.0,
            "print_scale": null, "residual_rms_px": 0.01, "residual_rms_um": 7.7,
            "residual_max_um": 20.0}
    });
    std::fs::write(&cal, rec.to_string()).unwrap();
    let out = rigctl_any(&["process", f, "--calibration", c]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success()
            && err
                .contains("calibration cal-test was fitted on 1280x720 frames; these are 300x200"),
        "{err}"
    );
    std::fs::write(&cal, "{\"version\": 7}").unwrap();
    let err = String::from_utf8_lossy(&rigctl_any(&["process", f, "--calibration", c]).stderr)
        .into_owned();
    assert!(
        err.contains(c) && err.contains("version 7: this rigd reads version 1"),
        "{err}"
    );
}
