//! Runs one job on the rig: per step move, settle, grab a fresh frame, record it; frame i
//! is processed on a second thread while the axis moves to i+1. Blocking code: it runs on
//! its own thread, never on the async runtime.
//!
//! A cancel is seen mid-move: while the stage moves the runner polls its status in short
//! slices and, on a cancel, stops it where it is (GRBL feed hold, GCS HLT). A shutdown
//! (SIGTERM) lets the current step finish instead.

use crate::daemon::interferometer;
use crate::daemon::plan::Plan;
use crate::daemon::protocol::{process_options, EventBody, JobRegistration, JobSpec, StepTimings};
use crate::daemon::session::{unix_s, Image16, SessionWriter, StepRow};
use crate::daemon::study::{summarize, RunResult};
use crate::hw::{HwError, MotionState, Stage};
use crate::pipeline::Pipeline;
use crate::rig::Rig;
use image::RgbImage;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::mpsc;
use std::time::{Duration, Instant, SystemTime};

/// Values of a job's stop flag.
pub const RUN: u8 = 0;
pub const CANCEL: u8 = 1;
pub const SHUTDOWN: u8 = 2;

const MOVE_TIMEOUT: Duration = Duration::from_secs(30);
/// Between status polls of a moving stage: how late a cancel stops it, at most.
const MOVE_POLL: Duration = Duration::from_millis(2);

/// Why a step did not produce a frame.
enum StepError {
    Hw(HwError),
    /// A client cancelled while the stage moved; it has been stopped.
    Cancelled,
}

impl From<HwError> for StepError {
    fn from(e: HwError) -> StepError {
        StepError::Hw(e)
    }
}

/// How a job ended.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    Finished,
    Failed(String),
    Cancelled(String),
}

/// What a job produced, whatever its outcome.
pub struct JobOutput {
    pub outcome: Outcome,
    /// `{"runs": [...], "study": {...}}`; runs that finished before a fault are kept.
    pub result: serde_json::Value,
    pub images: Vec<(String, Image16)>,
}

/// Everything the runner needs besides the rig and the session.
pub struct JobContext<'a> {
    pub spec: &'a JobSpec,
    pub plan: &'a Plan,
    pub stop: &'a AtomicU8,
    pub emit: &'a (dyn Fn(EventBody) + Sync),
}

