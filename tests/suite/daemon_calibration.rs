//! The daemon's calibration job over its real socket, on the simulated rig. The
//! job scans, fits (the code path of `rigctl calibrate DIR`) and keeps the record in the
//! data root as the current calibration; the next job applies it and names it in its
//! events, manifest and result; a stale or mismatched record warns, a corrupt one fails the
//! job naming the file while the daemon keeps serving.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{
    assert_finished, events_until_end, job_id, run_job, session_of, small_board_sim, submit, Daemon,
};
use crate::support::schema::{closed, errors, validator};
use rigd::acquisition::calibration_job::CalibrationScan;
use rigd::acquisition::JobSpec;
use rigd::calibration_note::CalibrationNote;
use rigd::calibration_store;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::rig::simulated;
use serde_json::Value;
use std::path::Path;

/// The calibration note of a job's `calibration` event.
fn note(events: &[EventBody]) -> CalibrationNote {
    events
        .iter()
        .find_map(|e| match e {
            EventBody::Calibration(n) => Some(n.clone()),
            _ => None,
        })
        .unwrap_or_else(|| panic!("no calibration event: {events:?}"))
}

/// A measurement job: 3 frames 100 µm apart, each target's mean offset.
fn measure() -> JobSpec {
    JobSpec {
        step_um: Some(100.0),
        steps: Some(3),
        k: Some(1),
        settle_ms: 0,
        ..JobSpec::default()
    }
}

fn result(d: &Daemon, id: u64) -> Value {
    d.client().request(&Request::Result { job_id: id }).unwrap()["result"].clone()
}

/// `result.json` validates against the protocol schema's `JobResult`, closed: every field,
/// the calibration's and the uncertainty's among them, is in the schema.
fn typed_as_the_schema_says(result: &Value) {
    let doc = closed(&rigd::daemon::schema::document());
    let e = errors(&validator(&doc, "JobResult"), result);
    assert!(e.is_empty(), "{e:?}");
}

