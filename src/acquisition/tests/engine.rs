//! The step engine on scripted devices: every way a step can end, in milliseconds, with no
//! emulator, socket or wall-clock wait. The scripts check the exact calls the engine makes
//! (a stop after every fault, no grab after a stop) and `done()` that none was skipped.

use super::fake::{
    frame, grab, move_abs, move_abs_fails, plain_move, resume, status, status_fails, stop,
    stop_fails, wait_settled, wait_settled_fails, IdealStage, ScriptedCamera, ScriptedLog,
    ScriptedStage,
};
use crate::acquisition::interferometer::ReadLog;
use crate::acquisition::outcome::{EndKind, Phase, StopCause};
use crate::acquisition::plan::{Plan, RunPlan};
use crate::acquisition::sink::{Collect, SinkError, StepSink, Threaded};
use crate::acquisition::{
    CaseScan, Devices, Engine, EngineSettings, JobError, JobRegistration, Outcome, StepRecord,
    StopFlag,
};
use crate::acquisition::{HoldPolicy, PauseCause, PauseEvent};
use crate::hw::{HwError, MotionState};
use std::sync::Arc;
use std::sync::Mutex;
use std::time::{Duration, Instant};

fn plan(positions_um: &[f64]) -> Plan {
    Plan {
        runs: vec![RunPlan {
            run: 0,
            case: CaseScan {
                name: "scan".into(),
                frames: positions_um.len() as u32,
                step_um: 50.0,
                k: 1,
            },
            repeat: 0,
            positions_um: positions_um.to_vec(),
            piezo_um: None,
            processing: None,
        }],
        total_frames: positions_um.len() as u32,
        first_index: 0,
    }
}

fn settings(settle_ms: u64) -> EngineSettings {
    EngineSettings {
        settle: Duration::from_millis(settle_ms),
        move_poll: Duration::from_micros(10),
        ..EngineSettings::default()
    }
}

/// Run `plan` on the scripted devices; returns the outcome (scripts checked used up).
fn run(
    plan: &Plan,
    settings: EngineSettings,
    flag: &StopFlag,
    stage: &mut ScriptedStage,
    camera: &mut ScriptedCamera,
    sink: &mut dyn StepSink,
) -> Outcome {
    let engine = Engine {
        plan,
        settings,
        stop: flag,
    };
    let mut dev = Devices {
        stage,
        camera,
        piezo: None,
    };
    let out = engine.run(&mut dev, sink);
    stage.done();
    camera.done();
    out
}

fn stopped_idle_at(p: f64) -> Vec<super::fake::Expect<super::fake::StageCall>> {
    vec![stop(), status(MotionState::Idle, p)]
}

#[test]
fn every_step_is_recorded_in_order_and_the_sink_is_flushed() {
    let p = plan(&[100.0, 150.0, 200.0]);
    let mut stage = ScriptedStage::new(
        "axis",
        [100.0, 150.0, 200.0].into_iter().flat_map(plain_move),
    );
    let mut camera = ScriptedCamera::frames(3);
    let mut sink = Collect::default();
    let flag = StopFlag::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    assert!(matches!(out, Outcome::Finished), "{out:?}");
    let got: Vec<(u32, f64, u64)> = sink
        .records
        .iter()
        .map(|r| (r.index, r.commanded_um, r.frame.sequence))
        .collect();
    assert_eq!(got, vec![(0, 100.0, 0), (1, 150.0, 1), (2, 200.0, 2)]);
    assert_eq!(sink.runs_ended, vec![0]);
    assert!(sink.finished);
}

#[test]
fn a_feed_hold_mid_move_fails_the_step_naming_where_the_stage_held() {
    let p = plan(&[5000.0]);
    let mut script = vec![
        move_abs(5000.0),
        status(MotionState::Moving, 1200.0),
        status(MotionState::Holding, 1482.0),
    ];
    script.extend(stopped_idle_at(1482.0));
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::new([]);
    let flag = StopFlag::default();
    let out = run(
        &p,
        EngineSettings {
            on_feed_hold: HoldPolicy::Fail,
            ..settings(0)
        },
        &flag,
        &mut stage,
        &mut camera,
        &mut Collect::default(),
    );
    let reason = out.reason().unwrap();
    assert!(
        reason.starts_with("axis: feed hold at 1482.0 µm during the move to 5000 µm"),
        "{reason}"
    );
    assert!(
        reason.ends_with("; axis stopped at 1482.000 µm (idle)"),
        "{reason}"
    );
    let d = out.detail().unwrap();
    assert_eq!(
        (d.kind, d.device.as_deref()),
        (EndKind::Hardware, Some("axis"))
    );
    assert_eq!(d.stopped.unwrap().position_um, Some(1482.0));
}

