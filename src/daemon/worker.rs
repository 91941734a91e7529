//! The worker: takes queued jobs one at a time and runs each on a blocking thread with the
//! rig: a session to record into, the step engine to drive the rig, the recorder and the
//! processor as its sinks; then records how the job ended.

use crate::acquisition::interferometer::ReadLog;
use crate::acquisition::outcome::{Stop, StopCause};
use crate::acquisition::processor::{Image16, Processor, ProcessorEvent};
use crate::acquisition::study::{summarize, JobResult, RunResult};
use crate::acquisition::{
    Devices, Engine, EngineSettings, JobError, Outcome, StageKind, StepSink, Threaded,
};
use crate::calibration_file::Applied;
use crate::daemon::calibration::{self, JobCalibration};
use crate::daemon::jobs::{JobRecord, JobSource, JobState};
use crate::daemon::live_view::{self, tap::Tap};
use crate::daemon::protocol::EventBody;
use crate::daemon::recorder::{disk_error, Recorder};
use crate::daemon::rig_commands::{self, RigRequest};
use crate::daemon::rig_state::{probe, probe_all};
use crate::daemon::Shared;
use crate::offline::index::SessionFacts;
use crate::rig::Rig;
use crate::session::{ReplayOf, Session, SessionState, SessionWriter};
use crate::text::panic_message;
use std::panic::AssertUnwindSafe;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

/// Frames the engine may be ahead of the disk by (each is a few MB in memory).
const RECORDER_QUEUE: usize = 2;
/// Frames processing may fall behind the disk by.
const PROCESSOR_QUEUE: usize = 4;

/// Run jobs and rig requests until the daemon shuts down; returns the rig (stopped).
/// Rig requests go first: one waiting when a job is due runs before it.
pub async fn run(shared: Arc<Shared>, mut rig: Rig) -> Rig {
    let mut requests = shared.take_rig_requests();
    rig = probe_at_start(&shared, rig).await;
    loop {
        let notified = shared.wake.notified();
        if shared.shutting_down.load(Ordering::SeqCst) {
            if let Some(rx) = requests.as_mut() {
                rx.close();
                rig_commands::refuse_waiting(rx);
            }
            shared.live.close();
            return rig;
        }
        if let Some(req) = requests.as_mut().and_then(|rx| rx.try_recv().ok()) {
            rig = rig_commands::serve(&shared, rig, req).await;
            continue;
        }
        let next = shared.jobs().start_next();
        let Some(job) = next else {
            // Between jobs and requests: a frame for the live view, when one is due.
            if shared.live.grab_due() {
                rig = live_view::idle::grab(&shared, rig).await;
                continue;
            }
            tokio::select! {
                Some(req) = next_request(&mut requests) => {
                    rig = rig_commands::serve(&shared, rig, req).await;
                }
                _ = notified => {}
                _ = shared.live.wait_due() => {}
            }
            continue;
        };
        if job.source.uses_rig() {
            let fault = {
                let mut cond = shared.rig();
                cond.jobs_started += 1;
                cond.fault.clone()
            };
            // Queued before the rig went into fault: it cannot run, and makes no session.
            if let Some(f) = fault {
                let message = format!("not started: {}", f.refusal());
                end(&shared, job.id, None, failed_setup(message));
                continue;
            }
        }
        let sh = shared.clone();
        let id = job.id;
        let handle = tokio::task::spawn_blocking(move || {
            let ran = std::panic::catch_unwind(AssertUnwindSafe(|| execute(&sh, &job, &mut rig)));
            let panicked = ran.err().map(|p| panic_message(p.as_ref()));
            if panicked.is_some() {
                stop_after_panic(&mut rig);
            }
            (rig, panicked)
        });
        let (r, panicked) = handle.await.expect("the job's thread catches its panics");
        rig = r;
        if let Some(what) = panicked {
            restart_after_panic(&shared, id, &what);
        }
    }
}

/// The rig's stages stopped after a job's thread panicked (errors logged: nothing else
/// can be done with them here).
fn stop_after_panic(rig: &mut Rig) {
    let piezo = rig.piezo.as_deref_mut();
    for stage in std::iter::once(rig.axis.as_mut()).chain(piezo) {
        if let Err(e) = stage.stop() {
            tracing::warn!(stage = stage.name(), "not stopped after a panic: {e}");
        }
    }
}