#[test]
fn a_calibration_job_is_kept_in_the_data_root_and_applied_by_the_next_job() {
    let d = Daemon::start(simulated(&rigd::cli::demo::sim_settings("webcam").unwrap()).unwrap());
    let mut c = d.subscribed();
    let scan = CalibrationScan {
        steps: 11,
        step_um: 2000.0,
        ..CalibrationScan::default()
    };
    let job = JobSpec {
        calibrate: Some(Box::new(scan)),
        settle_ms: 0,
        ..JobSpec::default()
    };
    let (id, ev) = run_job(&mut c, job);
    assert_finished(&ev);
    assert!(!note(&ev).applied, "a calibration scan applies none");
    let made = ev
        .iter()
        .find_map(|e| match e {
            EventBody::Calibrated(m) => Some(m.clone()),
            _ => None,
        })
        .expect("a calibrated event");
    // The record, where the result says, loads as `rigctl process --calibration` reads it.
    let r = result(&d, id);
    typed_as_the_schema_says(&r);
    assert_eq!(r["calibrated"]["id"], made.id.as_str());
    let cal = rigd::calibration_file::load(Path::new(&made.path)).unwrap();
    assert_eq!(cal.id, made.id);
    assert_eq!(cal.scan.frames, 11);
    assert_eq!(cal.scan.session.as_deref(), Some(made.session.as_str()));
    assert!(cal.targets.len() >= 4, "{}", made.summary);
    let rig = cal.rig.as_deref().unwrap();
    assert!(rig.contains("webcam") && rig.contains("paper"), "{rig}");
    let pointer = calibration_store::dir(&d.data).join(calibration_store::CURRENT);
    assert_eq!(
        std::fs::read_to_string(&pointer).unwrap().trim(),
        format!("{}.json", cal.id)
    );
    assert!(made.residual_rms_um < 30.0, "{}", made.summary);

    // Its session is not replayed: refused at once, naming the offline fit, no job run.
    let replay = Request::Replay {
        session: made.session.clone(),
        processing: Default::default(),
    };
    let err = format!("{:#}", d.client().request(&replay).unwrap_err());
    assert!(
        err.contains("is a calibration scan and is not replayed")
            && err.contains("rigctl calibrate")
            && err.contains(&made.session),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(&pointer).unwrap().trim(),
        format!("{}.json", cal.id),
        "the current calibration is unchanged"
    );

    // The next job applies it: events, manifest and result name it, offsets calibrated.
    let (id, ev) = run_job(&mut c, measure());
    assert_finished(&ev);
    let n = note(&ev);
    assert!(n.applied && n.warnings.is_empty(), "{n:?}");
    assert_eq!(n.id.as_deref(), Some(cal.id.as_str()));
    let m = session_of(&d.data, &ev).manifest;
    let named = m.calibration.expect("the manifest names the calibration");
    assert_eq!(named.id.as_deref(), Some(cal.id.as_str()));
    assert_eq!(named.source.as_deref(), Some(made.path.as_str()));
    let r = result(&d, id);
    typed_as_the_schema_says(&r);
    assert_eq!(r["calibration"]["id"], cal.id.as_str());
    let run = &r["runs"][0]["result"];
    assert_eq!(run["calibration"]["id"], cal.id.as_str());
    let objects = run["objects"].as_array().unwrap();
    assert!(objects.len() >= 4, "{run}");
    // Across a tilted, distorted webcam frame the local scale differs from the global one
    // by a few per cent: a calibrated offset is not the global scale's.
    let most = objects
        .iter()
        .map(|o| {
            let (a, g) = (&o["offset_um"], &o["offset_global_um"]);
            (0..2)
                .map(|i| (a[i].as_f64().unwrap() - g[i].as_f64().unwrap()).abs())
                .fold(0.0, f64::max)
        })
        .fold(0.0, f64::max);
    assert!(
        most > 5.0,
        "calibrated and global offsets differ by at most {most} µm"
    );

    // `rigctl process SESSION` applies the calibration the daemon did, and says so.
    let dir = session_of(&d.data, &ev).dir;
    let offline = |extra: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_rigctl"))
            .arg("process")
            .arg(&dir)
            .args(extra)
            .arg("--json")
            .output()
            .unwrap()
    };
    let out = offline(&[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(
        said.contains(&format!(
            "calibration {} applied, as the daemon did",
            cal.id
        )),
        "{said}"
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    let again = &v["runs"][0]["result"];
    assert_eq!(again["calibration"]["id"], cal.id.as_str());
    for (o, a) in objects.iter().zip(again["objects"].as_array().unwrap()) {
        for i in 0..2 {
            let (x, y) = (
                o["offset_um"][i].as_f64().unwrap(),
                a["offset_um"][i].as_f64().unwrap(),
            );
            assert!((x - y).abs() < 1e-6, "{o} vs {a}");
        }
    }
    // --no-calibration: the global scale; a record gone: an error naming the ways on.
    let v: Value = serde_json::from_slice(&offline(&["--no-calibration"]).stdout).unwrap();
    assert!(v["runs"][0]["result"]["calibration"].is_null(), "{v}");
    std::fs::rename(&made.path, d.data.join("moved.json")).unwrap();
    let out = offline(&[]);
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && e.contains(&cal.id) && e.contains("--calibration FILE"),
        "{e}"
    );
}

/// A calibration record for `frame_size` frames dated `date`, fitted on `board`: the
/// field model a plain scale of 774 µm/px about the frame centre.
fn record(id: &str, frame_size: [u32; 2], date: &str, board: Option<&str>) -> Value {
    let [w, h] = frame_size;
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    serde_json::json!({
        "version": 1, "id": id, "date": date, "method": "commanded", "rig": null,
        "fingerprint": {"frame_size": frame_size, "scale_um_per_px": 774.0, "board": board},
        "scan": {"frames": 30, "step_um": 500.0, "travel_um": 14500.0, "piezo_travel_um": null},
        "reference_rel_u": 1e-4, "targets": [],
        "field": {"layout": "free", "model": {"centre_px": [cx, cy],
            "norm_radius_px": cx.hypot(cy), "a_px_per_um": [[1.0 / 774.0, 0.0], [0.0, 1.0 / 774.0]],
            "g_per_um": [0.0, 0.0], "k1": 0.0, "k2": 0.0},
            "covariance": vec![[0.0; 8]; 8], "parameters": [], "stage_dir_rad": 3.0,
            "print_scale": null, "residual_rms_px": 0.01, "residual_rms_um": 7.7,
            "residual_max_um": 20.0}
    })
}

/// Make `text` the data root's current calibration, as `<id>.json`.
fn install(data: &Path, id: &str, text: &str) {
    let dir = calibration_store::dir(data);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join(format!("{id}.json")), text).unwrap();
    std::fs::write(dir.join(calibration_store::CURRENT), format!("{id}.json\n")).unwrap();
}