#[test]
fn an_alarm_is_named_by_the_driver_and_a_failing_stop_is_reported() {
    let p = plan(&[300.0]);
    let alarm = HwError::Alarm {
        device: "axis".into(),
        code: 1,
        message: "hard limit triggered".into(),
    };
    let gone = || HwError::PortGone {
        device: "axis".into(),
        message: "read: EIO".into(),
    };
    let mut stage = ScriptedStage::new(
        "axis",
        [
            move_abs(300.0),
            status(MotionState::Alarm, 120.0),
            wait_settled_fails(alarm),
            stop_fails(gone()),
            status_fails(gone()),
        ],
    );
    let mut camera = ScriptedCamera::new([]);
    let flag = StopFlag::default();
    let out = run(
        &p,
        settings(0),
        &flag,
        &mut stage,
        &mut camera,
        &mut Collect::default(),
    );
    assert_eq!(
        out.reason().unwrap(),
        "axis: alarm 1: hard limit triggered; axis did not stop (axis: port gone: read: EIO) \
         and did not report (axis: port gone: read: EIO)"
    );
    let stopped = out.detail().unwrap().stopped.unwrap();
    assert!(stopped.stop_error.is_some() && stopped.position_um.is_none());
}

#[test]
fn a_cancel_mid_move_stops_the_stage_where_it_is_and_grabs_nothing() {
    let p = plan(&[100.0, 9000.0]);
    let flag = Arc::new(StopFlag::default());
    let f = flag.clone();
    let mut script = plain_move(100.0);
    script.extend([
        move_abs(9000.0),
        status(MotionState::Moving, 2000.0).then(move || f.cancel()),
    ]);
    script.extend(stopped_idle_at(2010.5));
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::frames(1);
    let mut sink = Collect::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    let Outcome::Cancelled(s) = &out else {
        panic!("{out:?}")
    };
    assert_eq!(
        (s.cause, s.during),
        (StopCause::Client, Some((Phase::Move, 9000.0)))
    );
    assert_eq!(
        out.reason().unwrap(),
        "cancelled by a client during the move to 9000 µm; axis stopped at 2010.500 µm (idle)"
    );
    assert_eq!(sink.records.len(), 1);
}

#[test]
fn a_cancel_during_a_long_settle_ends_the_step_at_once_without_a_frame() {
    let p = plan(&[100.0]);
    let flag = Arc::new(StopFlag::default());
    let f = flag.clone();
    let mut stage = ScriptedStage::new(
        "axis",
        [
            move_abs(100.0),
            status(MotionState::Idle, 100.0),
            wait_settled(100.0).then(move || f.cancel()),
            stop(),
            status(MotionState::Idle, 100.0),
        ],
    );
    // No grab is scripted: a grab would panic.
    let mut camera = ScriptedCamera::new([]);
    let mut sink = Collect::default();
    let t = Instant::now();
    let out = run(
        &p,
        settings(10_000),
        &flag,
        &mut stage,
        &mut camera,
        &mut sink,
    );
    // The 10 s settle was cut short, not waited out.
    assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
    let Outcome::Cancelled(s) = &out else {
        panic!("{out:?}")
    };
    assert_eq!(s.during, Some((Phase::Settle, 100.0)));
    assert!(sink.records.is_empty());
}

#[test]
fn a_stop_arriving_during_the_grab_discards_that_frame() {
    let p = plan(&[100.0]);
    let flag = Arc::new(StopFlag::default());
    let f = flag.clone();
    let mut script = plain_move(100.0);
    script.extend(stopped_idle_at(100.0));
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::new([grab(Ok(frame(7))).then(move || f.shutdown())]);
    let mut sink = Collect::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    let Outcome::Cancelled(s) = &out else {
        panic!("{out:?}")
    };
    assert_eq!(
        (s.cause, s.during),
        (StopCause::Shutdown, Some((Phase::Grab, 100.0)))
    );
    assert!(sink.records.is_empty(), "the frame was recorded as good");
    assert!(out
        .reason()
        .unwrap()
        .starts_with("the daemon is shutting down while grabbing"));
}

