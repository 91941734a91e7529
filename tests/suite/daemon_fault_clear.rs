//! A latched alarm or a lost port, and the stops, through the daemon over its real socket on
//! the simulated rig (rigd's GRBL driver over a pty to the GRBL emulator, whose own fault
//! injection raises ALARM:1 or pulls the port). The rig state says `fault` (device, reason,
//! what clears it) to every client, jobs are refused at submit naming the request that
//! clears it (none is accepted only to make an empty session and fail), and `unlock` /
//! `reconnect` clear it once the controller confirms.

#![cfg(feature = "sim")]

use crate::support::daemon::{
    assert_finished, capture_job, events_until_end, fast_camera, reported_steps, run_job, submit,
    Daemon, RigdProcess,
};
use rigd::acquisition::JobSpec;
use rigd::cli::client::Client;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::rig::{simulated, Fault, SimSettings};
use rigd::session::{Session, SessionState};
use std::time::Duration;

fn start(faults: Vec<Fault>) -> Daemon {
    let s = SimSettings {
        camera: fast_camera(),
        faults,
        ..SimSettings::default()
    };
    let mut rig = simulated(&s).unwrap();
    rig.info.grab_timeout_ms = 500;
    Daemon::start(rig)
}

fn scan(steps: u32) -> JobSpec {
    JobSpec {
        start_um: Some(1_000.0),
        ..capture_job(500.0, steps, 0)
    }
}

