//! The step engine on two scripted stages (a plan over the axis and the piezo) and its
//! timed repeats: the piezo moved only when its target changes, both stages settled before
//! each grab, both stopped on a cancel, a wait between repeats that a cancel ends.

use super::fake::{
    frame, grab, move_abs, plain_move, status, stop, wait_settled, IdealStage, ScriptedCamera,
    ScriptedStage,
};
use crate::acquisition::outcome::{Phase, StopCause};
use crate::acquisition::plan::{Plan, RunPlan};
use crate::acquisition::sink::{Collect, SinkError, StepSink};
use crate::acquisition::{
    CaseScan, Devices, Engine, EngineSettings, Outcome, StepRecord, StopFlag,
};
use crate::hw::MotionState;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

fn run_plan(repeat: u32, axis: &[f64], piezo: Option<&[f64]>) -> RunPlan {
    RunPlan {
        run: repeat,
        case: CaseScan {
            name: "grid".into(),
            frames: axis.len() as u32,
            step_um: 50.0,
            k: 1,
        },
        repeat,
        positions_um: axis.to_vec(),
        piezo_um: piezo.map(<[f64]>::to_vec),
        processing: None,
    }
}

fn settings() -> EngineSettings {
    EngineSettings {
        settle: Duration::ZERO,
        move_poll: Duration::from_micros(10),
        ..EngineSettings::default()
    }
}

#[test]
fn a_grid_moves_the_piezo_once_a_row_and_grabs_with_both_settled() {
    // 2 x 2: axis inner (100, 150), piezo outer (0, 10).
    let plan = Plan {
        runs: vec![run_plan(
            0,
            &[100.0, 150.0, 100.0, 150.0],
            Some(&[0.0, 0.0, 10.0, 10.0]),
        )],
        total_frames: 4,
        first_index: 0,
    };
    let settled = Arc::new(AtomicU32::new(0));
    let count = |s: &Arc<AtomicU32>| {
        let s = s.clone();
        move || {
            s.fetch_add(1, Ordering::SeqCst);
        }
    };
    let mut axis = ScriptedStage::new(
        "axis",
        [100.0, 150.0, 100.0, 150.0].into_iter().flat_map(|p| {
            let mut m = plain_move(p);
            let w = m.pop().unwrap().then(count(&settled));
            m.push(w);
            m
        }),
    );
    // The piezo: moved for frames 0 and 2; for 1 and 3 only asked where it is.
    let mut piezo = ScriptedStage::new(
        "piezo",
        [
            move_abs(0.0),
            status(MotionState::Idle, 0.0),
            wait_settled(0.01).then(count(&settled)),
            status(MotionState::Idle, 0.01),
            move_abs(10.0),
            status(MotionState::Idle, 10.0),
            wait_settled(10.02).then(count(&settled)),
            status(MotionState::Idle, 10.02),
        ],
    );
    // Each grab comes after the axis's and (when it moved) the piezo's settled wait.
    let want = [2, 3, 5, 6];
    let mut camera = ScriptedCamera::new((0..4).map(|i| {
        let s = settled.clone();
        grab(Ok(frame(i))).then(move || {
            assert_eq!(s.load(Ordering::SeqCst), want[i as usize], "grab {i}");
        })
    }));
    let flag = StopFlag::default();
    let engine = Engine {
        plan: &plan,
        settings: settings(),
        stop: &flag,
    };
    let mut sink = Collect::default();
    let mut dev = Devices {
        stage: &mut axis,
        camera: &mut camera,
        piezo: Some(&mut piezo),
    };
    let out = engine.run(&mut dev, &mut sink);
    assert!(matches!(out, Outcome::Finished), "{:?}", out.reason());
    axis.done();
    piezo.done();
    camera.done();
    let got: Vec<(f64, f64, Option<f64>, Option<f64>)> = sink
        .records
        .iter()
        .map(|r| (r.commanded_um, r.axis_um, r.piezo_commanded_um, r.piezo_um))
        .collect();
    assert_eq!(
        got,
        [
            (100.0, 100.0, Some(0.0), Some(0.01)),
            (150.0, 150.0, Some(0.0), Some(0.01)),
            (100.0, 100.0, Some(10.0), Some(10.02)),
            (150.0, 150.0, Some(10.0), Some(10.02)),
        ]
    );
}