/// Cancels the job when it receives its `n`-th record.
struct CancelAt(usize, Arc<StopFlag>, Collect);
impl StepSink for CancelAt {
    fn step(&mut self, rec: Arc<StepRecord>) -> Result<(), SinkError> {
        self.2.step(rec)?;
        if self.2.records.len() == self.0 {
            self.1.cancel();
        }
        Ok(())
    }
}

#[test]
fn a_cancel_after_the_last_frame_still_ends_the_job_cancelled() {
    let p = plan(&[100.0, 150.0]);
    let flag = Arc::new(StopFlag::default());
    let mut script: Vec<_> = [100.0, 150.0].into_iter().flat_map(plain_move).collect();
    script.extend(stopped_idle_at(150.0));
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::frames(2);
    let mut sink = CancelAt(2, flag.clone(), Collect::default());
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    assert!(matches!(out, Outcome::Cancelled(_)), "{out:?}");
    assert_eq!(sink.2.records.len(), 2);
}

#[test]
fn a_shutdown_mid_move_lets_the_move_end_then_stops_before_the_grab() {
    let p = plan(&[400.0]);
    let flag = Arc::new(StopFlag::default());
    let f = flag.clone();
    let mut script = vec![
        move_abs(400.0),
        status(MotionState::Moving, 200.0).then(move || f.shutdown()),
        status(MotionState::Idle, 400.0),
        wait_settled(400.0),
    ];
    script.extend(stopped_idle_at(400.0));
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::new([]);
    let out = run(
        &p,
        settings(0),
        &flag,
        &mut stage,
        &mut camera,
        &mut Collect::default(),
    );
    let Outcome::Cancelled(s) = &out else {
        panic!("{out:?}")
    };
    assert_eq!(
        (s.cause, s.during),
        (StopCause::Shutdown, Some((Phase::Settle, 400.0)))
    );
}

#[test]
fn a_camera_stall_fails_the_job_naming_the_camera_and_stops_the_stage() {
    let p = plan(&[100.0, 150.0]);
    let mut script: Vec<_> = [100.0, 150.0].into_iter().flat_map(plain_move).collect();
    script.extend(stopped_idle_at(150.0));
    let mut stage = ScriptedStage::new("axis", script);
    let stall = HwError::Timeout {
        device: "camera".into(),
        timeout_ms: 500,
        waiting_for: "a frame exposed after the move settled".into(),
    };
    let mut camera = ScriptedCamera::new([grab(Ok(frame(0))), grab(Err(stall))]);
    let mut sink = Collect::default();
    let flag = StopFlag::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    assert!(
        out.reason()
            .unwrap()
            .starts_with("camera: no reply within 500 ms"),
        "{out:?}"
    );
    assert_eq!(out.detail().unwrap().device.as_deref(), Some("camera"));
    assert_eq!(sink.records.len(), 1);
}

#[test]
fn a_status_that_fails_mid_poll_fails_the_step() {
    let p = plan(&[100.0]);
    let gone = || HwError::PortGone {
        device: "axis".into(),
        message: "unplugged".into(),
    };
    let mut stage = ScriptedStage::new(
        "axis",
        [
            move_abs(100.0),
            status(MotionState::Moving, 10.0),
            status_fails(gone()),
            stop_fails(gone()),
            status_fails(gone()),
        ],
    );
    let mut camera = ScriptedCamera::new([]);
    let flag = StopFlag::default();
    let out = run(
        &p,
        settings(0),
        &flag,
        &mut stage,
        &mut camera,
        &mut Collect::default(),
    );
    let Outcome::Failed(JobError::Hardware { source, .. }) = &out else {
        panic!("{out:?}")
    };
    assert!(matches!(source, HwError::PortGone { .. }));
}

/// A controller that refuses the move (a soft limit it holds, say) fails the step; the stage
/// is stopped and asked where it is, and no frame is grabbed.
#[test]
fn a_refused_move_fails_the_step_and_stops_the_stage() {
    let p = plan(&[100.0, 200.0]);
    let refused = HwError::Other {
        device: "axis".into(),
        message: "error 15: travel exceeded".into(),
    };
    let mut script = plain_move(100.0);
    script.extend([
        move_abs_fails(200.0, refused),
        stop(),
        status(MotionState::Idle, 100.0),
    ]);
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::frames(1);
    let flag = StopFlag::default();
    let mut sink = Collect::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    assert!(
        out.reason().unwrap().contains("error 15: travel exceeded"),
        "{out:?}"
    );
    assert_eq!(
        sink.records.len(),
        1,
        "the first frame kept, no second grab"
    );
    let stopped = out.detail().unwrap().stopped.unwrap();
    assert_eq!(stopped.position_um, Some(100.0));
    stage.done();
    camera.done();
}

