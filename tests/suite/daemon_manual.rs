//! Manual control and pause/resume over the real socket on sim rigs (rigd's GRBL
//! driver over a pty to the GRBL emulator): `position`, `move` (limits and the maximum step
//! refused naming them, nothing moved), `stop` mid-move (the stage left short of its
//! target), moves refused during a job, moves sent while one runs queued in order and a
//! stop that stops the waiting ones too, the interferometer read by `position` between jobs
//! without its log growing; `pause`/`resume` mid-run with every frame of the plan recorded
//! once at its position, a paused job cancelled.

#![cfg(feature = "sim")]

use crate::support::daemon::{events_until_end, rig_from_toml, submit, Daemon};
use rigd::acquisition::{JobSpec, StageKind};
use rigd::cli::client::Client;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::daemon::protocol::{MoveReply, PositionReply, PositionSource};
use rigd::hw::MotionState;
use rigd::session::SessionState;

/// A config rig: the sim axis (10 mm/s: a long move lasts long enough to be seen running
/// even when the machine is busy) behind the GRBL emulator, soft limits [0, 100 mm], at
/// most 20 mm a move; a small fast camera.
const RIG: &str = r#"
[axis]
driver = "sim"
soft_min_um = 0.0
soft_max_um = 100000.0
max_step_um = 20000.0
[axis.sim]
max_speed_um_s = 10000.0
[camera]
driver = "sim"
[camera.sim]
width = 48
height = 32
supersample = 2
frame_period_ms = 2.0
exposure_ms = 1.0
"#;

fn start() -> Daemon {
    start_at(10_000.0)
}

/// The rig with the axis at `max_speed_um_s`: the queue and stop tests race a move against
/// a busy machine's scheduler, so they run one long enough to outlast any stall (CI ran a
/// 2 s move to its end before the `stop` sent right behind it arrived).
fn start_at(max_speed_um_s: f64) -> Daemon {
    let dir = tempfile::tempdir().unwrap();
    let text = RIG.replace(
        "max_speed_um_s = 10000.0",
        &format!("max_speed_um_s = {max_speed_um_s:.1}"),
    );
    let rig = rig_from_toml(dir.path(), &text);
    Daemon::start_in(rig, dir)
}

fn position(c: &mut Client) -> PositionReply {
    serde_json::from_value(c.request(&Request::Position {}).unwrap()).unwrap()
}

fn move_to(c: &mut Client, to_um: Option<f64>, by_um: Option<f64>) -> anyhow::Result<MoveReply> {
    let r = c.request(&Request::Move {
        stage: StageKind::Axis,
        to_um,
        by_um,
    })?;
    Ok(serde_json::from_value(r)?)
}

fn axis_um(p: &PositionReply) -> f64 {
    p.axis.as_ref().unwrap().position_um.unwrap()
}

#[test]
fn moves_go_where_asked_and_limits_are_refused_naming_them() {
    let d = start();
    let mut c = d.client();
    let p = position(&mut c);
    assert_eq!(p.source, PositionSource::Controllers);
    assert_eq!(p.axis.as_ref().unwrap().state, Some(MotionState::Idle));
    let m = move_to(&mut c, Some(5_000.0), None).unwrap();
    assert!(!m.stopped && m.state == MotionState::Idle, "{m:?}");
    assert!((m.position_um - 5_000.0).abs() < 10.0, "{m:?}");
    let m = move_to(&mut c, None, Some(-1_500.0)).unwrap();
    assert_eq!(m.target_um, 3_500.0);
    assert!((m.position_um - 3_500.0).abs() < 10.0, "{m:?}");
    assert!((axis_um(&position(&mut c)) - 3_500.0).abs() < 10.0);
    // Outside the soft limits, and a step over max_step_um: refused, nothing moves.
    let e = move_to(&mut c, Some(150_000.0), None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("rejected:") && e.contains("outside the soft travel limits [0, 100000] µm"),
        "{e}"
    );
    let e = move_to(&mut c, None, Some(25_000.0))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("exceeds the maximum step of 20000 µm") && e.contains("last target 3500 µm"),
        "{e}"
    );
    assert!((axis_um(&position(&mut c)) - 3_500.0).abs() < 10.0);
    // Bad shapes name the fields.
    let e = move_to(&mut c, Some(1.0), Some(1.0))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("`to_um` (absolute) or `by_um` (relative), not both"),
        "{e}"
    );
    let e = move_to(&mut c, None, None).unwrap_err().to_string();
    assert!(e.contains("a move needs `to_um`"), "{e}");
    // The daemon still serves.
    assert_eq!(position(&mut c).source, PositionSource::Controllers);
}