#[test]
fn a_cancel_during_the_piezos_move_stops_both_stages() {
    let plan = Plan {
        runs: vec![run_plan(0, &[100.0, 150.0], Some(&[0.0, 10.0]))],
        total_frames: 2,
        first_index: 0,
    };
    let flag = Arc::new(StopFlag::default());
    let f = flag.clone();
    let mut axis = ScriptedStage::new(
        "axis",
        [
            move_abs(100.0),
            status(MotionState::Idle, 100.0),
            wait_settled(100.0),
            stop(),
            status(MotionState::Idle, 100.0),
        ],
    );
    let mut piezo = ScriptedStage::new(
        "piezo",
        [
            move_abs(0.0),
            status(MotionState::Moving, 3.0).then(move || f.cancel()),
            stop(),
        ],
    );
    let mut camera = ScriptedCamera::new([]);
    let engine = Engine {
        plan: &plan,
        settings: settings(),
        stop: &flag,
    };
    let mut sink = Collect::default();
    let mut dev = Devices {
        stage: &mut axis,
        camera: &mut camera,
        piezo: Some(&mut piezo),
    };
    let out = engine.run(&mut dev, &mut sink);
    axis.done();
    piezo.done();
    let Outcome::Cancelled(s) = out else {
        panic!("{:?}", out.reason())
    };
    assert_eq!(
        (s.cause, s.during),
        (StopCause::Client, Some((Phase::Move, 0.0)))
    );
    assert_eq!(s.stopped.unwrap().device, "axis");
    assert!(sink.records.is_empty());
}

/// A sink that cancels the job when it sees its first frame.
struct CancelAtFirst(Arc<StopFlag>, Vec<u32>);

impl StepSink for CancelAtFirst {
    fn step(&mut self, rec: Arc<StepRecord>) -> Result<(), SinkError> {
        self.1.push(rec.index);
        self.0.cancel();
        Ok(())
    }
    fn end_run(&mut self, _run: u32) -> Result<(), SinkError> {
        Ok(())
    }
    fn finish(&mut self) -> Result<(), SinkError> {
        Ok(())
    }
}

#[test]
fn repeats_start_an_interval_apart_and_a_cancel_ends_the_wait() {
    let runs = (0..3).map(|r| run_plan(r, &[100.0], None)).collect();
    let plan = Plan {
        runs,
        total_frames: 3,
        first_index: 0,
    };
    let interval = Duration::from_millis(40);
    let flag = StopFlag::default();
    let engine = Engine {
        plan: &plan,
        settings: EngineSettings {
            repeat_interval: Some(interval),
            ..settings()
        },
        stop: &flag,
    };
    let mut stage = IdealStage::default();
    let mut camera = ScriptedCamera::frames(3);
    let mut sink = Collect::default();
    let mut dev = Devices {
        stage: &mut stage,
        camera: &mut camera,
        piezo: None,
    };
    let t0 = Instant::now();
    assert!(matches!(engine.run(&mut dev, &mut sink), Outcome::Finished));
    // The third repeat started two intervals after the first (sleeps never end early).
    assert!(t0.elapsed() >= 2 * interval, "{:?}", t0.elapsed());
    assert_eq!(sink.records.len(), 3);

    // An hour between repeats, cancelled after the first frame: the job ends cancelled
    // (this test would hang if the wait ignored the cancel).
    let flag = Arc::new(StopFlag::default());
    let engine = Engine {
        plan: &plan,
        settings: EngineSettings {
            repeat_interval: Some(Duration::from_secs(3600)),
            ..settings()
        },
        stop: &flag,
    };
    let mut camera = ScriptedCamera::frames(1);
    let mut dev = Devices {
        stage: &mut stage,
        camera: &mut camera,
        piezo: None,
    };
    let mut sink = CancelAtFirst(flag.clone(), Vec::new());
    let out = engine.run(&mut dev, &mut sink);
    let Outcome::Cancelled(s) = out else {
        panic!("{:?}", out.reason())
    };
    assert_eq!((s.cause, s.during), (StopCause::Client, None));
    assert_eq!(sink.1, [0]);
}
