//! The daemon driving GRBL 1.1h's own firmware (tests/support/firmware.rs) with frames from
//! the sim camera: a job of 20 × 50 µm records every frame where the motor really went and
//! polls `?` at no more than 5 Hz; a cancel mid-move leaves no alarm and the next job runs;
//! a pause and a resume lose no frame; a controller that boots locked is a fault until
//! `unlock`.

use crate::support::daemon::{capture_job, events_until_end, rig_from_toml, submit, Daemon};
use crate::support::firmware::Firmware;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::session::SessionState;
use std::time::{Duration, Instant};

/// GRBL 1.1h's default motor step ($100=250).
const STEP_UM: f64 = 4.0;

/// A rig on the firmware's port, with a small sim camera. Replies may take 3 s: the
/// firmware's simulated clock runs slow on a loaded machine.
fn daemon_on(fw: &Firmware) -> Daemon {
    let dir = tempfile::tempdir().unwrap();
    let text = format!(
        r#"
[axis]
driver = "grbl"
port = "{port}"
soft_min_um = -50000.0
soft_max_um = 50000.0
max_step_um = 50000.0
default_start_um = 0.0
reply_timeout_ms = 3000
[camera]
driver = "sim"
[camera.sim]
width = 48
height = 32
supersample = 1
frame_period_ms = 2.0
exposure_ms = 1.0
"#,
        port = fw.port
    );
    let rig = rig_from_toml(dir.path(), &text);
    Daemon::start_in(rig, dir)
}

/// Follow job `id` until an event `is` accepts; its events so far (panics if the job ends
/// first).
fn until(
    c: &mut rigd::cli::client::Client,
    id: u64,
    is: impl Fn(&EventBody) -> bool,
) -> Vec<EventBody> {
    let mut seen = Vec::new();
    loop {
        let e = c.next_event().unwrap();
        if e.job_id != id {
            continue;
        }
        let done = is(&e.body);
        let end = e.body.is_terminal();
        seen.push(e.body);
        if done {
            return seen;
        }
        assert!(!end, "job {id} ended first: {seen:?}");
    }
}

/// [`until`] a `step` event with `index`.
fn until_step(c: &mut rigd::cli::client::Client, id: u64, index: u32) -> Vec<EventBody> {
    until(
        c,
        id,
        |e| matches!(e, EventBody::Step { index: i, .. } if *i == index),
    )
}

fn alarms(fw: &Firmware) -> String {
    let rx = String::from_utf8_lossy(&fw.received()).into_owned();
    rx.lines().filter(|l| l.contains("ALARM")).collect()
}

#[test]
fn twenty_steps_of_50_um_record_where_the_motor_went_polling_at_5_hz() {
    let Some(fw) = Firmware::start("twenty_steps_of_50_um") else {
        return;
    };
    let d = daemon_on(&fw);
    let mut c = d.subscribed();
    let polls_before = fw.sent().iter().filter(|&&b| b == b'?').count();
    let t0 = Instant::now();
    let reply = c
        .request(&Request::Submit {
            job: capture_job(50.0, 20, 50),
        })
        .unwrap();
    // The step is 12.5 motor steps: the submit says so, naming the moves the axis makes.
    let warning = reply["warnings"][0].as_str().unwrap_or_default();
    assert!(warning.contains("48 or 52 µm"), "{reply}");
    let id = reply["job_id"].as_u64().unwrap();
    let events = events_until_end(&mut c, id);
    let secs = t0.elapsed().as_secs_f64();
    let s = d.session(&events);
    assert_eq!(s.manifest.state, SessionState::Finished, "{events:?}");
    assert_eq!(s.steps.len(), 20);
    for r in &s.steps {
        assert!(
            (r.axis_um - r.position_um).abs() <= STEP_UM / 2.0 + 1e-6,
            "frame {}: at {} for {}",
            r.index,
            r.axis_um,
            r.position_um
        );
        assert!((r.axis_um / STEP_UM).fract().abs() < 1e-6, "{}", r.axis_um);
    }
    let machine = s.manifest.rig.axis_machine.as_ref().expect("$$ recorded");
    assert_eq!(s.steps[1].commanded_registration_um(Some(machine)), 52.0);
    let polls = fw.sent().iter().filter(|&&b| b == b'?').count() - polls_before;
    assert!(
        polls as f64 <= 5.0 * secs + 2.0,
        "{polls} polls in {secs:.1} s"
    );
    assert_eq!(alarms(&fw), "");
}