/// A job's thread panicked outside the engine (its setup or closing): the job fails, its
/// session (if it has one) is marked failed, and the worker goes on with the next job.
fn restart_after_panic(shared: &Shared, id: u64, what: &str) {
    tracing::error!(job = id, panic = %what, "the worker panicked; it restarts with the next job");
    let message = format!("the worker panicked: {what}; it restarted");
    let session = shared.jobs().get(id).and_then(|r| r.session.clone());
    if let Some(name) = &session {
        let dir = shared.settings.data_root.join(name);
        if let Err(e) = crate::session::mark_failed(&dir, &message) {
            tracing::warn!(session = %name, "not marked failed: {e}");
        }
    }
    let e = JobError::Internal {
        message,
        stopped: None,
    };
    end(shared, id, session, Outcome::Failed(e));
}

/// The next rig request, or never when there is no channel.
async fn next_request(rx: &mut Option<rig_commands::Receiver>) -> Option<RigRequest> {
    match rx {
        Some(rx) => rx.recv().await,
        None => std::future::pending().await,
    }
}

/// What the controllers say before the first job: a GRBL locked at boot is a fault now.
async fn probe_at_start(shared: &Arc<Shared>, rig: Rig) -> Rig {
    let (rig, fault) = tokio::task::spawn_blocking(move || {
        let mut rig = rig;
        let fault = probe_all(&mut rig);
        (rig, fault)
    })
    .await
    .expect("the probe does not panic");
    if let Some(f) = &fault {
        tracing::warn!(device = %f.device, reason = %f.reason, "the rig starts in fault");
    }
    let mut cond = shared.rig();
    cond.fault = fault;
    cond.starting = false;
    drop(cond);
    rig
}

/// Run one job start to finish, on the calling (blocking) thread.
fn execute(shared: &Arc<Shared>, job: &JobRecord, live: &mut Rig) {
    let id = job.id;
    // A replay runs on a rig made of the recorded session; a live job on the rig.
    let mut replay;
    let (rig, replay_of): (&mut Rig, Option<ReplayOf>) = match &job.source {
        JobSource::Live | JobSource::Resume(_) => (live, None),
        JobSource::Replay { dir, .. } => match Session::open(dir).and_then(|s| {
            let rig = crate::rig::replay(&s)?;
            Ok((rig, ReplayOf::of(&s)))
        }) {
            Ok((r, name)) => {
                replay = r;
                (&mut replay, Some(name))
            }
            Err(e) => return end(shared, id, None, failed_setup(e.to_string())),
        },
    };
    let root = &shared.settings.data_root;
    let resumed_from = match &job.source {
        JobSource::Resume(origin) => Some(origin.link.clone()),
        _ => None,
    };
    let links = (replay_of, resumed_from);
    let calibration = match job_calibration(shared, job, &rig.info) {
        Ok(c) => c,
        Err(e) => return end(shared, id, None, failed_setup(e)),
    };
    let mut session = match SessionWriter::create(root, id, &job.spec, &job.plan, &rig.info, links)
    {
        Ok(s) => s,
        Err(e) => return end(shared, id, None, failed_setup(format!("disk: {e}"))),
    };
    let name = session.name().to_string();
    if let Err(e) = session.note_calibration(calibration.note.clone()) {
        return end(shared, id, Some(name), failed_setup(format!("disk: {e}")));
    }
    if let Some(r) = shared.jobs().get_mut(id) {
        r.session = Some(name.clone());
    }
    tracing::info!(job = id, session = %name, frames = job.plan.total_frames, "job started");
    let started = EventBody::Started {
        session: name.clone(),
        total_frames: job.plan.total_frames,
    };
    shared.events.emit(id, started);
    let note = calibration.note.clone();
    shared.events.emit(id, EventBody::Calibration(note.clone()));
    let (outcome, session, runs, images) = capture(shared, job, rig, session, calibration.applied);
    let outcome = decided(shared, job, outcome);
    let names: Vec<&str> = rig
        .info
        .board
        .iter()
        .flat_map(|b| b.targets.iter().map(|t| t.name.as_str()))
        .collect();
    let study = (job.spec.process && !runs.is_empty())
        .then(|| summarize(&runs, &names, rig.info.scale_um_per_px));
    let mut result = JobResult {
        runs,
        study,
        calibration: Some(note),
        calibrated: None,
    };
    let outcome = fit_calibration(
        shared,
        job,
        &rig.info,
        session.as_ref(),
        outcome,
        &mut result,
    );
    let facts = session.as_ref().map(|s| SessionFacts::of(s.manifest()));
    let outcome = close(session, outcome, &result, &images);
    if let (Some(facts), true) = (facts, job.spec.process) {
        index_job(root, &facts, &result);
    }
    // A job that failed on a live stage: the controller says whether the rig is in fault,
    // before any client hears of the end (and could submit again).
    if job.source.uses_rig() && matches!(outcome, Outcome::Failed(JobError::Hardware { .. })) {
        if let Some(f) = probe(rig, job.spec.stages().0) {
            tracing::warn!(device = %f.device, reason = %f.reason, "the rig is in fault");
            shared.rig().fault = Some(f);
        }
    }
    end(shared, id, Some(name), outcome);
}