/// The rig state once the daemon has asked the controllers (`busy` until then).
fn settled(c: &mut Client) -> serde_json::Value {
    let t = std::time::Instant::now();
    loop {
        let s = c.request(&Request::Hello {}).unwrap()["rig_state"].clone();
        if s != serde_json::json!({"state": "busy"}) || t.elapsed() > Duration::from_secs(10) {
            return s;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

fn rig_state(c: &mut Client) -> (serde_json::Value, serde_json::Value) {
    let hello = c.request(&Request::Hello {}).unwrap();
    let status = c.request(&Request::Status { job_id: None }).unwrap();
    (hello["rig_state"].clone(), status["rig_state"].clone())
}

fn sessions(c: &mut Client) -> usize {
    let list = c
        .request(&Request::List {
            limit: None,
            before: None,
        })
        .unwrap();
    list["sessions"].as_array().unwrap().len()
}

/// Run a job into the injected fault; its failure reason.
fn fail_one(c: &mut Client) -> String {
    let (_, ev) = run_job(c, scan(6));
    match ev.last() {
        Some(EventBody::Failed { reason, .. }) => reason.clone(),
        other => panic!("expected the job to fail: {other:?}"),
    }
}

#[test]
fn a_latched_alarm_is_a_fault_until_unlock_clears_it() {
    let d = start(vec![Fault::Alarm(2)]);
    let mut c = d.subscribed();
    assert_eq!(settled(&mut c)["state"], "ready");
    let (hello, status) = rig_state(&mut c);
    assert_eq!(
        (hello["state"].as_str(), status["state"].as_str()),
        (Some("ready"), Some("ready"))
    );
    let reason = fail_one(&mut c);
    assert!(reason.contains("alarm"), "{reason}");
    // Every client sees the fault, with the device and what clears it.
    let mut other = d.client();
    let (hello, status) = rig_state(&mut other);
    assert_eq!(hello, status);
    assert_eq!(hello["state"], "fault", "{hello}");
    assert_eq!(hello["device"], "axis");
    assert_eq!(hello["clear_with"], serde_json::json!(["unlock", "home"]));
    // A job is refused at submit, naming the fault and the request; no session is made.
    let before = sessions(&mut c);
    let e = c
        .request(&Request::Submit { job: scan(2) })
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("rigd: rejected:") && e.contains("the rig is in fault"),
        "{e}"
    );
    assert!(e.contains("`unlock` (rigctl unlock --stage axis)"), "{e}");
    assert_eq!(sessions(&mut c), before);
    // Unlock: GRBL `$X`, confirmed by a report out of alarm.
    let r = c.request(&Request::Unlock { stage: None }).unwrap();
    assert_eq!(r["request"], "unlock");
    assert_eq!(r["stage"], "axis");
    assert_eq!(r["state"], "idle", "{r}");
    assert_eq!(r["rig_state"]["state"], "ready", "{r}");
    assert_eq!(rig_state(&mut other).0["state"], "ready");
    let (_, ev) = run_job(&mut c, scan(3));
    assert_finished(&ev);
}

#[test]
fn home_clears_an_alarm_too() {
    let d = start(vec![Fault::Alarm(1)]);
    let mut c = d.subscribed();
    fail_one(&mut c);
    let r = c.request(&Request::Home { stage: None }).unwrap();
    assert_eq!(
        (r["state"].as_str(), r["rig_state"]["state"].as_str()),
        (Some("idle"), Some("ready"))
    );
    // GRBL's homing cycle sets the origin.
    assert!(r["position_um"].as_f64().unwrap().abs() < 1.0, "{r}");
    assert_finished(&run_job(&mut c, scan(2)).1);
}

#[test]
fn a_lost_port_is_a_fault_until_reconnect_brings_it_back() {
    let d = start(vec![Fault::SerialLoss(2)]);
    let mut c = d.subscribed();
    let reason = fail_one(&mut c);
    assert!(reason.contains("port gone"), "{reason}");
    let (hello, _) = rig_state(&mut c);
    assert_eq!(hello["state"], "fault", "{hello}");
    assert_eq!(hello["clear_with"], serde_json::json!(["reconnect"]));
    let e = c
        .request(&Request::Submit { job: scan(2) })
        .unwrap_err()
        .to_string();
    assert!(e.contains("rigctl reconnect --stage axis"), "{e}");
    // The wrong request fails on the controller and the fault stays.
    let e = c
        .request(&Request::Unlock { stage: None })
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("rigd: hardware:") && e.contains("unlock failed"),
        "{e}"
    );
    assert_eq!(rig_state(&mut c).0["state"], "fault");
    // The sim's port comes back on reconnect (as if plugged in again).
    let r = c.request(&Request::Reconnect { stage: None }).unwrap();
    assert_eq!(r["rig_state"]["state"], "ready", "{r}");
    assert_finished(&run_job(&mut c, scan(3)).1);
}

/// A job queued behind the one that faulted ends without a session instead of failing on
/// the rig.
#[test]
fn a_job_queued_before_the_fault_ends_without_a_session() {
    let d = start(vec![Fault::Alarm(2)]);
    let mut c = d.subscribed();
    let first = submit(&mut c, scan(6));
    let second = submit(&mut c, scan(2));
    assert!(matches!(
        events_until_end(&mut c, first).last(),
        Some(EventBody::Failed { .. })
    ));
    let ev = events_until_end(&mut c, second);
    assert_eq!(ev.len(), 1, "no started, no step: {ev:?}");
    let Some(EventBody::Failed {
        reason, session, ..
    }) = ev.last()
    else {
        panic!("{ev:?}")
    };
    assert!(
        reason.starts_with("not started: the rig is in fault"),
        "{reason}"
    );
    assert_eq!(*session, None);
    assert_eq!(sessions(&mut c), 1);
}

#[test]
fn rig_requests_are_refused_while_a_job_runs() {
    let d = start(vec![]);
    let mut c = d.subscribed();
    let id = submit(&mut c, capture_job(10.0, 200, 20));
    // Wait for it to be running.
    loop {
        if let EventBody::Started { .. } = c.next_event().unwrap().body {
            break;
        }
    }
    for req in [
        Request::Unlock { stage: None },
        Request::Home { stage: None },
        Request::Reconnect { stage: None },
    ] {
        let e = c.request(&req).unwrap_err().to_string();
        assert!(
            e.contains("rigd: busy:") && e.contains(&format!("job {id} is running")),
            "{e}"
        );
    }
    let (hello, _) = rig_state(&mut c);
    assert_eq!(hello, serde_json::json!({"state": "busy", "job_id": id}));
    c.request(&Request::Cancel { job_id: id }).unwrap();
    assert!(matches!(
        events_until_end(&mut c, id).last(),
        Some(EventBody::Cancelled { .. })
    ));
    assert_eq!(rig_state(&mut c).0["state"], "ready");
}

/// A cancel during the last step's settle: the job ends `cancelled` (as the client was
/// told), and that step's frame is not recorded.
#[test]
fn a_cancel_during_the_last_settle_ends_cancelled_without_its_frame() {
    let d = start(vec![]);
    let mut c = d.subscribed();
    // A 4 s settle: the cancel sent 0.3 s into it lands inside it on a busy machine too.
    let id = submit(&mut c, capture_job(10.0, 2, 4_000));
    let mut steps = 0;
    while steps < 1 {
        if let EventBody::Step { .. } = c.next_event().unwrap().body {
            steps += 1;
        }
    }
    // Now in the last step's settle.
    std::thread::sleep(Duration::from_millis(300));
    let r = c.request(&Request::Cancel { job_id: id }).unwrap();
    assert_eq!(r["state"], "cancelling");
    let ev = events_until_end(&mut c, id);
    assert!(
        matches!(ev.last(), Some(EventBody::Cancelled { .. })),
        "{ev:?}"
    );
    assert!(reported_steps(&ev).is_empty(), "{ev:?}");
    let list = c
        .request(&Request::List {
            limit: None,
            before: None,
        })
        .unwrap();
    let s = &list["sessions"][0];
    assert_eq!(
        (s["state"].as_str(), s["frames_captured"].as_u64()),
        (Some("cancelled"), Some(1))
    );
}

/// SIGTERM to `rigd --sim` during a settle: the step ends without its frame, the session is
/// closed `cancelled` with the frames before it.
#[test]
fn sigterm_during_a_settle_records_no_frame_for_that_step() {
    let dir = tempfile::tempdir().unwrap();
    let (socket, data) = (dir.path().join("s.sock"), dir.path().join("data"));
    let mut reaper = RigdProcess::spawn_sim(&socket, &data);
    let mut c = Client::connect(&socket).unwrap();
    c.request(&Request::Subscribe { job_id: None }).unwrap();
    // A 4 s settle: the signal sent 0.4 s into it lands inside it on a busy machine too.
    let id = submit(&mut c, capture_job(10.0, 3, 4_000));
    let mut name = None;
    loop {
        match c.next_event().unwrap().body {
            EventBody::Started { session, .. } => name = Some(session),
            EventBody::Step { index: 0, .. } => break,
            _ => {}
        }
    }
    std::thread::sleep(Duration::from_millis(400)); // in step 1's settle
    let child = reaper.take();
    // SAFETY: signalling our own child process.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "{:?}", out.status);
    let s = Session::open(&data.join(name.unwrap())).unwrap();
    assert_eq!(s.manifest.state, SessionState::Cancelled);
    assert_eq!(s.steps.len(), 1, "job {id}: only the frame before the stop");
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

/// `rigctl unlock | home | reconnect [--stage]`: what a user types to clear each fault.
#[test]
fn rigctl_clears_faults_by_name() {
    let d = start(vec![Fault::SerialLoss(1)]);
    let mut c = d.subscribed();
    fail_one(&mut c);
    let sock = d.bg.socket.clone();
    let (ok, _, err) = rigctl(&sock, &["submit", "--steps", "2", "--step-um", "10"]);
    assert!(
        !ok && err.contains("rigctl reconnect --stage axis"),
        "{err}"
    );
    let (ok, out, err) = rigctl(&sock, &["reconnect"]);
    assert!(ok, "{out}{err}");
    assert!(
        out.starts_with("axis reconnect: idle at ") && out.trim_end().ends_with("rig ready"),
        "{out}"
    );
    let (ok, out, err) = rigctl(&sock, &["home", "--stage", "piezo"]);
    assert!(ok, "{out}{err}");
    assert!(out.starts_with("piezo home: idle at "), "{out}");
    let (ok, out, err) = rigctl(&sock, &["unlock", "--stage", "axis"]);
    assert!(ok && out.contains("rig ready"), "{out}{err}");
}

/// A GRBL that boots locked (homing enabled) is a fault before the first job: the daemon
/// asks each stage at start. `unlock` (`$X`) clears it.
#[test]
fn a_controller_locked_at_boot_is_a_fault_at_start() {
    use rigd::sim::grbl::{GrblSim, GrblSimOptions};
    use rigd::sim::motion::{Axis, AxisParams};
    let axis = std::sync::Arc::new(Axis::new(AxisParams {
        position_error_rms_um: 0.0,
        ..AxisParams::default()
    }));
    let opts = GrblSimOptions {
        alarm_on_boot: true,
        ..GrblSimOptions::default()
    };
    let sim = GrblSim::spawn(axis, opts, None).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let text = format!(
        "[axis]\ndriver = \"grbl\"\nport = \"{}\"\nsoft_min_um = 0.0\nsoft_max_um = 10000.0\n\
         max_step_um = 10000.0\n[camera]\ndriver = \"sim\"\n[camera.sim]\nwidth = 48\n\
         height = 32\nsupersample = 2\nframe_period_ms = 2.0\nexposure_ms = 1.0\n",
        sim.path().display()
    );
    let rig = rigd::rig::from_config(&crate::support::daemon::config(dir.path(), &text)).unwrap();
    let d = Daemon::start_in(rig, dir);
    let mut c = d.subscribed();
    let state = settled(&mut c);
    assert_eq!(state["state"], "fault", "{state}");
    assert_eq!(state["clear_with"][0], "unlock");
    assert!(c
        .request(&Request::Submit {
            job: capture_job(10.0, 2, 0)
        })
        .is_err());
    let r = c
        .request(&Request::Unlock {
            stage: Some(rigd::acquisition::StageKind::Axis),
        })
        .unwrap();
    assert_eq!(r["rig_state"]["state"], "ready", "{r}");
    assert_finished(&run_job(&mut c, capture_job(10.0, 2, 0)).1);
}