#[test]
fn a_stop_mid_move_leaves_the_stage_short_of_its_target() {
    let d = start_at(2_000.0);
    let mut c = d.client();
    move_to(&mut c, Some(1_000.0), None).unwrap();
    let socket = d.bg.socket.clone();
    // 20 mm at 2 mm/s: ten seconds, on another connection.
    let mover = std::thread::spawn(move || {
        let mut c = Client::connect(&socket).unwrap();
        // Behind a `position` the polls send, it waits its turn.
        move_to(&mut c, None, Some(20_000.0)).unwrap()
    });
    // Wait (by what position says, not by the clock) until the axis is on its way.
    loop {
        let p = position(&mut c);
        let a = p.axis.clone().unwrap();
        if p.source == PositionSource::Move
            && a.state == Some(MotionState::Moving)
            && a.position_um.unwrap() > 1_100.0
        {
            break;
        }
        assert!(
            !mover.is_finished(),
            "the move ended before it was seen moving"
        );
    }
    let r = c.request(&Request::Stop {}).unwrap();
    assert_eq!(r["stopping"], true, "{r}");
    let m = mover.join().unwrap();
    assert!(m.stopped, "{m:?}");
    assert_eq!(m.target_um, 21_000.0);
    assert!(
        m.position_um > 1_100.0 && m.position_um < 20_000.0,
        "stopped short: {m:?}"
    );
    let at = axis_um(&position(&mut c));
    assert!((at - m.position_um).abs() < 5.0, "{at} vs {m:?}");
    // Nothing to stop now.
    let r = c.request(&Request::Stop {}).unwrap();
    assert_eq!(r["stopping"], false, "{r}");
    // The stage moves again from where it stopped.
    let m2 = move_to(&mut c, None, Some(100.0)).unwrap();
    assert!((m2.position_um - (m.position_um + 100.0)).abs() < 10.0);
}

fn job(steps: u32) -> JobSpec {
    JobSpec {
        start_um: Some(1_000.0),
        step_um: Some(50.0),
        steps: Some(steps),
        settle_ms: 20,
        process: false,
        ..JobSpec::default()
    }
}

/// Events of job `id` until one matches.
fn until(c: &mut Client, id: u64, f: impl Fn(&EventBody) -> bool) -> Vec<EventBody> {
    let mut seen = Vec::new();
    loop {
        let e = c.next_event().unwrap();
        if e.job_id != id {
            continue;
        }
        let done = f(&e.body) || e.body.is_terminal();
        seen.push(e.body);
        if done {
            return seen;
        }
    }
}

#[test]
fn pause_and_resume_mid_run_record_every_frame_of_the_plan_once() {
    let d = start();
    let mut c = d.subscribed();
    let mut other = d.client();
    let id = submit(&mut c, job(20));
    let mut events = until(&mut c, id, |b| {
        matches!(b, EventBody::Step { index: 3, .. })
    });
    let r = other.request(&Request::Pause { job_id: id }).unwrap();
    assert_eq!(r["state"], "pausing", "{r}");
    events.extend(until(&mut c, id, |b| matches!(b, EventBody::Paused { .. })));
    let Some(EventBody::Paused {
        next_index,
        at_um,
        cause,
        ..
    }) = events.last().cloned()
    else {
        panic!("not paused: {events:?}")
    };
    assert_eq!(cause, "client");
    assert!((4..20).contains(&next_index), "{next_index}");
    // Left where the last frame was taken.
    let last_um = 1_000.0 + 50.0 * (next_index - 1) as f64;
    assert!(
        (at_um.unwrap() - last_um).abs() < 10.0,
        "{at_um:?} vs {last_um}"
    );
    let st = other
        .request(&Request::Status { job_id: Some(id) })
        .unwrap();
    assert_eq!(st["state"], "paused", "{st}");
    // The paused job owns the stage: no move; its position is readable.
    let e = move_to(&mut other, Some(5_000.0), None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&format!("job {id} is paused")) && e.contains(&format!("rigctl resume {id}")),
        "{e}"
    );
    let p = position(&mut other);
    assert_eq!((p.source, p.job_id), (PositionSource::PausedJob, Some(id)));
    let r = other.request(&Request::Resume { job_id: id }).unwrap();
    assert_eq!(r["state"], "resumed", "{r}");
    events.extend(events_until_end(&mut c, id));
    assert!(
        events.contains(&EventBody::Resumed { next_index }),
        "{events:?}"
    );
    assert!(matches!(events.last(), Some(EventBody::Finished { .. })));
    // Each frame's step event once, in order; the session's steps exactly the plan's.
    let indices: Vec<u32> = events
        .iter()
        .filter_map(|e| match e {
            EventBody::Step { index, .. } => Some(*index),
            _ => None,
        })
        .collect();
    assert_eq!(indices, (0..20).collect::<Vec<_>>());
    let s = d.session(&events);
    assert_eq!(s.manifest.state, SessionState::Finished);
    let steps: Vec<(u32, f64)> = s.steps.iter().map(|r| (r.index, r.position_um)).collect();
    let plan: Vec<(u32, f64)> = (0..20).map(|i| (i, 1_000.0 + 50.0 * i as f64)).collect();
    assert_eq!(steps, plan);
    for r in &s.steps {
        assert!(s.frame_path(r.index).is_file(), "frame {}", r.index);
    }
}

