//! Offline processing of recorded sessions through the built `rigctl`: `process` on a
//! study session gives the daemon's result.json run by run (the same code path), with
//! every registration; `reprocess` writes only `processed/<settings>/` inside each
//! session, reports a broken session by name while the others succeed, and indexes the
//! results, which `rigctl results` queries and `rigctl index rebuild|merge` remake.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{assert_finished, run_job, Daemon};
use rigd::acquisition::{JobSpec, PaperCase};
use rigd::daemon::protocol::Request;
use rigd::rig::simulated;
use rigd::session::Session;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// A sim rig with the small board (two targets) on 300x200 frames: targets are found.
fn daemon() -> Daemon {
    let dir = tempfile::tempdir().unwrap();
    let rig = simulated(&crate::support::daemon::small_board_sim(dir.path())).unwrap();
    Daemon::start_in(rig, dir)
}

/// Run `job` to its end; its session and the daemon's `result` reply.
fn recorded(d: &Daemon, job: JobSpec) -> (Session, Value) {
    let mut c = d.subscribed();
    let (id, ev) = run_job(&mut c, job);
    assert_finished(&ev);
    let reply = c.request(&Request::Result { job_id: id }).unwrap();
    (d.session(&ev), reply)
}

fn scan(steps: u32, label: &str) -> JobSpec {
    JobSpec {
        step_um: Some(154.8),
        steps: Some(steps),
        k: Some(5),
        settle_ms: 0,
        label: Some(label.into()),
        ..JobSpec::default()
    }
}

fn rigctl(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(args)
        .output()
        .expect("rigctl runs")
}

fn ok(out: &Output) -> String {
    assert!(
        out.status.success(),
        "rigctl failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout.clone()).unwrap()
}

fn process_json(dir: &Path, extra: &[&str]) -> Value {
    let mut args: Vec<&std::ffi::OsStr> = vec!["process".as_ref(), dir.as_os_str()];
    args.extend(extra.iter().map(std::ffi::OsStr::new));
    args.push("--json".as_ref());
    serde_json::from_str(&ok(&rigctl(&args))).unwrap()
}

/// Every offset of every run, (run, target) -> offset_um and sigma_um.
fn offsets(result: &Value) -> BTreeMap<(u64, String), Vec<f64>> {
    let mut m = BTreeMap::new();
    for r in result["runs"].as_array().unwrap() {
        for o in r["result"]["objects"].as_array().unwrap() {
            let v = [&o["offset_um"], &o["sigma_um"]]
                .iter()
                .flat_map(|p| p.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()))
                .collect();
            let key = (
                r["run"].as_u64().unwrap(),
                o["name"].as_str().unwrap().into(),
            );
            m.insert(key, v);
        }
    }
    m
}

/// A study session (three cases, two repeats: six runs) processed offline gives one result
/// per run, each the daemon's to float tolerance, and the same study; `--registration`
/// overrides the recorded one with the commanded positions or the interferometer readings.
#[test]
fn process_on_a_study_session_gives_the_daemons_result_run_by_run() {
    let d = daemon();
    let job = JobSpec {
        study: Some(PaperCase::ALL.to_vec()),
        repeats: 2,
        settle_ms: 0,
        ..JobSpec::default()
    };
    let (s, reply) = recorded(&d, job);
    let daemon_result = &reply["result"];
    let offline = process_json(&s.dir, &[]);
    let runs = offline["runs"].as_array().unwrap();
    assert_eq!(runs.len(), 6, "one result per run, never one merged scan");
    let cases: Vec<(&str, u64, u64)> = runs
        .iter()
        .map(|r| {
            let frames = r["result"]["frames"].as_u64().unwrap();
            (
                r["case"].as_str().unwrap(),
                r["k"].as_u64().unwrap(),
                frames,
            )
        })
        .collect();
    assert_eq!(
        cases,
        [("case1", 1, 1), ("case2", 5, 10), ("case3", 10, 20)].repeat(2)
    );
    let (a, b) = (offsets(daemon_result), offsets(&offline));
    assert_eq!(a.len(), 12, "two targets in six runs: {a:?}");
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (key, want) in &a {
        for (x, y) in want.iter().zip(&b[key]) {
            assert!(
                (x - y).abs() <= 1e-9 * x.abs().max(1.0),
                "{key:?}: {want:?} vs {:?}",
                b[key]
            );
        }
    }
    // The board's names (from the manifest) and the study's tables.
    assert_eq!(offline["study"]["cases"], daemon_result["study"]["cases"]);

    // Registration by the commanded positions / the interferometer's readings.
    let used = |v: &Value, run: usize| -> Vec<f64> {
        v["runs"][run]["result"]["steps"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["position_um"].as_f64().unwrap())
            .collect()
    };
    let case3: Vec<_> = s.steps.iter().filter(|r| r.run == 2).collect();
    let commanded = process_json(&s.dir, &["--registration", "commanded"]);
    let want: Vec<f64> = case3.iter().map(|r| r.position_um).collect();
    assert_eq!(used(&commanded, 2), want);
    let laser = process_json(&s.dir, &["--registration", "interferometer"]);
    let want: Vec<f64> = case3.iter().map(|r| r.interferometer_um.unwrap()).collect();
    assert_eq!(used(&laser, 2), want);
    assert_ne!(used(&laser, 2), used(&commanded, 2));
    assert_eq!(
        laser["runs"][2]["result"]["options"]["registration"],
        "positions"
    );
    // k beyond the pipeline's K_RANGE is refused naming the range the daemon uses.
    let out = rigctl(&[
        "process".as_ref(),
        s.dir.as_os_str(),
        "--k".as_ref(),
        "33".as_ref(),
    ]);
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && e.contains("1..=32"), "{e}");
}