/// Fails with a full disk at its `n`-th record.
struct DiskFullAt(usize, usize);
impl StepSink for DiskFullAt {
    fn step(&mut self, _rec: Arc<StepRecord>) -> Result<(), SinkError> {
        self.1 += 1;
        if self.1 == self.0 {
            return Err(SinkError::Disk {
                file: Some("/data/s/frames/000001.png".into()),
                disk_full: true,
                message: "session /data/s/frames/000001.png: disk full".into(),
            });
        }
        Ok(())
    }
}

#[test]
fn a_sink_that_cannot_write_fails_the_job_naming_the_file() {
    let p = plan(&[100.0, 150.0, 200.0]);
    let mut script: Vec<_> = [100.0, 150.0].into_iter().flat_map(plain_move).collect();
    script.extend(stopped_idle_at(150.0));
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::frames(2);
    let flag = StopFlag::default();
    let out = run(
        &p,
        settings(0),
        &flag,
        &mut stage,
        &mut camera,
        &mut DiskFullAt(2, 0),
    );
    assert_eq!(
        out.reason().unwrap(),
        "disk: session /data/s/frames/000001.png: disk full; axis stopped at 150.000 µm (idle)"
    );
    let d = out.detail().unwrap();
    assert_eq!((d.kind, d.disk_full), (EndKind::Disk, Some(true)));
    assert_eq!(d.file.as_deref(), Some("/data/s/frames/000001.png"));
}

/// Panics at its first record, like a processing bug.
struct Panics;
impl StepSink for Panics {
    fn step(&mut self, _rec: Arc<StepRecord>) -> Result<(), SinkError> {
        panic!("index out of bounds: the len is 0")
    }
}

#[test]
fn a_panic_on_a_sink_thread_fails_the_job_with_its_message() {
    let p = plan(&[100.0, 150.0, 200.0, 250.0]);
    let flag = StopFlag::default();
    let mut sink = Threaded::spawn("processor", Panics, 1);
    // The panic surfaces at a later step or at the flush, whichever comes first.
    let mut stage = IdealStage::default();
    let mut camera = ScriptedCamera::new((0..4).map(|i| grab(Ok(frame(i)))));
    let engine = Engine {
        plan: &p,
        settings: settings(0),
        stop: &flag,
    };
    let mut dev = Devices {
        stage: &mut stage,
        camera: &mut camera,
        piezo: None,
    };
    let out = engine.run(&mut dev, &mut sink);
    let reason = out.reason().unwrap();
    assert!(
        reason.starts_with("processing failed: processor: index out of bounds: the len is 0"),
        "{reason}"
    );
    assert_eq!(out.detail().unwrap().kind, EndKind::Processing);
}

#[test]
fn registration_by_interferometer_fails_at_a_frame_the_log_does_not_cover() {
    let p = plan(&[100.0, 150.0]);
    let mut script: Vec<_> = [100.0, 150.0].into_iter().flat_map(plain_move).collect();
    script.extend(stopped_idle_at(150.0));
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::frames(2);
    let log = ScriptedLog::new([Some(-100.25), None]);
    let mut sink = ReadLog::new(
        Some(Box::new(log)),
        JobRegistration::Interferometer,
        Collect::default(),
    );
    let flag = StopFlag::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    assert!(
        out.reason()
            .unwrap()
            .starts_with("frame 1: no interferometer reading at its time"),
        "{out:?}"
    );
    assert_eq!(out.detail().unwrap().index, Some(1));
    // Both frames were handed on (what was captured is kept); the first registers by its
    // reading and carries the sample it was read from.
    let recs = &sink.inner.records;
    assert_eq!(recs.len(), 2);
    assert_eq!(
        (recs[0].interferometer_um, recs[0].registration_um),
        (Some(-100.25), -100.25)
    );
    assert_eq!(recs[0].samples.len(), 1);
    assert_eq!(
        (recs[1].interferometer_um, recs[1].registration_um),
        (None, 150.0)
    );
}

