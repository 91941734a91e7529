//! `rigctl process DIR`: the folder contract, run through the built binary on folders
//! rendered with the simulator.

mod support;

use rigd::sim::View;
use serde_json::Value;
use std::path::Path;
use std::process::{Command, Output};
use support::*;

fn rigctl(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .arg("process")
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