/// `--k` on a session whose runs average per-frame fits (`combine = mean`) would change
/// nothing: it is refused, saying what to add; with `--combine interp` it reconstructs.
#[test]
fn k_on_a_session_combined_by_mean_is_refused_saying_what_would_use_it() {
    let d = daemon();
    let job = JobSpec {
        combine: Some(rigd::pipeline::Combine::Mean),
        ..scan(4, "mean")
    };
    let (s, _) = recorded(&d, job);
    let out = rigctl(&[
        "process".as_ref(),
        s.dir.as_os_str(),
        "--k".as_ref(),
        "3".as_ref(),
    ]);
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{e}");
    assert!(
        e.contains("--k 3 changes nothing") && e.contains("--combine interp"),
        "{e}"
    );
    let v = process_json(&s.dir, &["--k", "3", "--combine", "interp"]);
    assert_eq!(v["runs"][0]["result"]["options"]["k"], 3, "{v}");
}

/// Every file below `dir`, by its path relative to `dir`, with its bytes.
fn files(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if e.file_type().unwrap().is_dir() {
                todo.push(p);
            } else {
                let bytes = std::fs::read(&p).unwrap();
                out.insert(p.strip_prefix(dir).unwrap().to_path_buf(), bytes);
            }
        }
    }
    out
}

fn csv_rows(text: &str) -> Vec<BTreeMap<String, String>> {
    let mut r = csv::Reader::from_reader(text.as_bytes());
    let head: Vec<String> = r.headers().unwrap().iter().map(String::from).collect();
    r.records()
        .map(|rec| {
            head.iter()
                .cloned()
                .zip(rec.unwrap().iter().map(String::from))
                .collect()
        })
        .collect()
}