#[test]
fn a_stale_or_mismatched_calibration_warns_and_a_corrupt_one_fails_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let rig = simulated(&small_board_sim(dir.path())).unwrap();
    let d = Daemon::start_in(rig, dir);
    let mut c = d.subscribed();

    // Fitted on 1280x720 frames; this rig's are 300x200: not applied, and said so.
    let other = record("cal-big", [1280, 720], "2026-01-01T00:00:00Z", None);
    install(&d.data, "cal-big", &other.to_string());
    let (id, ev) = run_job(&mut c, measure());
    assert_finished(&ev);
    let n = note(&ev);
    assert!(!n.applied, "{n:?}");
    let w = n.warnings.join("\n");
    assert!(
        w.contains("was fitted on 1280x720 frames; these are 300x200"),
        "{w}"
    );
    assert!(result(&d, id)["runs"][0]["result"]["calibration"].is_null());
    let m = session_of(&d.data, &ev).manifest.calibration.unwrap();
    assert!(!m.applied && m.id.as_deref() == Some("cal-big"), "{m:?}");

    // Old, and fitted on another board: applied, with both warnings, in events and result.
    let old = record("cal-old", [300, 200], "2020-01-01T00:00:00Z", Some("paper"));
    install(&d.data, "cal-old", &old.to_string());
    let (id, ev) = run_job(&mut c, measure());
    assert_finished(&ev);
    let n = note(&ev);
    assert!(n.applied && n.age_days.unwrap() > 300.0, "{n:?}");
    let w = n.warnings.join("\n");
    assert!(
        w.contains("days old") && w.contains("calibration_max_age_days"),
        "{w}"
    );
    assert!(
        w.contains("fitted on board paper, this run has board small"),
        "{w}"
    );
    let r = result(&d, id);
    assert_eq!(
        r["calibration"]["warnings"].as_array().unwrap().len(),
        2,
        "{r}"
    );
    assert_eq!(r["runs"][0]["result"]["calibration"]["id"], "cal-old");

    // Corrupt: the job fails before it starts, naming the file; the daemon still serves.
    install(&d.data, "cal-bad", "{\"version\": 1, \"id\": ");
    let (_, ev) = run_job(&mut c, measure());
    let reason = match ev.last() {
        Some(EventBody::Failed { reason, .. }) => reason.clone(),
        other => panic!("{other:?}"),
    };
    let file = calibration_store::dir(&d.data).join("cal-bad.json");
    assert!(
        reason.contains(&file.display().to_string()) && reason.contains("not a calibration record"),
        "{reason}"
    );
    assert!(c.request(&Request::Hello {}).is_ok());
    // A readable record made current again: jobs run.
    install(&d.data, "cal-old", &old.to_string());
    let (_, ev) = run_job(&mut c, measure());
    assert_finished(&ev);
}

/// `rigctl calibrate` without a DIR: the calibration job on `rigd --sim`'s rig, its
/// summary printed, the record the daemon's current one.
#[test]
fn rigctl_calibrate_without_a_folder_runs_the_daemons_job_and_prints_its_summary() {
    let dir = tempfile::tempdir().unwrap();
    let (socket, data) = (dir.path().join("rigd.sock"), dir.path().join("data"));
    let _rigd = crate::support::daemon::RigdProcess::spawn_sim(&socket, &data);
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args([
            "calibrate",
            "--steps",
            "11",
            "--step-um",
            "2000",
            "--socket",
        ])
        .arg(&socket)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("field model residual RMS"), "{stdout}");
    let current = calibration_store::current(&data)
        .unwrap()
        .expect("a current one");
    assert!(
        stdout.contains(&format!("written to {}", current.source)),
        "{stdout}"
    );
    // Offline flags go with a DIR only.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(["calibrate", "--out", "x.json", "--socket"])
        .arg(&socket)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("go with DIR"),
        "{err}"
    );
}

