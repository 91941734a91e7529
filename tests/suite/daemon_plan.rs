//! Plans beyond one line on the sim rig, end to end: `rigctl submit --grid-inner ...
//! --grid-outer ... --snake` over a real socket to a daemon whose axis (GRBL emulator) and
//! piezo (GCS emulator, moving the line of sight across the axis) are on ptys; the session's
//! steps.csv with both stages' positions; the image registration seeing the 2-D shifts;
//! plans refused at submit naming the field; a replay of the grid.

use crate::support::daemon::*;
use rigd::acquisition::{Grid, JobRegistration, JobSpec, Line, ScanPlan, StageKind};
use rigd::daemon::protocol::Request;
use rigd::pipeline::Combine;
use rigd::rig::{simulated, SimSettings};
use rigd::session::Session;

fn sim(dir: &std::path::Path) -> SimSettings {
    crate::support::daemon::small_board_sim(dir)
}

fn rigctl(socket: &std::path::Path, args: &[&str]) -> (bool, String, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(args)
        .arg("--socket")
        .arg(socket)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn a_snake_grid_over_the_axis_and_the_piezo_runs_and_registers_in_2d() {
    let dir = tempfile::tempdir().unwrap();
    let s = sim(dir.path());
    let d = Daemon::start(simulated(&s).unwrap());
    // 3 x 2 at 1/4 px along the axis and 1/5 px across it on the piezo, twice.
    let (ok, out, err) = rigctl(
        &d.bg.socket,
        &[
            "submit",
            "--grid-inner",
            "axis:193.5:3",
            "--grid-outer",
            "piezo:154.8:2:100",
            "--snake",
            "--repeats",
            "2",
            "--interval-s",
            "0.05",
            "--k",
            "4",
            "--combine",
            "interp",
            "--settle-ms",
            "0",
        ],
    );
    assert!(ok, "{out}\n{err}");
    let mut c = d.client();
    let sessions = list_all_sessions(&mut c);
    let name = sessions[0]["name"].as_str().unwrap();
    let session = Session::open(&d.data.join(name)).unwrap();
    assert_eq!(
        session.manifest.job.plan,
        Some(ScanPlan::Grid(Grid {
            inner: Line {
                stage: StageKind::Axis,
                step_um: 193.5,
                steps: 3,
                start_um: None,
            },
            outer: Line {
                stage: StageKind::Piezo,
                step_um: 154.8,
                steps: 2,
                start_um: Some(100.0),
            },
            snake: true,
        }))
    );
    let rows = &session.steps;
    assert_eq!(rows.len(), 12);
    let axis: Vec<f64> = rows[..6].iter().map(|r| r.position_um).collect();
    assert_eq!(axis, [1000.0, 1193.5, 1387.0, 1387.0, 1193.5, 1000.0]);
    let piezo: Vec<Option<f64>> = rows[..6].iter().map(|r| r.piezo_commanded_um).collect();
    let (p0, p1) = (Some(100.0), Some(100.0 + 154.8));
    assert_eq!(piezo, [p0, p0, p0, p1, p1, p1]);
    for r in rows {
        // The GCS piezo settles within nanometres of its target, and the XL-80 reads the
        // axis only (its beam along the axis, the piezo moving across it).
        let (want, got) = (r.piezo_commanded_um.unwrap(), r.piezo_um.unwrap());
        assert!((want - got).abs() < 0.5, "{r:?}");
        let x = r.interferometer_um.expect("a reading at every frame");
        assert!((x - r.axis_um).abs() < 5.0, "{r:?}");
    }
    // Every repeat started at least 50 ms after the previous one.
    assert!(rows[6].t_unix_s - rows[0].t_unix_s >= 0.05);
    // The image moved across the axis with the piezo: the registration measured it.
    let result: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(d.data.join(name).join("result.json")).unwrap(),
    )
    .unwrap();
    let steps = result["runs"][0]["result"]["steps"].as_array().unwrap();
    let y: Vec<f64> = steps
        .iter()
        .map(|s| s["image_shift_px"][1].as_f64().unwrap())
        .collect();
    for (i, y) in y.iter().enumerate() {
        let want = if i < 3 { 0.0 } else { -0.2 };
        assert!(
            (y - want).abs() < 0.03,
            "frame {i}: y shift {y} px, want {want}"
        );
    }
    // Residuals against both stages' positions stay small in x and y.
    let rms = &result["runs"][0]["result"]["step_summary"]["rms_residual_um"];
    for a in 0..2 {
        assert!(rms[a].as_f64().unwrap() < 10.0, "{rms}");
    }
    assert_eq!(result["runs"].as_array().unwrap().len(), 2);

    // `rigctl process` on the session registers the piezo by its commands too (each run
    // on its own, as the daemon did): the positions registration predicts the y shifts the
    // image shows.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args([
            "process",
            "--registration",
            "positions",
            "--piezo-dir",
            "0,-1",
            "--json",
        ])
        .arg(d.data.join(name))
        .args(["--frames", "6"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let job: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let r = &job["runs"][0]["result"];
    assert_eq!(r["options"]["piezo_dir"], serde_json::json!([0.0, -1.0]));
    let last = &r["steps"][5];
    assert_eq!(last["piezo_um"], 254.8);
    let predicted = last["position_shift_px"][1].as_f64().unwrap();
    assert!((predicted + 0.2).abs() < 1e-9, "{last}");
    let rms = &r["step_summary"]["rms_residual_um"];
    assert!(rms[1].as_f64().unwrap() < 10.0, "{rms}");

    // A replay registers by the recorded positions, both stages.
    let (_, events) = run_request(
        &mut d.subscribed(),
        &Request::Replay {
            session: name.into(),
            processing: rigd::acquisition::Processing {
                registration: Some(JobRegistration::Commanded),
                ..Default::default()
            },
        },
    );
    assert_finished(&events);
}

#[test]
fn plans_are_refused_at_submit_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start(simulated(&sim(dir.path())).unwrap());
    let mut c = d.client();
    let line = |stage, step_um, steps| Line {
        stage,
        step_um,
        steps,
        start_um: None,
    };
    let grid = |inner, outer| JobSpec {
        plan: Some(ScanPlan::Grid(Grid {
            inner,
            outer,
            snake: false,
        })),
        combine: Some(Combine::Mean),
        ..JobSpec::default()
    };
    for (job, says) in [
        (
            grid(
                line(StageKind::Axis, 50.0, 3),
                line(StageKind::Piezo, 155.0, 0),
            ),
            "`plan.grid.outer.steps` must be at least 1",
        ),
        (
            grid(
                line(StageKind::Axis, 50.0, 3),
                line(StageKind::Piezo, 500.0, 4),
            ),
            "`plan.grid.outer`: position 1500 µm leaves the piezo soft limits [0, 1400] µm",
        ),
        (
            JobSpec {
                steps: Some(2),
                ..grid(
                    line(StageKind::Axis, 50.0, 3),
                    line(StageKind::Piezo, 1.0, 2),
                )
            },
            "give either `plan` or `steps`, not both",
        ),
    ] {
        let e = c.request(&Request::Submit { job }).unwrap_err().to_string();
        assert!(e.contains(says), "{e}");
    }
    // A misspelt shape: the decoder names what it expected.
    let (ok, out, err) = rigctl(
        &d.bg.socket,
        &[
            "submit",
            "--grid-inner",
            "axis:50:3",
            "--grid-outer",
            "axis:50:2",
        ],
    );
    assert!(!ok, "{out}");
    assert!(
        err.contains("`plan.grid.outer.stage` must be the other stage"),
        "{err}"
    );
    // The daemon keeps serving.
    c.request(&Request::Status { job_id: None }).unwrap();
}