/// `reprocess` of three sessions writes `processed/<settings>/result.json` (and its
/// settings and images) in each and changes nothing else; a broken fourth is reported by
/// name, the others succeed, the exit code says one failed. The index then answers
/// `rigctl results` by label, target, settings and date; a rebuild from the files and a
/// merge of per-task indexes give the same rows.
#[test]
fn reprocess_writes_only_processed_settings_and_reports_a_broken_session() {
    let d = daemon();
    let sessions: Vec<(Session, Value)> = [("a", 4), ("a", 5), ("b", 4)]
        .iter()
        .map(|&(label, n)| recorded(&d, scan(n, label)))
        .collect();
    let (broken, _) = recorded(&d, scan(3, "b"));
    // A frame cut short: the session cannot be processed.
    let f1 = broken.frame_path(1);
    let bytes = std::fs::read(&f1).unwrap();
    std::fs::write(&f1, &bytes[..bytes.len() / 2]).unwrap();
    let before: Vec<_> = sessions.iter().map(|(s, _)| files(&s.dir)).collect();
    let broken_before = files(&broken.dir);

    let mut args: Vec<&std::ffi::OsStr> = vec!["reprocess".as_ref()];
    args.extend(sessions.iter().map(|(s, _)| s.dir.as_os_str()));
    args.push(broken.dir.as_os_str());
    args.extend(["--k", "3", "--estimator", "fit", "--threads", "2"].map(std::ffi::OsStr::new));
    let out = rigctl(&args);
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(!out.status.success(), "a failed session fails the command");
    let broken_name = broken.dir.display().to_string();
    assert!(
        stderr.contains(&format!("{broken_name}: failed")) && stderr.contains("000001.png"),
        "{stderr}"
    );
    assert!(
        stdout.contains("3 sessions reprocessed as fit-k3, 1 failed"),
        "{stdout}"
    );
    for ((s, reply), old) in sessions.iter().zip(&before) {
        let now = files(&s.dir);
        let added: Vec<&PathBuf> = now.keys().filter(|p| !old.contains_key(*p)).collect();
        assert!(
            added.iter().all(|p| p.starts_with("processed/fit-k3")),
            "{added:?}"
        );
        for p in ["result.json", "settings.json", "results.csv"] {
            assert!(
                added.contains(&&Path::new("processed/fit-k3").join(p)),
                "{added:?}"
            );
        }
        for (p, bytes) in old {
            assert!(now.get(p) == Some(bytes), "{} changed", p.display());
        }
        let r: Value =
            serde_json::from_slice(&now[Path::new("processed/fit-k3/result.json")]).unwrap();
        assert_eq!(r["runs"][0]["k"], 3);
        assert_eq!(r["runs"][0]["result"]["options"]["k"], 3);
        assert_eq!(
            r["runs"][0]["result"]["objects"].as_array().unwrap().len(),
            2
        );
        assert_ne!(
            r["runs"], reply["result"]["runs"],
            "k = 3, not the recorded 5"
        );
        // results.csv: a row per target of the run, its offsets those of result.json.
        let csv =
            String::from_utf8(now[Path::new("processed/fit-k3/results.csv")].clone()).unwrap();
        let rows: Vec<&str> = csv.lines().skip(1).collect();
        assert_eq!(rows.len(), 2, "{csv}");
        let dx: f64 = rows[0].split(',').nth(4).unwrap().parse().unwrap();
        let want = r["runs"][0]["result"]["objects"][0]["offset_um"][0]
            .as_f64()
            .unwrap();
        assert_eq!(dx, want, "{csv}");
        let st: Value =
            serde_json::from_slice(&now[Path::new("processed/fit-k3/settings.json")]).unwrap();
        assert_eq!(
            st["overrides"],
            serde_json::json!({"k": 3, "estimator": "fit"})
        );
    }
    let after = files(&broken.dir);
    assert!(
        after
            .keys()
            .all(|p| broken_before.contains_key(p) || p.starts_with("processed")),
        "{:?}",
        after.keys()
    );
    assert!(!after
        .keys()
        .any(|p| p.ends_with("result.json") && p.starts_with("processed")));

    // The index: the daemon's rows (settings `recorded`) and reprocess's (`fit-k3`).
    let root = d.data.clone();
    let results = |extra: &[&str]| -> Vec<BTreeMap<String, String>> {
        let mut args: Vec<&std::ffi::OsStr> =
            vec!["results".as_ref(), "--data-root".as_ref(), root.as_os_str()];
        args.extend(extra.iter().map(std::ffi::OsStr::new));
        csv_rows(&ok(&rigctl(&args)))
    };
    let all = results(&[]);
    assert_eq!(
        all.len(),
        2 * 4 + 3 * 2,
        "4 recorded sessions and 3 reprocessed, 2 targets each"
    );
    let k3 = results(&["--settings", "fit-k3"]);
    assert_eq!(k3.len(), 6);
    let a = results(&["--label", "a", "--settings", "fit-k3", "--target", "H"]);
    assert_eq!(a.len(), 2);
    let first = &a[0];
    let name = sessions[0].0.manifest.name.clone();
    let r: Value = serde_json::from_slice(
        &std::fs::read(sessions[0].0.dir.join("processed/fit-k3/result.json")).unwrap(),
    )
    .unwrap();
    let h = r["runs"][0]["result"]["objects"]
        .as_array()
        .unwrap()
        .iter()
        .find(|o| o["name"] == "H")
        .unwrap();
    let row = a.iter().find(|r| r["session"] == name).unwrap_or(first);
    assert_eq!(
        row["dx_um"].parse::<f64>().unwrap(),
        h["offset_um"][0].as_f64().unwrap()
    );
    assert_eq!((row["label"].as_str(), row["case"].as_str()), ("a", "scan"));
    assert!(results(&["--since", "2999-01-01"]).is_empty());
    assert_eq!(results(&["--since", "2000-01-01"]).len(), all.len());

    // Rebuilt from the files: the same rows. Merged from two per-task indexes: the same.
    let rebuilt = root.join("rebuilt.sqlite");
    ok(&rigctl(&[
        "index".as_ref(),
        "rebuild".as_ref(),
        "--data-root".as_ref(),
        root.as_os_str(),
        "--into".as_ref(),
        rebuilt.as_os_str(),
    ]));
    let from = |index: &Path, extra: &[&str]| {
        let mut args: Vec<&std::ffi::OsStr> =
            vec!["results".as_ref(), "--index".as_ref(), index.as_os_str()];
        args.extend(extra.iter().map(std::ffi::OsStr::new));
        csv_rows(&ok(&rigctl(&args)))
    };
    assert_eq!(from(&rebuilt, &[]), all);
    let tasks: Vec<PathBuf> = (0..2)
        .map(|i| root.join(format!("task{i}.sqlite")))
        .collect();
    for (i, t) in tasks.iter().enumerate() {
        let mut args: Vec<&std::ffi::OsStr> = vec!["reprocess".as_ref()];
        args.extend(
            sessions
                .iter()
                .skip(i)
                .step_by(2)
                .map(|(s, _)| s.dir.as_os_str()),
        );
        args.extend(["--k", "3", "--estimator", "fit", "--index"].map(std::ffi::OsStr::new));
        args.push(t.as_os_str());
        ok(&rigctl(&args));
    }
    let merged = root.join("merged.sqlite");
    let mut args: Vec<&std::ffi::OsStr> = vec!["index".as_ref(), "merge".as_ref()];
    args.extend(tasks.iter().map(|t| t.as_os_str()));
    args.extend(["--into".as_ref(), merged.as_os_str()]);
    ok(&rigctl(&args));
    assert_eq!(from(&merged, &[]), k3);
}