/// A job queued behind a calibration job counts the ink prior that calibration may learn:
/// the submit reply's `memory_mb` (what was checked against `[daemon] max_job_memory_mb`)
/// is the prior's working set more than the same job's alone. Counting only the current
/// calibration's prior would estimate a job queued behind a scan short.
#[test]
fn a_job_behind_a_calibration_job_counts_the_prior_it_may_learn() {
    let d = Daemon::start(simulated(&rigd::cli::demo::sim_settings("webcam").unwrap()).unwrap());
    let mut c = d.subscribed();
    let memory_mb = |r: &Value| r["memory_mb"].as_u64().unwrap_or_else(|| panic!("{r}"));
    let reply = c.request(&Request::Submit { job: measure() }).unwrap();
    let alone = memory_mb(&reply);
    assert_finished(&events_until_end(&mut c, job_id(&reply)));
    // A long job, paused once it runs, holds the queue: the scan waits behind it.
    let blocker = submit(
        &mut c,
        JobSpec {
            steps: Some(200),
            ..measure()
        },
    );
    while !matches!(c.next_event().unwrap(), e if e.job_id == blocker && matches!(e.body, EventBody::Step { .. }))
    {
    }
    c.request(&Request::Pause { job_id: blocker }).unwrap();
    let scan = JobSpec {
        calibrate: Some(Box::new(CalibrationScan {
            steps: 11,
            step_um: 2000.0,
            ..CalibrationScan::default()
        })),
        settle_ms: 0,
        ..JobSpec::default()
    };
    let scan_id = submit(&mut c, scan);
    let reply = c.request(&Request::Submit { job: measure() }).unwrap();
    let behind = memory_mb(&reply);
    // No calibration is current: the scan queued ahead is what was counted.
    assert!(calibration_store::current(&d.data).unwrap().is_none());
    let prior_mb = rigd::pipeline::estimate::PRIOR_PEAK_BYTES >> 20;
    assert!(
        behind >= alone + prior_mb,
        "{behind} MB behind the scan, {alone} MB alone, the prior {prior_mb} MB a thread"
    );
    for id in [job_id(&reply), scan_id, blocker] {
        c.request(&Request::Cancel { job_id: id }).unwrap();
    }
}

/// The reason a job that failed gives.
fn failed_reason(events: &[EventBody]) -> String {
    match events.last() {
        Some(EventBody::Failed { reason, .. }) => reason.clone(),
        other => panic!("not failed: {other:?}"),
    }
}

/// One target of a record, `i`-th.
fn target(i: usize) -> Value {
    serde_json::json!({"name": format!("T{i}"), "centre_px": [10.0, 10.0], "steps": 3,
        "px_per_um": [0.0013, 0.0], "scale_um_per_px": 774.0, "scale_u_um_per_px": 0.1,
        "axis_angle_rad": 0.0, "axis_angle_u_rad": 0.0, "model_scale_um_per_px": 774.0,
        "model_scale_rel_u": 1e-4, "model_angle_u_rad": 0.0, "residuals_um": [[0.0, 0.0]],
        "residual_rms_um": 0.1, "residual_max_um": 0.2, "model_residual_rms_um": 0.1})
}

#[test]
fn hostile_calibration_records_fail_the_job_naming_the_field_in_a_short_reason() {
    let dir = tempfile::tempdir().unwrap();
    let rig = simulated(&small_board_sim(dir.path())).unwrap();
    let d = Daemon::start_in(rig, dir);
    let mut c = d.subscribed();
    let good = record("cal-ok", [300, 200], "2026-01-01T00:00:00Z", None);
    let cases: Vec<(&str, Value, &str)> = vec![
        (
            "k1",
            serde_json::json!(1e308),
            "field.model.k1 1e308 is outside",
        ),
        (
            "norm_radius_px",
            serde_json::json!(0.0),
            "field.model.norm_radius_px 0 is outside",
        ),
        (
            "zoom_per_um",
            serde_json::json!(1e308),
            "field.zoom_per_um 1e308 is outside",
        ),
        (
            "id",
            serde_json::json!("q/../../x"),
            "id \"q/../../x\" is not a plain file name",
        ),
        (
            "targets",
            (0..5000).map(target).collect(),
            "5000 targets, over the 4096",
        ),
    ];
    for (field, value, says) in cases {
        let mut bad = good.clone();
        match field {
            "id" => bad["id"] = value,
            "targets" => bad["targets"] = value,
            "zoom_per_um" => bad["field"]["zoom_per_um"] = value,
            f => bad["field"]["model"][f] = value,
        }
        install(&d.data, "cal-bad", &bad.to_string());
        let (_, ev) = run_job(&mut c, measure());
        let reason = failed_reason(&ev);
        assert!(reason.contains(says), "{field}: {reason}");
    }
    // A 200 MB pointer (sparse) is neither read nor quoted: a short reason, short replies.
    let pointer = calibration_store::dir(&d.data).join(calibration_store::CURRENT);
    std::fs::File::create(&pointer)
        .unwrap()
        .set_len(200 << 20)
        .unwrap();
    let (id, ev) = run_job(&mut c, measure());
    let reason = failed_reason(&ev);
    assert!(
        reason.len() < 1000,
        "{} bytes: {}",
        reason.len(),
        &reason[..200]
    );
    assert!(reason.contains("over the 4096-byte limit"), "{reason}");
    let status = c.request(&Request::Status { job_id: Some(id) }).unwrap();
    assert!(status.to_string().len() < 4000, "{status}");
    // Nothing was applied anywhere: the daemon serves on, a good record runs.
    install(&d.data, "cal-ok", &good.to_string());
    let (_, ev) = run_job(&mut c, measure());
    assert_finished(&ev);
}

