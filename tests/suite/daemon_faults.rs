//! Faults from the simulated rig itself, through the daemon over its real socket: the
//! camera's stream stalling (the driver's deadline runs out) and a cancel mid-move (the
//! controller is told to stop where it is). Each time the axis is left stopped, what was
//! captured is kept, and the daemon runs the next job.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{
    assert_finished, assert_frames_decode, capture_job, events_until_end, fast_camera,
    reported_steps, submit, Daemon,
};
use rigd::acquisition::outcome::{EndDetail, Phase};
use rigd::acquisition::JobSpec;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::hw::MotionState;
use rigd::rig::{simulated_with_truth, Fault, SimSettings, SimTruth};
use rigd::session::{Session, SessionState};
use rigd::sim::motion::AxisParams;
use std::time::{Duration, Instant};

fn settings(faults: Vec<Fault>, axis: AxisParams) -> SimSettings {
    SimSettings {
        camera: fast_camera(),
        axis,
        faults,
        ..SimSettings::default()
    }
}

/// The daemon on the sim rig `s`, and the rig's true state.
fn start(s: SimSettings) -> (Daemon, SimTruth) {
    let (mut rig, truth) = simulated_with_truth(&s).unwrap();
    // As `rigd --sim --grab-timeout-ms 500`: a stalled camera fails the job in 0.5 s, not 5
    // (frames come every millisecond here).
    rig.info.grab_timeout_ms = 500;
    (Daemon::start(rig), truth)
}

fn scan(start_um: f64, step_um: f64, steps: u32) -> JobSpec {
    JobSpec {
        start_um: Some(start_um),
        ..capture_job(step_um, steps, 0)
    }
}

/// Every frame reported captured is in steps.csv and its PNG decodes whole.
fn check_captured(s: &Session, reported: &[(u32, f64)]) {
    assert_eq!(s.steps.len(), reported.len(), "{:?}", s.manifest.reason);
    assert_eq!(s.manifest.frames_captured as usize, reported.len());
    for (row, (index, commanded)) in s.steps.iter().zip(reported) {
        assert_eq!((row.index, row.position_um), (*index, *commanded));
    }
    assert_frames_decode(s, (48, 32));
}

/// `(position_um, state)` where the job left the stage, from the event's `detail` (the
/// reason's text says the same: "axis stopped at 123.456 µm (idle)").
fn stopped_at(detail: &Option<EndDetail>, reason: &str) -> (f64, MotionState) {
    let st = detail
        .as_ref()
        .and_then(|d| d.stopped.clone())
        .unwrap_or_else(|| panic!("no stop position with {reason:?}"));
    assert_eq!(st.device, "axis");
    let at = st.position_um.unwrap();
    assert!(
        reason.contains(&format!("axis stopped at {at:.3} µm")),
        "{reason}"
    );
    (at, st.state.unwrap())
}

/// The true axis has stopped at what the driver reported (within its positioning error).
fn check_axis_stopped(truth: &SimTruth, reported_um: f64) {
    let now = Instant::now();
    assert!(!truth.axis.is_moving(now), "the axis is still moving");
    let at = truth.axis.position_at(now);
    assert!(
        (at - reported_um).abs() < 12.0,
        "true {at} vs reported {reported_um}"
    );
}

#[test]
fn a_stalled_camera_fails_the_job_naming_the_camera_and_the_next_job_runs() {
    let (d, truth) = start(settings(
        vec![Fault::CameraTimeout(4)],
        SimSettings::default().axis,
    ));
    let mut c = d.subscribed();
    let id = submit(&mut c, scan(1_000.0, 50.0, 10));
    let ev = events_until_end(&mut c, id);
    let Some(EventBody::Failed { reason, detail, .. }) = ev.last() else {
        panic!("{ev:?}")
    };
    // The driver's deadline ran out: the reason names the camera and the wait.
    assert!(
        reason.starts_with("sim-camera: no reply within 500 ms"),
        "{reason}"
    );
    assert!(reason.contains("waiting for a frame"), "{reason}");
    let reported = reported_steps(&ev);
    assert_eq!(reported.len(), 3, "grabs 1-3 delivered, grab 4 stalled");
    let s = d.session(&ev);
    assert_eq!(s.manifest.state, SessionState::Failed);
    assert_eq!(s.manifest.reason.as_deref(), Some(reason.as_str()));
    check_captured(&s, &reported);
    // The axis was stopped where the failed step left it: at frame 4's position (the
    // emulator's stop takes the true position, within the 2 µm RMS positioning error).
    let (at, state) = stopped_at(detail, reason);
    assert!((at - 1_150.0).abs() < 12.0, "{reason}");
    assert!(
        matches!(state, MotionState::Idle | MotionState::Holding),
        "{reason}"
    );
    assert_eq!(
        detail.as_ref().unwrap().device.as_deref(),
        Some("sim-camera")
    );
    check_axis_stopped(&truth, at);
    // The driver restarted the stalled stream: the next job captures every frame.
    let id = submit(&mut c, scan(2_000.0, 50.0, 3));
    let ev = events_until_end(&mut c, id);
    assert_finished(&ev);
    check_captured(&d.session(&ev), &reported_steps(&ev));
}