#[test]
fn a_paused_job_cancelled_ends_cancelled_with_the_frames_before_the_pause() {
    let d = start();
    let mut c = d.subscribed();
    let mut other = d.client();
    let id = submit(&mut c, job(30));
    let mut ev = until(&mut c, id, |b| {
        matches!(b, EventBody::Step { index: 1, .. })
    });
    other.request(&Request::Pause { job_id: id }).unwrap();
    ev.extend(until(&mut c, id, |b| matches!(b, EventBody::Paused { .. })));
    let Some(EventBody::Paused { next_index, .. }) = ev.last().cloned() else {
        panic!("{ev:?}")
    };
    // A pause while paused says so; a resume of a job not paused is refused.
    let r = other.request(&Request::Pause { job_id: id }).unwrap();
    assert_eq!(r["state"], "paused");
    let r = other.request(&Request::Cancel { job_id: id }).unwrap();
    assert_eq!(r["state"], "cancelling");
    ev.extend(events_until_end(&mut c, id));
    assert!(
        matches!(ev.last(), Some(EventBody::Cancelled { .. })),
        "{ev:?}"
    );
    let s = d.session(&ev);
    assert_eq!(s.manifest.state, SessionState::Cancelled);
    assert_eq!(s.steps.len() as u32, next_index);
    let e = other
        .request(&Request::Resume { job_id: id })
        .unwrap_err()
        .to_string();
    assert!(e.contains(&format!("job {id} is cancelled")), "{e}");
}

#[test]
fn moves_are_refused_while_a_job_runs_naming_it_and_how_to_stop_it() {
    let d = start();
    let mut c = d.subscribed();
    let mut other = d.client();
    let id = submit(&mut c, job(30));
    until(&mut c, id, |b| matches!(b, EventBody::Step { .. }));
    let e = move_to(&mut other, Some(5_000.0), None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("busy:")
            && e.contains(&format!("job {id} is running"))
            && e.contains(&format!("rigctl cancel {id}"))
            && e.contains("is refused")
            && !e.contains("waits"),
        "{e}"
    );
    let r = other.request(&Request::Stop {}).unwrap();
    assert_eq!(r["stopping"], false);
    assert!(r["message"]
        .as_str()
        .unwrap()
        .contains(&format!("rigctl cancel {id}")));
    other.request(&Request::Cancel { job_id: id }).unwrap();
    events_until_end(&mut c, id);
}

/// The rig state `hello` reports now.
fn rig_state(c: &mut Client) -> serde_json::Value {
    c.request(&Request::Hello {}).unwrap()["rig_state"].clone()
}

/// Start a long move (20 mm: two seconds at the default speed) on its own connection; return once
/// `position` sees the axis on its way.
fn long_move(d: &Daemon, c: &mut Client) -> std::thread::JoinHandle<MoveReply> {
    move_to(c, Some(1_000.0), None).unwrap();
    let socket = d.bg.socket.clone();
    let mover = std::thread::spawn(move || {
        let mut c = Client::connect(&socket).unwrap();
        move_to(&mut c, None, Some(20_000.0)).unwrap()
    });
    loop {
        let p = position(c);
        let a = p.axis.clone().unwrap();
        if p.source == PositionSource::Move
            && a.state == Some(MotionState::Moving)
            && a.position_um.unwrap() > 1_100.0
        {
            return mover;
        }
        assert!(
            !mover.is_finished(),
            "the move ended before it was seen moving"
        );
    }
}