#[test]
fn registration_by_image_keeps_the_commanded_position_and_records_the_reading() {
    let p = plan(&[100.0]);
    let mut stage = ScriptedStage::new("axis", plain_move(100.0));
    let mut camera = ScriptedCamera::frames(1);
    let log = ScriptedLog::new([Some(-99.5)]);
    let mut sink = ReadLog::new(
        Some(Box::new(log)),
        JobRegistration::Image,
        Collect::default(),
    );
    let flag = StopFlag::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    assert!(matches!(out, Outcome::Finished), "{out:?}");
    let r = &sink.inner.records[0];
    assert_eq!(
        (r.interferometer_um, r.registration_um),
        (Some(-99.5), 100.0)
    );
}

/// A SIGTERM (the daemon's shutdown) during the last step's settle ends that step
/// without its frame, and the job ends cancelled with the frames before it.
#[test]
fn a_shutdown_during_the_last_settle_records_only_the_frames_before() {
    let p = plan(&[100.0, 150.0]);
    let flag = Arc::new(StopFlag::default());
    let f = flag.clone();
    let mut script = plain_move(100.0);
    script.extend([
        move_abs(150.0),
        status(MotionState::Idle, 150.0),
        wait_settled(150.0).then(move || f.shutdown()),
    ]);
    script.extend(stopped_idle_at(150.0));
    let mut stage = ScriptedStage::new("axis", script);
    // One grab only: a second would panic.
    let mut camera = ScriptedCamera::frames(1);
    let mut sink = Collect::default();
    let out = run(
        &p,
        settings(5_000),
        &flag,
        &mut stage,
        &mut camera,
        &mut sink,
    );
    let Outcome::Cancelled(s) = &out else {
        panic!("{out:?}")
    };
    assert_eq!(
        (s.cause, s.during),
        (StopCause::Shutdown, Some((Phase::Settle, 150.0)))
    );
    assert_eq!(sink.records.len(), 1);
    assert_eq!(sink.records[0].commanded_um, 100.0);
}

/// A client told `cancelling` during the last step's grab gets `cancelled`, not `finished`,
/// and that grab's frame is not recorded.
#[test]
fn a_cancel_during_the_last_grab_ends_cancelled_without_that_frame() {
    let p = plan(&[100.0, 150.0, 200.0]);
    let flag = Arc::new(StopFlag::default());
    let f = flag.clone();
    let mut script: Vec<_> = [100.0, 150.0, 200.0]
        .into_iter()
        .flat_map(plain_move)
        .collect();
    script.extend(stopped_idle_at(200.0));
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::new([
        grab(Ok(frame(1))),
        grab(Ok(frame(2))),
        grab(Ok(frame(3))).then(move || f.cancel()),
    ]);
    let mut sink = Collect::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    let Outcome::Cancelled(s) = &out else {
        panic!("{out:?}")
    };
    assert_eq!(
        (s.cause, s.during),
        (StopCause::Client, Some((Phase::Grab, 200.0)))
    );
    let kept: Vec<f64> = sink.records.iter().map(|r| r.commanded_um).collect();
    assert_eq!(kept, vec![100.0, 150.0]);
}

/// What a pause listener does when the engine pauses.
#[derive(Clone, Copy)]
enum OnPause {
    Resume,
    Cancel,
}

/// Hear the flag's pauses: record them, and resume or cancel at once (the engine waits for
/// it, polling), so the test takes no wall-clock wait.
fn on_pause(flag: &Arc<StopFlag>, then: OnPause) -> Arc<Mutex<Vec<PauseEvent>>> {
    let seen = Arc::new(Mutex::new(Vec::new()));
    let (s, f) = (seen.clone(), Arc::downgrade(flag));
    flag.pause.listen(Some(Box::new(move |ev| {
        s.lock().unwrap().push(ev.clone());
        let Some(f) = f.upgrade() else { return };
        if matches!(ev, PauseEvent::Paused { .. }) {
            match then {
                OnPause::Resume => {
                    f.pause.release();
                }
                OnPause::Cancel => f.cancel(),
            }
        }
    })));
    seen
}