/// A calibration record written by hand for the sessions' 300x200 frames: no tilt or
/// distortion, `um_per_px` everywhere, a commanded reference of 1e-4. Its layout is a
/// board's, whose print fixes the perspective, so a conversion carries no gauge allowance.
fn hand_calibration(id: &str, um_per_px: f64) -> serde_json::Value {
    let a = 1.0 / um_per_px;
    serde_json::json!({
        "version": 1, "id": id, "date": "2026-12-02T19:00:00Z", "method": "commanded",
        "rig": null,
        "fingerprint": {"frame_size": [300, 200], "scale_um_per_px": 774.0, "board": null},
        "scan": {"frames": 30, "step_um": 500.0, "travel_um": 14500.0, "piezo_travel_um": null},
        "reference_rel_u": 1e-4, "targets": [],
        "field": {"layout": "board", "model": {"centre_px": [149.5, 99.5],
            "norm_radius_px": 180.3, "a_px_per_um": [[a, 0.0], [0.0, a]],
            "g_per_um": [0.0, 0.0], "k1": 0.0, "k2": 0.0},
            "covariance": vec![[0.0; 8]; 8], "parameters": [], "stage_dir_rad": 3.0,
            "print_scale": null, "residual_rms_px": 0.01, "residual_rms_um": 7.7,
            "residual_max_um": 20.0}
    })
}