/// Send `move by_um` on a connection of its own; return once the daemon counts it waiting
/// (`waiting` in the rig state is `n`).
fn queued_move(
    d: &Daemon,
    c: &mut Client,
    by_um: f64,
    n: u64,
) -> std::thread::JoinHandle<anyhow::Result<MoveReply>> {
    let socket = d.bg.socket.clone();
    let h = std::thread::spawn(move || {
        let mut c = Client::connect(&socket).unwrap();
        move_to(&mut c, None, Some(by_um))
    });
    while rig_state(c)["waiting"] != n {
        assert!(!h.is_finished(), "the move was answered before it waited");
    }
    h
}

#[test]
fn moves_sent_while_one_runs_wait_their_turn_in_order() {
    // 20 mm at 4 mm/s: five seconds for the two others to be seen waiting.
    let d = start_at(4_000.0);
    let mut c = d.client();
    let first = long_move(&d, &mut c);
    let second = queued_move(&d, &mut c, 100.0, 1);
    let third = queued_move(&d, &mut c, -300.0, 2);
    let s = rig_state(&mut c);
    assert_eq!(
        (s["state"].as_str(), s["request"].as_str()),
        (Some("busy"), Some("move")),
        "{s}"
    );
    let first = first.join().unwrap();
    let (second, third) = (
        second.join().unwrap().unwrap(),
        third.join().unwrap().unwrap(),
    );
    // Each ran after the one before it ended, from where it ended.
    assert!(
        !first.stopped && (first.position_um - 21_000.0).abs() < 10.0,
        "{first:?}"
    );
    assert!(!second.stopped, "{second:?}");
    assert!(
        (second.target_um - (first.position_um + 100.0)).abs() < 1.0,
        "{second:?}"
    );
    assert!(
        (third.target_um - (second.position_um - 300.0)).abs() < 1.0,
        "{third:?}"
    );
    assert!((axis_um(&position(&mut c)) - 20_800.0).abs() < 10.0);
    assert_eq!(rig_state(&mut c), serde_json::json!({"state": "ready"}));
}

#[test]
fn a_stop_stops_the_running_move_and_the_waiting_ones_never_start() {
    // 20 mm at 1 mm/s: twenty seconds for the stop to arrive while it runs.
    let d = start_at(1_000.0);
    let mut c = d.client();
    let first = long_move(&d, &mut c);
    let waiting = queued_move(&d, &mut c, 5_000.0, 1);
    // `stop` does not queue behind them.
    let r = c.request(&Request::Stop {}).unwrap();
    assert_eq!(r["stopping"], true, "{r}");
    assert!(
        r["message"]
            .as_str()
            .unwrap()
            .contains("the move waiting behind it does not run"),
        "{r}"
    );
    let first = first.join().unwrap();
    assert!(first.stopped && first.position_um < 20_000.0, "{first:?}");
    let w = waiting.join().unwrap().unwrap();
    assert!(w.stopped, "{w:?}");
    assert!(
        (w.position_um - first.position_um).abs() < 5.0,
        "it moved: {w:?}"
    );
    assert!((axis_um(&position(&mut c)) - first.position_um).abs() < 5.0);
    // A move sent after the stop runs.
    let m = move_to(&mut c, None, Some(100.0)).unwrap();
    assert!(!m.stopped && (m.position_um - (first.position_um + 100.0)).abs() < 10.0);
}

#[test]
fn position_reads_the_interferometer_between_jobs_and_its_log_does_not_grow() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("xl80.csv");
    let text = format!("{RIG}\n[xl80]\npath = \"xl80.csv\"\nformat = \"csv\"\n");
    let rig = rig_from_toml(dir.path(), &text);
    let d = Daemon::start_in(rig, dir);
    let mut c = d.client();
    let idle_bytes = std::fs::metadata(&log).unwrap().len();
    let a = position(&mut c);
    let la = a.interferometer.clone().expect("the sim rig's XL-80");
    let t = la.t_unix_s.unwrap();
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    assert!((t - now).abs() < 5.0, "taken at {t}");
    move_to(&mut c, None, Some(3_000.0)).unwrap();
    let b = position(&mut c);
    let (xa, xb) = (
        la.position_um.unwrap(),
        b.interferometer.as_ref().unwrap().position_um.unwrap(),
    );
    // The laser sees the move the controller reports (its noise is 0.2 µm RMS).
    let moved = axis_um(&b) - axis_um(&a);
    assert!((moved - 3_000.0).abs() < 10.0);
    assert!(
        ((xb - xa).abs() - moved).abs() < 1.5,
        "laser {xa} -> {xb}, axis moved {moved}"
    );
    // Read on request: the idle log is not written.
    assert_eq!(std::fs::metadata(&log).unwrap().len(), idle_bytes);
}