enum ToProcessor {
    Frame {
        run: u32,
        index: u32,
        image: RgbImage,
        position_um: f64,
    },
    EndRun(u32),
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// Run `ctx`'s plan on `rig`, recording into `session`.
pub fn run_job(ctx: &JobContext<'_>, rig: &mut Rig, session: &mut SessionWriter) -> JobOutput {
    let (tx, rx) = mpsc::sync_channel::<ToProcessor>(4);
    let info = rig.info.clone();
    std::thread::scope(|scope| {
        let processor = scope.spawn(|| process_frames(ctx, &info, rx));
        let outcome = capture(ctx, rig, session, &tx);
        drop(tx);
        let (runs, images) = processor
            .join()
            .unwrap_or_else(|_| (Vec::new(), Vec::new()));
        let names: Vec<&str> = info
            .board
            .iter()
            .flat_map(|b| b.targets.iter().map(|t| t.name.as_str()))
            .collect();
        let study = (ctx.spec.process && !runs.is_empty())
            .then(|| summarize(&runs, &names, info.scale_um_per_px));
        JobOutput {
            outcome,
            result: serde_json::json!({ "runs": runs, "study": study }),
            images,
        }
    })
}

/// The capture loop. On any fault or stop the stage is stopped before returning.
fn capture(
    ctx: &JobContext<'_>,
    rig: &mut Rig,
    session: &mut SessionWriter,
    tx: &mpsc::SyncSender<ToProcessor>,
) -> Outcome {
    let total = ctx.plan.total_frames;
    // Stop the stage and say where it was left ("" if it cannot say).
    let stop_stage = |rig: &mut Rig| -> String {
        let Ok(s) = rig.stage(ctx.spec.stage) else {
            return String::new();
        };
        if let Err(e) = s.stop() {
            tracing::warn!(stage = s.name(), "stopping after the job: {e}");
        }
        stopped_at(s)
    };
    if let Err(e) = interferometer::begin_job(rig.log.as_deref_mut(), session) {
        return Outcome::Failed(format!("disk: {e}"));
    }
    let mut index = 0u32;
    for run in &ctx.plan.runs {
        for &commanded_um in &run.positions_um {
            match ctx.stop.load(Ordering::SeqCst) {
                RUN => {}
                CANCEL => {
                    let at = stop_stage(rig);
                    return Outcome::Cancelled(format!("cancelled by a client{at}"));
                }
                _ => {
                    let at = stop_stage(rig);
                    return Outcome::Cancelled(format!("the daemon is shutting down{at}"));
                }
            }
            let step = step(ctx, rig, commanded_um);
            let (axis_um, frame, timings) = match step {
                Ok(s) => s,
                Err(StepError::Cancelled) => {
                    let at = stop_stage(rig);
                    return Outcome::Cancelled(format!(
                        "cancelled by a client during the move to {commanded_um} µm{at}"
                    ));
                }
                Err(StepError::Hw(e)) => {
                    let at = stop_stage(rig);
                    return Outcome::Failed(format!("{e}{at}"));
                }
            };
            let interferometer_um =
                match interferometer::at_frame(rig.log.as_deref_mut(), session, frame.timestamp) {
                    Ok(x) => x,
                    Err(e) => {
                        stop_stage(rig);
                        return Outcome::Failed(format!("disk: {e}"));
                    }
                };
            let row = StepRow {
                index,
                position_um: commanded_um,
                run: run.run,
                case: run.case.name.clone(),
                repeat: run.repeat,
                axis_um,
                interferometer_um,
                t_unix_s: unix_s(frame.timestamp),
                sequence: frame.sequence,
                move_ms: timings.move_ms,
                settle_ms: timings.settle_ms,
                grab_ms: timings.grab_ms,
            };
            if let Err(e) = session.record(row, &frame.image) {
                let at = stop_stage(rig);
                return Outcome::Failed(format!("disk: {e}{at}"));
            }
            (ctx.emit)(EventBody::Step {
                index,
                run: run.run,
                case: run.case.name.clone(),
                repeat: run.repeat,
                commanded_um,
                axis_um,
                interferometer_um,
                timings,
                total_frames: total,
            });
            if ctx.spec.process {
                let position_um =
                    match (ctx.spec.registration.unwrap_or_default(), interferometer_um) {
                        (JobRegistration::Interferometer, Some(x)) => x,
                        (JobRegistration::Interferometer, None) => {
                            stop_stage(rig);
                            return Outcome::Failed(format!(
                                "frame {index}: no interferometer reading at its time \
                             (registration: interferometer needs one)"
                            ));
                        }
                        _ => commanded_um,
                    };
                // Blocks only if processing falls four frames behind the capture.
                let _ = tx.send(ToProcessor::Frame {
                    run: run.run,
                    index,
                    image: frame.image,
                    position_um,
                });
            }
            index += 1;
        }
        if ctx.spec.process {
            let _ = tx.send(ToProcessor::EndRun(run.run));
        }
    }
    Outcome::Finished
}

/// `"; axis stopped at 123.4 µm (idle)"`: where a stopped stage reports itself.
fn stopped_at(stage: &mut dyn Stage) -> String {
    match stage.status() {
        Ok(st) => format!(
            "; {} stopped at {:.3} µm ({})",
            stage.name(),
            st.position_um,
            state_name(st.state)
        ),
        Err(e) => format!("; {} did not report after the stop: {e}", stage.name()),
    }
}

fn state_name(s: MotionState) -> &'static str {
    match s {
        MotionState::Idle => "idle",
        MotionState::Moving => "moving",
        MotionState::Holding => "holding",
        MotionState::Homing => "homing",
        MotionState::Alarm => "alarm",
    }
}

/// Wait for the move to `target_um` just commanded to finish, watching for a cancel while
/// the stage reports it moving. Returns the settled position.
///
/// A stage that stops moving in `Holding` (GRBL feed hold or safety door: never the
/// runner's doing here, its own stop comes only after a cancel) or in `Alarm` fails the step
/// at once, naming the state and where the stage is, rather than waiting out the move
/// deadline for a move that will not finish by itself.
fn finish_move(
    ctx: &JobContext<'_>,
    stage: &mut dyn Stage,
    target_um: f64,
) -> Result<f64, StepError> {
    let deadline = Instant::now() + MOVE_TIMEOUT;
    loop {
        if ctx.stop.load(Ordering::SeqCst) == CANCEL {
            return Err(StepError::Cancelled);
        }
        let st = stage.status()?;
        match st.state {
            MotionState::Moving | MotionState::Homing => {}
            MotionState::Idle => break,
            MotionState::Holding => {
                return Err(StepError::Hw(HwError::Other {
                    device: stage.name().into(),
                    message: format!(
                        "feed hold at {:.1} µm during the move to {target_um} µm (the \
                         controller holds: feed hold or safety door, not asked for by rigd)",
                        st.position_um
                    ),
                }))
            }
            MotionState::Alarm => {
                // The driver names the alarm (its code and meaning) if it knows it.
                return Err(StepError::Hw(
                    match stage.wait_settled(Duration::from_millis(1)) {
                        Err(e @ HwError::Alarm { .. }) => e,
                        _ => HwError::Other {
                            device: stage.name().into(),
                            message: format!(
                                "alarm at {:.1} µm during the move to {target_um} µm",
                                st.position_um
                            ),
                        },
                    },
                ));
            }
        }
        if Instant::now() >= deadline {
            return Err(StepError::Hw(HwError::Timeout {
                device: stage.name().into(),
                timeout_ms: MOVE_TIMEOUT.as_millis() as u64,
                waiting_for: "the move to finish (still moving)".into(),
            }));
        }
        std::thread::sleep(MOVE_POLL);
    }
    // The driver's own wait confirms the end of the move (and reports alarms and timeouts).
    let left = deadline.saturating_duration_since(Instant::now());
    Ok(stage.wait_settled(left.max(Duration::from_millis(1)))?)
}