/// `--calibration` on a session: every run is converted through it and names it. The
/// calibration here is written by hand for the session's 300x200 frames: no tilt or
/// distortion, 1 % finer than the rig's 774 µm/px, so every offset is 1 % smaller than the
/// global scale's and its type-B uncertainty is the reference's alone.
#[test]
fn process_on_a_session_applies_a_calibration_run_by_run() {
    let d = daemon();
    let (s, _) = recorded(&d, scan(5, "cal"));
    let tmp = tempfile::tempdir().unwrap();
    let cal = tmp.path().join("cal.json");
    let rec = hand_calibration("cal-hand", 0.99 * 774.0);
    std::fs::write(&cal, rec.to_string()).unwrap();
    let v = process_json(&s.dir, &["--calibration", cal.to_str().unwrap()]);
    let runs = v["runs"].as_array().unwrap();
    assert!(!runs.is_empty());
    for r in runs {
        let res = &r["result"];
        assert_eq!(res["calibration"]["id"], "cal-hand", "{r}");
        assert!(
            res["calibration"].get("ink_prior").is_none(),
            "no ink learnt: {r}"
        );
        for o in res["objects"].as_array().unwrap() {
            let g = |k: &str, a: usize| o[k][a].as_f64().unwrap();
            for a in 0..2 {
                // The apparent-centre correction of a parallel board and a plain lens is 0.
                let want = 0.99 * g("offset_global_um", a);
                assert!((g("offset_um", a) - want).abs() < 1e-6, "{o}");
                // u_b: the reference's 1e-4 of the offset, and the ink model's when the
                // fit freed the contrast planes.
                let ink = o["u_ink_um"][a].as_f64().unwrap_or(0.0);
                let ub = (1e-4 * g("offset_um", a)).hypot(ink);
                assert!((g("u_b_um", a) - ub).abs() < 1e-6 + 1e-3 * ub, "{o}");
            }
        }
    }
}

/// A calibration that learnt the print's ink takes it into every run of a session as the
/// fit's prior (the result names it, and its posterior widens u_a on this even print);
/// `--no-calibration-ink` declines it.
#[test]
fn a_sessions_runs_take_the_ink_the_calibration_learnt_unless_declined() {
    let d = daemon();
    let (s, _) = recorded(&d, scan(3, "ink"));
    let tmp = tempfile::tempdir().unwrap();
    let cal = tmp.path().join("cal.json");
    let mut rec = hand_calibration("cal-ink", 774.0);
    rec["ink"] = serde_json::json!({"density_rms": 0.04, "u_density_rms": 0.002,
        "corr_um": 3000.0, "u_corr_um": 90.0, "observed_rms": 0.038, "observed_corr_px": 3.8,
        "blur_px": 0.7, "shapes": 24, "cells": 2500});
    std::fs::write(&cal, rec.to_string()).unwrap();
    let c = cal.to_str().unwrap();
    let taken = process_json(&s.dir, &["--calibration", c]);
    let declined = process_json(&s.dir, &["--calibration", c, "--no-calibration-ink"]);
    for (t, n) in taken["runs"]
        .as_array()
        .unwrap()
        .iter()
        .zip(declined["runs"].as_array().unwrap())
    {
        let (t, n) = (&t["result"], &n["result"]);
        let prior = &t["calibration"]["ink_prior"];
        assert_eq!(
            (prior["density_rms"].as_f64(), prior["corr_um"].as_f64()),
            (Some(0.04), Some(3000.0))
        );
        assert!(n["calibration"].get("ink_prior").is_none(), "{n}");
        // The same frames measured with the prior and without: its MAP moves the offsets
        // (measured 1.1–2.9 µm RMS on this even print), and its posterior, whose density
        // modes stay unknown, is wider than the frames' scatter (u_a summed over the
        // targets 8.8–8.9 µm with it, 1.7–5.9 µm without: 3 frames scatter a lot).
        let objects = |r: &serde_json::Value| r["objects"].as_array().unwrap().clone();
        let (ot, on) = (objects(t), objects(n));
        assert!(!ot.is_empty() && ot.len() == on.len());
        let f = |o: &serde_json::Value, k: &str, a: usize| o[k][a].as_f64().unwrap();
        let moved = ot.iter().zip(&on).flat_map(|(a, b)| {
            (0..2).map(move |i| (f(a, "offset_um", i) - f(b, "offset_um", i)).powi(2))
        });
        let moved = (moved.sum::<f64>() / (2 * ot.len()) as f64).sqrt();
        let u = |os: &[serde_json::Value]| os.iter().map(|o| f(o, "u_a_um", 0)).sum::<f64>();
        let (ut, un) = (u(&ot), u(&on));
        println!("offsets moved {moved:.2} µm RMS; u_a {ut:.2} with the prior, {un:.2} without");
        assert!(
            moved > 0.5,
            "the prior moved the offsets by {moved:.3} µm RMS"
        );
        assert!(ut > un, "u_a with the prior {ut:.2}, without {un:.2}");
    }
}