#[test]
fn a_cancel_stops_the_axis_mid_move_and_the_next_job_runs() {
    // A slow axis: the second step is a 100 mm move of about 50 s (beyond the runner's
    // 30 s move deadline, so only a cancel mid-move ends this job as cancelled).
    let slow = AxisParams {
        max_speed_um_s: 2_000.0,
        accel_um_s2: 200_000.0,
        ..SimSettings::default().axis
    };
    let (d, truth) = start(settings(vec![], slow));
    let mut c = d.subscribed();
    let target = 101_000.0;
    let id = submit(&mut c, scan(1_000.0, 100_000.0, 2));
    let mut ev = Vec::new();
    while !matches!(ev.last(), Some(EventBody::Step { .. })) {
        let e = c.next_event().unwrap();
        assert!(!e.body.is_terminal(), "{:?}", e.body);
        if e.job_id == id {
            ev.push(e.body);
        }
    }
    // Cancel once the axis is truly on its way to the second position.
    let t = Instant::now();
    while !(truth.axis.is_moving(Instant::now())
        && truth.axis.position_at(Instant::now()) > 1_100.0)
    {
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "the move never started"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    let r = c.request(&Request::Cancel { job_id: id }).unwrap();
    assert_eq!(r["state"], "cancelling");
    ev.extend(events_until_end(&mut c, id));
    assert!(
        matches!(
            ev.last(),
            Some(EventBody::Cancelled {
                session: Some(_),
                ..
            })
        ),
        "{ev:?}"
    );
    let st = c.request(&Request::Status { job_id: Some(id) }).unwrap();
    assert_eq!(st["state"], "cancelled");
    let reason = st["reason"].as_str().unwrap();
    assert!(reason.contains("during the move to 101000 µm"), "{reason}");
    let Some(EventBody::Cancelled { detail, .. }) = ev.last() else {
        unreachable!()
    };
    let end = detail.as_ref().unwrap();
    assert_eq!(
        (end.phase, end.target_um),
        (Some(Phase::Move), Some(target))
    );
    // Stopped by the controller short of the target, not moving.
    let (at, state) = stopped_at(detail, reason);
    assert!(
        matches!(state, MotionState::Idle | MotionState::Holding),
        "{reason}"
    );
    assert!(at > 1_100.0 && at < target - 1_000.0, "{reason}");
    check_axis_stopped(&truth, at);
    // The frame of the first step is kept, nothing of the interrupted one.
    let s = d.session(&ev);
    assert_eq!(s.manifest.state, SessionState::Cancelled);
    check_captured(&s, &reported_steps(&ev));
    assert_eq!(s.steps.len(), 1);
    // The daemon runs the next job from where the axis was left.
    let next = scan(at.round() + 100.0, 50.0, 3);
    let id = submit(&mut c, next);
    let ev = events_until_end(&mut c, id);
    assert_finished(&ev);
    check_captured(&d.session(&ev), &reported_steps(&ev));
}

#[test]
fn fault_flags_parse_and_bad_ones_say_what_is_wrong() {
    assert_eq!(
        "camera-timeout@4".parse::<Fault>(),
        Ok(Fault::CameraTimeout(4))
    );
    assert_eq!("alarm@1".parse::<Fault>(), Ok(Fault::Alarm(1)));
    assert_eq!("serial-loss@2".parse::<Fault>(), Ok(Fault::SerialLoss(2)));
    for (bad, says) in [
        ("camera-timeout", "KIND@N"),
        ("camera-timeout@0", "not a call number"),
        ("alarm@x", "not a call number"),
        ("smoke@3", "unknown kind"),
    ] {
        let e = bad.parse::<Fault>().unwrap_err();
        assert!(e.contains(bad) && e.contains(says), "{bad}: {e}");
    }
}