/// The job's end once its capture is over, decided under the job table's lock: a cancel
/// that reached the table before this point ends the job `cancelled` (even one that arrived
/// during its last step, which the engine finished); one after it is refused as too late.
fn decided(shared: &Shared, job: &JobRecord, outcome: Outcome) -> Outcome {
    let mut jobs = shared.jobs();
    if let Some(r) = jobs.get_mut(job.id) {
        r.closing = true;
    }
    match (outcome, job.stop.cause()) {
        (Outcome::Finished, Some(StopCause::Client)) => Outcome::Cancelled(Stop {
            cause: StopCause::Client,
            during: None,
            stopped: None,
        }),
        (o, _) => o,
    }
}

/// The calibration the job applies (`daemon::calibration::for_job`), its warnings logged;
/// an unreadable current calibration is logged and the job does not run.
fn job_calibration(
    shared: &Shared,
    job: &JobRecord,
    info: &crate::rig::RigInfo,
) -> Result<JobCalibration, String> {
    let s = &shared.settings;
    let calibrating = job.spec.calibrate.is_some();
    let c = calibration::for_job(&s.data_root, s.calibration_max_age_days, info, calibrating)
        .inspect_err(|e| tracing::error!(job = job.id, "{e}"))?;
    for w in &c.note.warnings {
        tracing::warn!(job = job.id, "{w}");
    }
    if let (true, Some(cal)) = (c.note.applied, c.note.id.as_deref()) {
        tracing::info!(job = job.id, calibration = cal, "calibration applied");
    }
    Ok(c)
}

/// A calibration job that captured its scan: the fit of its session (the code path of
/// `rigctl calibrate DIR`), kept as the data root's current calibration and announced. A
/// fit that fails fails the job, naming why.
fn fit_calibration(
    shared: &Shared,
    job: &JobRecord,
    info: &crate::rig::RigInfo,
    session: Option<&SessionWriter>,
    outcome: Outcome,
    result: &mut JobResult,
) -> Outcome {
    let (Some(scan), Outcome::Finished, Some(session)) = (&job.spec.calibrate, &outcome, session)
    else {
        return outcome;
    };
    let failed = |message: String| {
        tracing::error!(job = job.id, "{message}");
        Outcome::Failed(JobError::Processing {
            message,
            stopped: None,
        })
    };
    if !matches!(job.source, JobSource::Live) {
        return failed(
            "a replayed or resumed calibration scan is not fitted: calibrate again".into(),
        );
    }
    let root = &shared.settings.data_root;
    match calibration::fit_session(root, session.dir(), session.name(), info, scan) {
        Ok(made) => {
            tracing::info!(job = job.id, calibration = %made.id, path = %made.path,
                residual_rms_um = made.residual_rms_um, "calibration made, now the current one");
            shared
                .events
                .emit(job.id, EventBody::Calibrated(Box::new(made.clone())));
            result.calibrated = Some(made);
            outcome
        }
        Err(e) => failed(format!(
            "calibration: {}",
            crate::text::error_chain(e.chain())
        )),
    }
}