#[test]
fn a_pause_is_taken_at_the_next_boundary_and_resume_goes_on_with_the_next_frame() {
    let positions = [100.0, 150.0, 200.0, 250.0];
    let p = plan(&positions);
    let flag = Arc::new(StopFlag::default());
    let seen = on_pause(&flag, OnPause::Resume);
    // Asked during the second frame's move: taken after that frame, before the third move.
    let f = flag.clone();
    let mut script = plain_move(100.0);
    script.push(move_abs(150.0).then(move || {
        f.pause.request();
    }));
    script.extend([status(MotionState::Idle, 150.0), wait_settled(150.0)]);
    script.extend([200.0, 250.0].into_iter().flat_map(plain_move));
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::frames(4);
    let mut sink = Collect::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    assert!(matches!(out, Outcome::Finished), "{out:?}");
    // Every frame of the plan once, in order, at its position: none lost or repeated.
    let got: Vec<(u32, f64, u64)> = sink
        .records
        .iter()
        .map(|r| (r.index, r.commanded_um, r.frame.sequence))
        .collect();
    assert_eq!(
        got,
        vec![(0, 100.0, 0), (1, 150.0, 1), (2, 200.0, 2), (3, 250.0, 3)]
    );
    assert_eq!(
        *seen.lock().unwrap(),
        vec![
            PauseEvent::Paused {
                next_index: 2,
                at_um: Some(150.0),
                cause: PauseCause::Client
            },
            PauseEvent::Resumed { next_index: 2 }
        ]
    );
}

#[test]
fn a_paused_job_cancelled_ends_cancelled_between_steps_with_its_frames_kept() {
    let p = plan(&[100.0, 150.0, 200.0]);
    let flag = Arc::new(StopFlag::default());
    let seen = on_pause(&flag, OnPause::Cancel);
    flag.pause.request();
    let mut script = Vec::new();
    // Paused before the first step: nothing moves until the cancel, then the stop.
    script.extend(stopped_idle_at(0.0));
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::new([]);
    let mut sink = Collect::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    let Outcome::Cancelled(stop) = &out else {
        panic!("{out:?}")
    };
    assert_eq!((stop.cause, stop.during), (StopCause::Client, None));
    assert!(sink.records.is_empty() && sink.finished);
    assert_eq!(seen.lock().unwrap().len(), 1, "paused, never resumed");
}

#[test]
fn a_feed_hold_pauses_and_resume_restarts_the_controller_and_the_held_move() {
    let p = plan(&[100.0, 5000.0]);
    let flag = Arc::new(StopFlag::default());
    let seen = on_pause(&flag, OnPause::Resume);
    let mut script = plain_move(100.0);
    script.extend([
        move_abs(5000.0),
        status(MotionState::Moving, 1200.0),
        status(MotionState::Holding, 1482.0),
        // Resumed: cycle start, the move issued again, then waited for as before.
        resume(),
        move_abs(5000.0),
        status(MotionState::Moving, 3000.0),
        status(MotionState::Idle, 5000.0),
        wait_settled(5000.0),
    ]);
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::frames(2);
    let mut sink = Collect::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    assert!(matches!(out, Outcome::Finished), "{out:?}");
    let got: Vec<(u32, f64, f64)> = sink
        .records
        .iter()
        .map(|r| (r.index, r.commanded_um, r.axis_um))
        .collect();
    assert_eq!(got, vec![(0, 100.0, 100.0), (1, 5000.0, 5000.0)]);
    let seen = seen.lock().unwrap();
    assert_eq!(
        seen[0],
        PauseEvent::Paused {
            next_index: 1,
            at_um: Some(1482.0),
            cause: PauseCause::FeedHold {
                device: "axis".into(),
                target_um: 5000.0
            }
        }
    );
    assert_eq!(seen[1], PauseEvent::Resumed { next_index: 1 });
}

#[test]
fn a_job_held_then_cancelled_ends_cancelled_in_the_move_and_records_nothing_of_it() {
    let p = plan(&[5000.0]);
    let flag = Arc::new(StopFlag::default());
    let _seen = on_pause(&flag, OnPause::Cancel);
    let mut script = vec![move_abs(5000.0), status(MotionState::Holding, 1482.0)];
    script.extend(stopped_idle_at(1482.0));
    let mut stage = ScriptedStage::new("axis", script);
    let mut camera = ScriptedCamera::new([]);
    let mut sink = Collect::default();
    let out = run(&p, settings(0), &flag, &mut stage, &mut camera, &mut sink);
    let Outcome::Cancelled(stop) = &out else {
        panic!("{out:?}")
    };
    assert_eq!(stop.during, Some((Phase::Move, 5000.0)));
    assert_eq!(stop.stopped.as_ref().unwrap().position_um, Some(1482.0));
    assert!(sink.records.is_empty());
}