#[test]
fn a_cancel_mid_move_leaves_no_alarm_and_the_next_job_runs() {
    let Some(fw) = Firmware::start("a_cancel_mid_move_leaves_no_alarm") else {
        return;
    };
    let d = daemon_on(&fw);
    let mut c = d.subscribed();
    // 4 mm moves: 1.3 s each at the firmware's rate and acceleration.
    let id = submit(&mut c, capture_job(4_000.0, 4, 0));
    until_step(&mut c, id, 0);
    std::thread::sleep(Duration::from_millis(400));
    c.request(&Request::Cancel { job_id: id }).unwrap();
    let events = events_until_end(&mut c, id);
    assert!(
        matches!(events.last(), Some(EventBody::Cancelled { .. })),
        "{events:?}"
    );
    assert_eq!(alarms(&fw), "");
    let next = submit(&mut c, capture_job(100.0, 3, 0));
    let events = events_until_end(&mut c, next);
    assert_eq!(d.session(&events).manifest.state, SessionState::Finished);
}

#[test]
fn a_pause_and_a_resume_lose_no_frame() {
    let Some(fw) = Firmware::start("a_pause_and_a_resume_lose_no_frame") else {
        return;
    };
    let d = daemon_on(&fw);
    let mut c = d.subscribed();
    let id = submit(&mut c, capture_job(500.0, 6, 0));
    let mut events = until_step(&mut c, id, 1);
    c.request(&Request::Pause { job_id: id }).unwrap();
    events.extend(until(&mut c, id, |e| matches!(e, EventBody::Paused { .. })));
    c.request(&Request::Resume { job_id: id }).unwrap();
    events.extend(events_until_end(&mut c, id));
    let s = d.session(&events);
    assert_eq!(s.manifest.state, SessionState::Finished, "{events:?}");
    let positions: Vec<f64> = s.steps.iter().map(|r| r.axis_um).collect();
    assert_eq!(positions, vec![0.0, 500.0, 1000.0, 1500.0, 2000.0, 2500.0]);
}

#[test]
fn a_controller_that_boots_locked_is_a_fault_until_unlock() {
    // Homing enabled: GRBL boots in alarm until homed or unlocked.
    let Some(fw) = Firmware::start_with("a_controller_that_boots_locked", &["$22=1"]) else {
        return;
    };
    let d = daemon_on(&fw);
    let mut c = d.subscribed();
    let hello = wait_for_state(&mut c, "fault");
    // `$$` is read in alarm too: hello gives the motor step.
    assert_eq!(
        hello["rig"]["axis_machine"]["motor_step_um"], 4.0,
        "{hello}"
    );
    assert!(
        hello["rig_state"]["reason"]
            .as_str()
            .unwrap_or_default()
            .contains("alarm"),
        "{hello}"
    );
    let refused = c.request(&Request::Submit {
        job: capture_job(100.0, 2, 0),
    });
    assert!(refused.is_err(), "{refused:?}");
    let r = c.request(&Request::Unlock { stage: None }).unwrap();
    assert_eq!(r["state"], "idle", "{r}");
    wait_for_state(&mut c, "ready");
    let id = submit(&mut c, capture_job(100.0, 2, 0));
    let events = events_until_end(&mut c, id);
    assert_eq!(d.session(&events).manifest.state, SessionState::Finished);
}

/// `hello` until its rig state is `state` (the worker asks the controllers after start).
fn wait_for_state(c: &mut rigd::cli::client::Client, state: &str) -> serde_json::Value {
    let t0 = Instant::now();
    loop {
        let h = c.request(&Request::Hello {}).unwrap();
        if h["rig_state"]["state"] == state {
            return h;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "never {state}: {h}");
        std::thread::sleep(Duration::from_millis(100));
    }
}