/// Add a processed job's results to the data root's index (`rigctl results`). The index is
/// a convenience (`rigctl index rebuild` remakes it from the sessions): a failure is logged.
fn index_job(root: &std::path::Path, facts: &SessionFacts, result: &JobResult) {
    use crate::offline::index::{rows_of, Index, INDEX_FILE, RECORDED};
    let path = root.join(INDEX_FILE);
    // Nothing under the data root is opened through a symlink (docs/architecture.md).
    if path.symlink_metadata().is_ok_and(|m| !m.is_file()) {
        tracing::warn!(path = %path.display(), "results not indexed: not a regular file");
        return;
    }
    let rows = rows_of(facts, RECORDED, result);
    let added = Index::open(&path).and_then(|mut i| i.replace(&facts.session, RECORDED, &rows));
    if let Err(e) = added {
        tracing::warn!(session = %facts.session, "results not indexed: {e}");
    }
}

fn failed_setup(message: String) -> Outcome {
    Outcome::Failed(JobError::Setup { message })
}

type Captured = (
    Outcome,
    Option<SessionWriter>,
    Vec<RunResult>,
    Vec<(String, Image16)>,
);

/// The job's sinks: the interferometer read (on the engine's thread: see
/// `acquisition::interferometer`), then the session and processing, each on its own
/// thread behind the one before.
/// The live view's tap sits in front of the recorder, on the engine's thread.
type JobSink = ReadLog<Tap<Threaded<Recorder>>>;

/// Drive the rig through the job's plan, recording and processing behind it.
fn capture(
    shared: &Arc<Shared>,
    job: &JobRecord,
    rig: &mut Rig,
    mut session: SessionWriter,
    calibration: Option<Applied>,
) -> Captured {
    if let Some(log) = rig.log.as_deref_mut() {
        log.begin(SystemTime::now());
        if let Err(e) = session.begin_interferometer(log.source()) {
            log.end();
            let e = crate::acquisition::engine::sink_error(disk_error(e));
            return (Outcome::Failed(e), Some(session), Vec::new(), Vec::new());
        }
    }
    let mut sink = job_sink(shared, job, rig, session, calibration);
    let engine = Engine {
        plan: &job.plan,
        settings: EngineSettings {
            settle: Duration::from_millis(job.spec.settle_ms),
            grab_timeout: Duration::from_millis(rig.info.grab_timeout_ms),
            // Checked at submit; a number no Duration holds waits not at all.
            repeat_interval: job
                .spec
                .interval_s
                .and_then(|s| Duration::try_from_secs_f64(s).ok()),
            on_feed_hold: shared.settings.on_feed_hold,
            ..EngineSettings::default()
        },
        stop: &job.stop,
    };
    crate::daemon::pausing::listen(shared, job);
    let outcome = match devices(rig, job.spec.stages()) {
        Ok(mut dev) => engine.run(&mut dev, &mut sink),
        Err(e) => {
            let _ = sink.finish();
            Outcome::Failed(JobError::Hardware {
                source: e,
                stopped: None,
            })
        }
    };
    crate::daemon::pausing::unlisten(job);
    rig.log = sink.log.take();
    if let Some(log) = rig.log.as_deref_mut() {
        log.end();
    }
    let Some(mut recorder) = sink.inner.inner.into_inner() else {
        // The recorder's thread panicked: the session cannot be closed here; the next
        // start marks it incomplete.
        return (outcome, None, Vec::new(), Vec::new());
    };
    let (runs, images) = match recorder.processor.take().and_then(|p| p.into_inner()) {
        Some(p) => (p.results, p.images),
        None => (Vec::new(), Vec::new()),
    };
    (outcome, Some(recorder.session), runs, images)
}

/// The sink chain; the rig's interferometer is lent to it for the job.
fn job_sink(
    shared: &Arc<Shared>,
    job: &JobRecord,
    rig: &mut Rig,
    session: SessionWriter,
    calibration: Option<Applied>,
) -> JobSink {
    let processor = job.spec.process.then(|| {
        let mut p = Processor::new(
            job.plan.runs.clone(),
            rig.info.board.clone(),
            processor_events(shared, job.id),
        )
        .with_calibration(calibration);
        // A resumed job's runs are processed from the original's frames too.
        if let JobSource::Resume(origin) = &job.source {
            p = p.with_prior(origin.prior());
        }
        Threaded::spawn("processor", p, PROCESSOR_QUEUE)
    });
    let recorder = Recorder::new(session, step_recorded(shared, job.id), processor);
    let registration = job.spec.registration.unwrap_or_default();
    let recorder = Threaded::spawn("recorder", recorder, RECORDER_QUEUE);
    let tap = Tap::new(shared.clone(), job.id, job.spec.stage, recorder);
    ReadLog::new(rig.log.take(), registration, tap)
}

