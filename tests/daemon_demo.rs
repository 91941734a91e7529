//! `rigctl demo --json` end to end, and the guard of README's demo figures: a simulated rig
//! and daemon on a temporary socket, the calibration job and then the paper's study through
//! it, the report as JSON. 10 repeats where README's figures are of 20 (the demo's default):
//! each figure is held within 25 % of README's. The first test runs the ideal camera
//! (`--camera ideal`); the second the default, the webcam.
//!
//! A study (`cargo studies`, Cargo.toml): `cargo test` leaves it out.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use std::process::Command;

/// `rigctl demo --json ARGS --data-root DIR`'s report; the command must succeed.
fn demo_json(args: &[&str], dir: &std::path::Path) -> serde_json::Value {
    let out = Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .arg("demo")
        .arg("--json")
        .args(args)
        .arg("--data-root")
        .arg(dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn demo_json_reports_three_cases_and_averaging_beats_raw_frames() {
    let dir = tempfile::tempdir().unwrap();
    let r = demo_json(&["--camera", "ideal", "--repeats", "10"], dir.path());
    let cases = r["cases"].as_array().unwrap();
    let got: Vec<(String, u64, f64)> = cases
        .iter()
        .map(|c| {
            (
                c["name"].as_str().unwrap().to_string(),
                c["frames"].as_u64().unwrap(),
                c["step_um"].as_f64().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        got,
        vec![
            ("case1".into(), 1, 0.0),
            ("case2".into(), 10, 100.0),
            ("case3".into(), 20, 50.0)
        ]
    );
    let rms = case_figures(&r, "rms_std_um");
    // Not seeded: the simulated camera's frame clock numbers the frames, and that number
    // seeds each frame's noise, so the figures vary from run to run. Ten repeats estimate
    // each case's RMS std to a few per cent (each target's std has 9 degrees of
    // freedom, ±24 %; the RMS is over 12 targets).
    within_readme("ideal, RMS std", &rms, [(2.4, 2.4), (0.8, 0.8), (0.6, 0.6)]);
    assert_eq!(r["runs_failed"], 0, "every run was processed");
    // README: the fit's largest bias (mean - nominal) up to 1.3 µm raw, up to 2.0 µm
    // averaged, largest on F (its 5000 µm offset; the k-times reconstruction's systematic).
    // Ten repeats' means carry 0.8 / 0.25 / 0.2 µm of the scatter.
    let bias = |case: usize, target: &str| -> f64 {
        let c = &r["stats"]["cases"][case];
        let t = c["targets"].as_array().unwrap().iter();
        let t: Vec<_> = t
            .filter(|t| target.is_empty() || t["name"] == target)
            .collect();
        assert!(
            t.iter().all(|t| t["n"] == 10),
            "every repeat measures every target: {c}"
        );
        t.iter()
            .map(|t| t["bias_um"].as_f64().unwrap().abs())
            .fold(0.0, f64::max)
    };
    assert!(
        bias(0, "") < 1.3 * 1.25 + 3.0 * 0.8,
        "raw: largest |bias| {}",
        bias(0, "")
    );
    for case in [1, 2] {
        let (all, f) = (bias(case, ""), bias(case, "F"));
        assert!(
            all <= 2.0 * 1.25 && (1.0..=2.5).contains(&f),
            "case {}: largest |bias| {all:.2} µm, F's {f:.2} µm; README: up to 2.0, on F",
            case + 1
        );
    }
    let session = dir.path().join(r["session"].as_str().unwrap());
    assert!(session.join("report.json").is_file() && session.join("result.json").is_file());
}

/// The default demo: the webcam camera, calibrated first by the daemon's calibration job;
/// the study applies it and reports calibrated and global-scale figures side by side.
#[test]
fn demo_on_the_webcam_calibrates_first_and_reports_calibrated_beside_global_figures() {
    let dir = tempfile::tempdir().unwrap();
    let r = demo_json(&["--repeats", "10"], dir.path());
    assert_eq!(r["camera"], "webcam");
    let id = r["calibrated"]["id"]
        .as_str()
        .expect("a calibration was made");
    assert_eq!(r["calibration"]["applied"], true, "{}", r["calibration"]);
    assert_eq!(r["calibration"]["id"], id);
    assert_eq!(r["runs_failed"], 0);
    let record = std::path::Path::new(r["calibrated"]["path"].as_str().unwrap());
    assert!(record.starts_with(dir.path()) && record.is_file());
    for c in r["cases"].as_array().unwrap() {
        let f = |k: &str| {
            c[k].as_f64()
                .unwrap_or_else(|| panic!("{}: no {k}: {c}", c["name"]))
        };
        let (cal, global) = (f("rms_bias_um"), f("rms_bias_global_um"));
        // The global scale is a few per cent off across a tilted, distorted frame (up to
        // ~200 µm on 5 mm offsets): the calibration takes most of that bias away.
        assert!(
            cal < global,
            "{}: RMS |bias| {cal:.1} calibrated, {global:.1} global",
            c["name"]
        );
        assert!(f("rms_std_global_um") > 0.0);
    }
    // README's two runs of 20 repeats: RMS std 9.7-11.5 / 3.8 / 2.4-2.6 µm; calibrated RMS
    // bias 4.8-6.5 / 6.2-6.7 / 6.1-6.7 µm. Ten repeats leave std/√10 of scatter in each
    // target's mean (~3 µm raw), which the RMS bias carries.
    let std = case_figures(&r, "rms_std_um");
    within_readme(
        "webcam, RMS std",
        &std,
        [(9.7, 11.5), (3.8, 3.8), (2.4, 2.6)],
    );
    let bias = case_figures(&r, "rms_bias_um");
    within_readme(
        "webcam, calibrated RMS bias",
        &bias,
        [(4.8, 6.5), (6.2, 6.7), (6.1, 6.7)],
    );
}

/// `key` of each of the report's three cases.
fn case_figures(r: &serde_json::Value, key: &str) -> Vec<f64> {
    let cases = r["cases"].as_array().unwrap();
    cases.iter().map(|c| c[key].as_f64().unwrap()).collect()
}

/// Each case's figure within 25 % of README's range for it (`(low, high)`, µm).
fn within_readme(what: &str, got: &[f64], readme: [(f64, f64); 3]) {
    println!("{what}: {got:.2?} µm");
    for (c, (&g, (lo, hi))) in got.iter().zip(readme).enumerate() {
        assert!(
            g >= 0.75 * lo && g <= 1.25 * hi,
            "{what}, case {}: {g:.2} µm, README.md says {lo}-{hi} (within 25 %)",
            c + 1
        );
    }
}
