//! `rigctl demo --json` end to end: a simulated rig and daemon on a temporary socket, the
//! paper's study through it (3 repeats here, 93 full 1280x720 frames: ~10 s), the report
//! as JSON.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use std::process::Command;

#[test]
fn demo_json_reports_three_cases_and_averaging_beats_raw_frames() {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(["demo", "--json", "--repeats", "3", "--data-root"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
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
    let rms: Vec<f64> = cases
        .iter()
        .map(|c| c["rms_std_um"].as_f64().unwrap())
        .collect();
    assert!(rms[2] < rms[0] && rms[1] < rms[0], "{rms:?}");
    let session = dir.path().join(r["session"].as_str().unwrap());
    assert!(session.join("report.json").is_file() && session.join("result.json").is_file());
}
