//! The rig's configuration reaches its jobs: `[pipeline]` defaults fill what a job leaves
//! out (recorded in the session and echoed on `accepted`), explicit values win.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{
    assert_finished, events_until_end, job_id, rig_from_toml, subscribe, Daemon,
};
use rigd::acquisition::{JobRegistration, JobSpec};
use rigd::cli::client::Client;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::pipeline::{Combine, Estimator};
use rigd::session::{Session, SessionState};

const SIM_RIG: &str = r#"
[axis]
driver = "sim"
soft_min_um = 0.0
soft_max_um = 100000.0
max_step_um = 100000.0
[axis.sim]
max_speed_um_s = 50000.0
accel_um_s2 = 2000000.0
[camera]
driver = "sim"
frame_timeout_ms = 1500
[camera.sim]
width = 48
height = 32
supersample = 2
frame_period_ms = 2.0
exposure_ms = 1.0
[pipeline]
k = 3
estimator = "paper"
combine = "splat"
registration = "positions"
whole_frame = true
"#;

/// Run `job` to its end; its `accepted` event's job and its session.
fn run(c: &mut Client, d: &Daemon, job: JobSpec) -> (JobSpec, Session) {
    let reply = c.request(&Request::Submit { job }).unwrap();
    let ev = events_until_end(c, job_id(&reply));
    assert_finished(&ev);
    let accepted = ev
        .iter()
        .find_map(|e| match e {
            EventBody::Accepted { job, .. } => job.clone(),
            _ => None,
        })
        .expect("the accepted event carries the resolved job");
    let accepted = *accepted;
    // The submit reply says the same.
    assert_eq!(reply["job"], serde_json::to_value(&accepted).unwrap());
    let s = d.session(&ev);
    assert_eq!(s.manifest.state, SessionState::Finished);
    (accepted, s)
}

#[test]
fn pipeline_defaults_fill_what_a_job_omits_and_explicit_values_win() {
    let dir = tempfile::tempdir().unwrap();
    let rig = rig_from_toml(dir.path(), SIM_RIG);
    assert_eq!(rig.info.grab_timeout_ms, 1500, "[camera] frame_timeout_ms");
    let d = Daemon::start_in(rig, dir);
    let mut c = d.client();
    let hello = c.request(&Request::Hello {}).unwrap();
    assert_eq!(hello["rig"]["job_defaults"]["estimator"], "paper");
    subscribe(&mut c);
    let bare = JobSpec {
        start_um: Some(2_000.0),
        step_um: Some(100.0),
        steps: Some(2),
        settle_ms: 0,
        process: false,
        ..JobSpec::default()
    };

    let (job, s) = run(&mut c, &d, bare.clone());
    let got = |j: &JobSpec| (j.k, j.estimator, j.combine, j.registration, j.whole_frame);
    let configured = (
        Some(3),
        Some(Estimator::Paper),
        Some(Combine::Splat),
        Some(JobRegistration::Commanded),
        Some(true),
    );
    assert_eq!(got(&job), configured);
    assert_eq!(
        got(&s.manifest.job),
        configured,
        "the session records what ran"
    );
    assert!(s.manifest.plan.runs.iter().all(|r| r.case.k == 3));

    let explicit = JobSpec {
        k: Some(1),
        estimator: Some(Estimator::Fit),
        combine: Some(Combine::Mean),
        ..bare
    };
    let (job, s) = run(&mut c, &d, explicit);
    let want = (
        Some(1),
        Some(Estimator::Fit),
        Some(Combine::Mean),
        Some(JobRegistration::Commanded),
        Some(true),
    );
    assert_eq!(got(&job), want);
    assert_eq!(got(&s.manifest.job), want);
}

#[test]
fn the_grab_deadline_flag_is_for_the_sim_and_positive() {
    let rigd = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_rigd"))
            .args(args)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{args:?} was accepted");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let e = rigd(&["--grab-timeout-ms", "100"]);
    assert!(e.contains("--grab-timeout-ms needs --sim"), "{e}");
    let e = rigd(&["--sim", "--grab-timeout-ms", "0"]);
    assert!(e.contains("--grab-timeout-ms") && e.contains('0'), "{e}");
}