#[test]
fn rigctl_refuses_a_calibration_whose_id_leaves_the_output_folder() {
    let dir = tempfile::tempdir().unwrap();
    let rig = simulated(&small_board_sim(dir.path())).unwrap();
    let d = Daemon::start_in(rig, dir);
    let mut c = d.subscribed();
    let (_, ev) = run_job(&mut c, measure());
    let s = session_of(&d.data, &ev);
    let (_, ev) = run_job(&mut c, measure());
    let victim = session_of(&d.data, &ev);
    let victim_result = std::fs::read(victim.dir.join("result.json")).unwrap();
    let out_dir = tempfile::tempdir().unwrap();
    let evil = out_dir.path().join("evil.json");
    let mut rec = record("x", [300, 200], "2026-01-01T00:00:00Z", None);
    rec["id"] = format!("q/../../../{}", victim.manifest.name).into();
    std::fs::write(&evil, rec.to_string()).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .arg("reprocess")
        .arg(&s.dir)
        .arg("--calibration")
        .arg(&evil)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("evil.json") && err.contains("is not a plain file name"),
        "{err}"
    );
    assert!(!s.dir.join("processed").exists());
    assert_eq!(
        std::fs::read(victim.dir.join("result.json")).unwrap(),
        victim_result
    );
}

mod extreme_numbers {
    use super::record;
    use proptest::prelude::*;
    use std::path::Path;

    /// ±0, denormals, the extremes, ordinary values, and numbers JSON cannot hold.
    fn extreme() -> impl Strategy<Value = String> {
        prop_oneof![
            Just("0".to_string()),
            Just("-0.0".to_string()),
            Just("5e-324".to_string()),
            Just("-2.2250738585072014e-309".to_string()),
            Just("1e308".to_string()),
            Just("-1e308".to_string()),
            Just("1e-308".to_string()),
            Just("1e400".to_string()),
            Just("NaN".to_string()),
            Just("Infinity".to_string()),
            any::<f64>().prop_map(|v| format!("{v:e}")),
            (-20.0f64..20.0).prop_map(|v| v.to_string()),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]
        /// Each number of the field model, as a record's text: parsed or refused naming the
        /// field, never a panic; accepted only in its range.
        #[test]
        fn model_numbers_are_range_checked_at_parse(field in 0usize..6, v in extreme()) {
            let names = ["k1", "k2", "norm_radius_px", "g_per_um", "centre_px", "scale"];
            let rec = record("cal-p", [300, 200], "2026-01-01T00:00:00Z", None);
            let marker = "98765.25";
            let mut rec = rec;
            match names[field] {
                "g_per_um" => rec["field"]["model"]["g_per_um"][0] = marker.parse::<f64>().unwrap().into(),
                "centre_px" => rec["field"]["model"]["centre_px"][1] = marker.parse::<f64>().unwrap().into(),
                "scale" => rec["fingerprint"]["scale_um_per_px"] = marker.parse::<f64>().unwrap().into(),
                f => rec["field"]["model"][f] = marker.parse::<f64>().unwrap().into(),
            }
            let text = rec.to_string().replace(marker, &v);
            let parsed = rigd::calibration_file::parse(text.as_bytes(), Path::new("p.json"));
            let value: Option<f64> = serde_json::from_str::<f64>(&v).ok();
            let in_range = value.is_some_and(|x| match names[field] {
                "k1" | "k2" => (-10.0..=10.0).contains(&x),
                "norm_radius_px" => (1.0..=32768.0).contains(&x),
                "g_per_um" => (-1e-2..=1e-2).contains(&x),
                "centre_px" => (-16384.0..=32768.0).contains(&x),
                _ => (1e-6..=1e6).contains(&x),
            });
            prop_assert_eq!(parsed.is_ok(), in_range, "{} = {}: {:?}", names[field], v, parsed.err());
        }
    }
}