/// The job's stage, and the piezo when its plan moves it besides the axis.
fn devices(
    rig: &mut Rig,
    (stage, moves_piezo): (StageKind, bool),
) -> Result<Devices<'_>, crate::hw::HwError> {
    if moves_piezo {
        let piezo = rig.piezo.as_deref_mut().ok_or(crate::hw::HwError::Other {
            device: "piezo".into(),
            message: "this rig has no piezo".into(),
        })?;
        return Ok(Devices {
            stage: rig.axis.as_mut(),
            camera: rig.camera.as_mut(),
            piezo: Some(piezo),
        });
    }
    let stage: &mut dyn crate::hw::Stage = match stage {
        StageKind::Axis => rig.axis.as_mut(),
        StageKind::Piezo => match rig.piezo.as_deref_mut() {
            Some(p) => p,
            None => {
                return Err(crate::hw::HwError::Other {
                    device: "piezo".into(),
                    message: "this rig has no piezo".into(),
                })
            }
        },
    };
    Ok(Devices {
        stage,
        camera: rig.camera.as_mut(),
        piezo: None,
    })
}

/// Once a step is on disk: count it and tell the clients.
fn step_recorded(shared: &Arc<Shared>, id: u64) -> crate::daemon::recorder::OnRecorded {
    let shared = shared.clone();
    Box::new(move |rec| {
        shared.jobs().step_recorded(id, rec.index + 1);
        shared.events.emit(id, EventBody::step(rec));
    })
}

fn processor_events(shared: &Arc<Shared>, id: u64) -> crate::acquisition::processor::Emit {
    let shared = shared.clone();
    Box::new(move |ev| {
        let body = match ev {
            ProcessorEvent::Frame {
                index,
                process_ms,
                targets_found,
            } => EventBody::Processed {
                index,
                process_ms,
                targets_found,
            },
            ProcessorEvent::Run(r) => EventBody::Result {
                run: r.run,
                case: r.case,
                repeat: r.repeat,
                objects: r.result.as_ref().map(|x| x.objects.len()),
                error: r.error,
            },
        };
        shared.events.emit(id, body);
    })
}

/// Write the result and the final manifest. A write failing here keeps the job's own
/// reason first (on a full disk that names the frame that did not fit).
fn close(
    session: Option<SessionWriter>,
    outcome: Outcome,
    result: &JobResult,
    images: &[(String, Image16)],
) -> Outcome {
    let Some(mut session) = session else {
        return outcome;
    };
    let closing_failed = |outcome: &Outcome, e| {
        let e = crate::acquisition::engine::sink_error(disk_error(e));
        Outcome::Failed(e.after(outcome.reason()))
    };
    let outcome = match session.write_result(result, images) {
        Ok(()) => outcome,
        Err(e) => closing_failed(&outcome, e),
    };
    let state = match &outcome {
        Outcome::Finished => SessionState::Finished,
        Outcome::Cancelled(_) => SessionState::Cancelled,
        Outcome::Failed(_) => SessionState::Failed,
    };
    match session.close(state, outcome.reason(), outcome.detail()) {
        Ok(()) => outcome,
        Err(e) => closing_failed(&outcome, e),
    }
}

/// Record the job's end in the table and tell the clients.
fn end(shared: &Shared, id: u64, session: Option<String>, outcome: Outcome) {
    let reason = outcome.reason();
    let detail = outcome.detail();
    let (state, body) = match outcome {
        Outcome::Finished => (
            JobState::Finished,
            EventBody::Finished {
                session: session.unwrap_or_default(),
            },
        ),
        Outcome::Cancelled(_) => (
            JobState::Cancelled,
            EventBody::Cancelled {
                session,
                reason: reason.clone(),
                detail,
            },
        ),
        Outcome::Failed(_) => (
            JobState::Failed,
            EventBody::Failed {
                reason: reason.clone().unwrap_or_default(),
                session,
                detail,
            },
        ),
    };
    // Logged as people read them: `state=failed reason=…`, no `Some(..)`.
    let (state_name, why) = (crate::text::wire_name(&state), reason.as_deref());
    tracing::info!(job = id, state = %state_name, reason = why.unwrap_or("-"), "job ended");
    shared.jobs().finish(id, state, reason);
    shared.events.emit(id, body);
}