/// Move, settle, grab one fresh frame.
fn step(
    ctx: &JobContext<'_>,
    rig: &mut Rig,
    commanded_um: f64,
) -> Result<(f64, crate::hw::Frame, StepTimings), StepError> {
    let t0 = Instant::now();
    let stage = rig.stage(ctx.spec.stage)?;
    stage.move_abs(commanded_um)?;
    let axis_um = finish_move(ctx, stage, commanded_um)?;
    let t1 = Instant::now();
    // Settle in short sleeps so a cancel is not held up by a long settle time.
    let settle = Duration::from_millis(ctx.spec.settle_ms);
    while t1.elapsed() < settle && ctx.stop.load(Ordering::SeqCst) == RUN {
        std::thread::sleep((settle - t1.elapsed()).min(Duration::from_millis(20)));
    }
    let t2 = Instant::now();
    // The rig's deadline ([camera] frame_timeout_ms; the sim's 5 s unless rigd is told).
    let grab_timeout = Duration::from_millis(rig.info.grab_timeout_ms);
    let frame = rig.camera.grab_fresh(SystemTime::now(), grab_timeout)?;
    let t3 = Instant::now();
    Ok((
        axis_um,
        frame,
        StepTimings {
            move_ms: ms(t1 - t0),
            settle_ms: ms(t2 - t1),
            grab_ms: ms(t3 - t2),
            process_ms: None,
        },
    ))
}

type Images = Vec<(String, Image16)>;

/// The processing side: one pipeline per run, fed as frames arrive.
fn process_frames(
    ctx: &JobContext<'_>,
    info: &crate::rig::RigInfo,
    rx: mpsc::Receiver<ToProcessor>,
) -> (Vec<RunResult>, Images) {
    let mut results = Vec::new();
    let mut images = Vec::new();
    let mut current: Option<(u32, Result<Pipeline, String>)> = None;
    for msg in rx {
        match msg {
            ToProcessor::Frame {
                run,
                index,
                image,
                position_um,
            } => {
                if current.as_ref().map(|c| c.0) != Some(run) {
                    let case = &ctx.plan.runs[run as usize].case;
                    let opts =
                        process_options(ctx.spec, case.k, info.scale_um_per_px, info.axis_dir);
                    let p = Pipeline::new(opts, info.board.clone()).map_err(|e| e.to_string());
                    current = Some((run, p));
                }
                let Some((_, Ok(p))) = current.as_mut() else {
                    continue;
                };
                let t = Instant::now();
                match p.push(&image, position_um) {
                    Ok(r) => (ctx.emit)(EventBody::Processed {
                        index,
                        process_ms: ms(t.elapsed()),
                        targets_found: r.targets_found,
                    }),
                    Err(e) => {
                        current.as_mut().expect("set above").1 = Err(format!("frame {index}: {e}"))
                    }
                }
            }
            ToProcessor::EndRun(run) => {
                let plan = &ctx.plan.runs[run as usize];
                let outcome = match current.take() {
                    Some((r, Ok(p))) if r == run => p.finish().map_err(|e| e.to_string()),
                    Some((r, Err(e))) if r == run => Err(e),
                    _ => Err("no frame reached processing".into()),
                };
                let (result, error) = match outcome {
                    Ok(f) => {
                        for im in f.images {
                            images.push((format!("run-{run:03}-{}", im.name), im.image));
                        }
                        (Some(f.result), None)
                    }
                    Err(e) => (None, Some(e)),
                };
                (ctx.emit)(EventBody::Result {
                    run,
                    case: plan.case.name.clone(),
                    repeat: plan.repeat,
                    objects: result.as_ref().map(|r| r.objects.len()),
                    error: error.clone(),
                });
                results.push(RunResult {
                    run,
                    case: plan.case.name.clone(),
                    repeat: plan.repeat,
                    frames: plan.case.frames,
                    step_um: plan.case.step_um,
                    k: plan.case.k,
                    result,
                    error,
                });
            }
        }
    }
    (results, images)
}
