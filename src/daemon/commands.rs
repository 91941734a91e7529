//! What each request does. Quick and synchronous: nothing here touches the rig; jobs are
//! only checked (the plan) and queued for the worker.

use crate::acquisition::budget;
use crate::acquisition::plan::{check_disk, plan, Plan, PlanError};
use crate::acquisition::JobSpec;
use crate::daemon::jobs::{CancelRefused, JobSource, JobState, JobStatus, QueueError};
use crate::daemon::listing;
use crate::daemon::pausing;
use crate::daemon::protocol::{
    CancelReply, CancelState, Capabilities, DaemonStatus, ErrorCode, EventBody, HelloReply,
    ListReply, ProtoError, ReplyBody, Request, ResultReply, RigSummary, SubmitReply,
    PROTOCOL_VERSION,
};
use crate::daemon::replay::replay_job;
use crate::daemon::resuming::{self, ResumeError};
use crate::daemon::timing::{rfc3339_unix, JobTiming};
use crate::daemon::Shared;
use crate::session::{self, Session};
use std::sync::atomic::Ordering;

fn not_found(msg: String) -> ProtoError {
    ProtoError::new(ErrorCode::NotFound, msg)
}

fn rejected(e: PlanError) -> ProtoError {
    ProtoError::new(ErrorCode::Rejected, e.0)
}

/// Handle every request but `subscribe` (the connection owns subscriptions).
pub fn handle(shared: &Shared, req: Request) -> Result<ReplyBody, ProtoError> {
    match req {
        Request::Hello {} => Ok(ReplyBody::Hello(hello(shared))),
        Request::Submit { job } => submit(shared, job).map(ReplyBody::Submit),
        Request::Replay {
            session: name,
            processing,
        } => {
            refuse_if_stopping(shared)?;
            let dir = session_dir(shared, &name)?;
            let s = Session::open(&dir).map_err(|e| not_found(e.to_string()))?;
            if s.steps.is_empty() {
                return Err(ProtoError::new(
                    ErrorCode::Rejected,
                    format!("session {name} holds no frame"),
                ));
            }
            if s.manifest.job.calibrate.is_some() {
                // Refused here, not after the frames ran: a replay is a measurement, and a
                // calibration made from old frames must not become the rig's current one.
                return Err(ProtoError::new(
                    ErrorCode::Rejected,
                    format!(
                        "session {name} is a calibration scan and is not replayed: fit it again offline with `rigctl calibrate {} --scale-um-per-px S --out FILE` (then `rigctl process ... --calibration FILE`), or scan again with `rigctl calibrate`",
                        dir.display()
                    ),
                ));
            }
            let (spec, plan) = replay_job(&s, &processing).map_err(rejected)?;
            let source = JobSource::Replay {
                dir,
                overrides: processing,
            };
            // Checked as a live job is (the replay's frames are referenced, not written again:
            // the check overestimates by them).
            let queued = queue(shared, spec.clone(), plan.clone(), &s.manifest.rig, source)?;
            Ok(ReplyBody::Submit(announce(shared, queued, spec, &plan)))
        }
        Request::ResumeSession { session: name } => resume(shared, &name).map(ReplyBody::Submit),
        Request::Status { job_id: None } => {
            let jobs = shared.jobs();
            Ok(ReplyBody::DaemonStatus(DaemonStatus {
                running: jobs
                    .running()
                    .and_then(|id| jobs.status(id, &shared.rig_info)),
                queued: jobs.queued(),
                queued_jobs: jobs
                    .queued()
                    .into_iter()
                    .filter_map(|id| jobs.status(id, &shared.rig_info))
                    .collect(),
                shutting_down: shared.shutting_down.load(Ordering::SeqCst),
                rig_state: shared.rig_state_with(jobs.running()),
            }))
        }
        Request::Status { job_id: Some(id) } => status(shared, id).map(ReplyBody::JobStatus),
        Request::List { limit, before } => list(shared, limit, before).map(ReplyBody::List),
        Request::Cancel { job_id } => cancel(shared, job_id).map(ReplyBody::Cancel),
        Request::Result { job_id } => result(shared, job_id).map(ReplyBody::Result),
        Request::Pause { job_id } => pausing::pause(shared, job_id).map(ReplyBody::Pause),
        Request::Resume { job_id } => pausing::resume(shared, job_id).map(ReplyBody::Pause),
        Request::Subscribe { .. }
        | Request::Position {}
        | Request::Move { .. }
        | Request::Stop {}
        | Request::Unlock { .. }
        | Request::Home { .. }
        | Request::Reconnect { .. }
        | Request::Snap { .. }
        | Request::Preview { .. }
        | Request::PreviewStop {} => Err(ProtoError::new(
            ErrorCode::Internal,
            "subscribe and rig requests are handled by the connection",
        )),
    }
}

fn hello(shared: &Shared) -> HelloReply {
    let i = &shared.rig_info;
    HelloReply {
        protocol: PROTOCOL_VERSION,
        rigd: env!("CARGO_PKG_VERSION").into(),
        rig: RigSummary {
            mode: i.mode,
            axis_limits_um: i.axis_limits_um,
            piezo_limits_um: i.piezo_limits_um,
            default_start_um: i.default_start_um,
            scale_um_per_px: i.scale_um_per_px,
            frame_size: i.frame_size,
            job_defaults: i.job_defaults,
            axis_machine: i.axis_machine.clone(),
            camera: camera_of(&i.config),
        },
        data_root: shared.settings.data_root.clone(),
        rig_state: shared.rig_state(),
        capabilities: Capabilities::this_daemon(),
    }
}

/// The camera as the rig's recorded config names it: the sim's profile, or the configured
/// driver and device.
fn camera_of(config: &serde_json::Value) -> Option<String> {
    if config["sim"] == true {
        return Some(match config["camera_profile"].as_str() {
            Some(p) => format!("sim: {p}"),
            None => "sim".into(),
        });
    }
    let c = &config["camera"];
    let driver = c["driver"].as_str()?;
    Some(match c["device"].as_str() {
        Some(d) => format!("{driver}: {d}"),
        None => driver.to_string(),
    })
}

/// Check a job against the rig and the disk, and queue it.
fn submit(shared: &Shared, job: JobSpec) -> Result<SubmitReply, ProtoError> {
    refuse_if_stopping(shared)?;
    if let Some(f) = shared.rig().fault.clone() {
        return Err(ProtoError::new(ErrorCode::Rejected, f.refusal()));
    }
    crate::acquisition::calibration_job::check_submitted(&job).map_err(rejected)?;
    // What the client leaves out, the rig's configuration decides; the job is recorded and
    // echoed as resolved.
    let job = job.with_defaults(&shared.rig_info.job_defaults);
    let plan = plan(&job, &shared.rig_info, &shared.settings.data_root, 0).map_err(rejected)?;
    let queued = queue(
        shared,
        job.clone(),
        plan.clone(),
        &shared.rig_info,
        JobSource::Live,
    )?;
    let warnings = match &shared.rig_info.axis_machine {
        Some(m) => crate::acquisition::motor_steps::warnings(&job, &plan, m),
        None => Vec::new(),
    };
    for w in &warnings {
        tracing::warn!(job = queued.id, "{w}");
    }
    Ok(SubmitReply {
        warnings,
        ..announce(shared, queued, job, &plan)
    })
}

/// Where a job was queued and the memory its processing was estimated to hold.
struct Queued {
    id: u64,
    ahead: usize,
    memory_bytes: u64,
}

/// Check a planned job against the budgets and queue it. The disk must hold it next to what
/// the queued and running jobs will still write; the table stays locked from the checks to
/// the queueing so two submits cannot both count on the same free space, nor miss a
/// calibration job queued between them.
fn queue(
    shared: &Shared,
    job: JobSpec,
    plan: Plan,
    rig: &crate::rig::RigInfo,
    source: JobSource,
) -> Result<Queued, ProtoError> {
    // The current calibration is read before the table is locked (it is a file); a scan
    // pending then and finished before the lock still counts.
    let scan_pending = calibration_pending(&shared.jobs());
    let learnt = current_calibration_has_prior(shared);
    let mut jobs = shared.jobs();
    let prior = learnt || scan_pending || calibration_pending(&jobs);
    let budget_mb = shared.settings.max_job_memory_mb;
    let memory_bytes = budget::check_memory(&plan, rig, budget_mb, prior).map_err(rejected)?;
    let disk = budget::disk_bytes(&plan, rig);
    let committed = jobs.committed_disk_bytes();
    check_disk(&plan, rig, &shared.settings.data_root, committed).map_err(rejected)?;
    let (id, ahead) = jobs.submit(job, plan, source, disk).map_err(|e| match e {
        QueueError::Full => ProtoError::new(ErrorCode::Unavailable, e.to_string()),
        QueueError::Id(e) => ProtoError::new(ErrorCode::Internal, e.to_string()),
    })?;
    Ok(Queued {
        id,
        ahead,
        memory_bytes,
    })
}

/// Whether a calibration job is running or queued: it may learn an ink prior that the jobs
/// queued behind it take (counted as if it will: the memory estimate errs high, not low).
fn calibration_pending(jobs: &crate::daemon::Jobs) -> bool {
    jobs.pending().any(|r| r.spec.calibrate.is_some())
}

/// Whether the current calibration learnt an ink prior, which every job takes when it runs.
fn current_calibration_has_prior(shared: &Shared) -> bool {
    crate::calibration_store::current(&shared.settings.data_root)
        .ok()
        .flatten()
        .is_some_and(|a| a.calibration.ink.as_ref().and_then(|i| i.prior()).is_some())
}

fn refuse_if_stopping(shared: &Shared) -> Result<(), ProtoError> {
    if shared.shutting_down.load(Ordering::SeqCst) {
        return Err(ProtoError::new(
            ErrorCode::Unavailable,
            "the daemon is shutting down",
        ));
    }
    Ok(())
}

/// Tell subscribers and the worker about a queued job; the submit reply.
fn announce(shared: &Shared, queued: Queued, job: JobSpec, plan: &Plan) -> SubmitReply {
    let Queued {
        id,
        ahead,
        memory_bytes,
    } = queued;
    let total_frames = plan.total_frames;
    shared.events.emit(
        id,
        EventBody::Accepted {
            queue_position: ahead,
            total_frames,
            job: Some(Box::new(job.clone())),
        },
    );
    shared.wake.notify_one();
    SubmitReply {
        job_id: id,
        queue_position: ahead,
        total_frames,
        job,
        memory_mb: memory_bytes.div_ceil(1 << 20),
        resumed_from: None,
        warnings: Vec::new(),
    }
}

/// Check an interrupted session's job against the rig as a submit is, and queue it to take
/// the frames from the session's first missing one on (`daemon::resuming`).
fn resume(shared: &Shared, name: &str) -> Result<SubmitReply, ProtoError> {
    refuse_if_stopping(shared)?;
    if let Some(f) = shared.rig().fault.clone() {
        return Err(ProtoError::new(ErrorCode::Rejected, f.refusal()));
    }
    let dir = session_dir(shared, name)?;
    let root = &shared.settings.data_root;
    let (spec, plan, origin) =
        resuming::resume_job(root, &dir, &shared.rig_info).map_err(|e| match e {
            ResumeError::NotFound(m) => not_found(m),
            ResumeError::Rejected(m) => ProtoError::new(ErrorCode::Rejected, m),
        })?;
    let link = origin.link.clone();
    let source = JobSource::Resume(std::sync::Arc::new(origin));
    let queued = queue(shared, spec.clone(), plan.clone(), &shared.rig_info, source)?;
    let mut reply = announce(shared, queued, spec, &plan);
    reply.resumed_from = Some(link);
    Ok(reply)
}

fn list(shared: &Shared, limit: Option<u32>, before: Option<u64>) -> Result<ListReply, ProtoError> {
    // The statuses are copied out first: the disk is not read under the table's lock.
    let jobs: Vec<JobStatus> = shared.jobs().statuses(&shared.rig_info);
    listing::page(jobs, &shared.settings.data_root, limit, before)
}

fn cancel(shared: &Shared, job_id: u64) -> Result<CancelReply, ProtoError> {
    let ended = shared.jobs().cancel(job_id).map_err(|e| match e {
        CancelRefused::NotFound(m) => ProtoError::new(ErrorCode::NotFound, m),
        CancelRefused::TooLate(m) => ProtoError::new(ErrorCode::Rejected, m),
    })?;
    if ended {
        let body = EventBody::cancelled_in_queue("cancelled by a client before it started");
        shared.events.emit(job_id, body);
    }
    Ok(CancelReply {
        job_id,
        state: match ended {
            true => CancelState::Cancelled,
            false => CancelState::Cancelling,
        },
    })
}

fn result(shared: &Shared, job_id: u64) -> Result<ResultReply, ProtoError> {
    let (state, name) = {
        let jobs = shared.jobs();
        match jobs.get(job_id) {
            Some(r) => (Some(r.state), r.session.clone()),
            None => (None, None),
        }
    };
    if let Some(s) = state {
        if !s.is_done() {
            return Err(ProtoError::new(
                ErrorCode::NotFound,
                format!("job {job_id} is {s:?}: no result yet").to_lowercase(),
            ));
        }
    }
    let s = match name {
        Some(n) => Session::open(&shared.settings.data_root.join(&n)).ok(),
        None => find_session(shared, job_id),
    }
    .ok_or_else(|| not_found(format!("no session of job {job_id}")))?;
    Ok(ResultReply {
        job_id,
        session: s.manifest.name.clone(),
        state: s.manifest.state,
        reason: s.manifest.reason.clone(),
        result: s.result(),
    })
}

/// A job's status: from the table, else from its session on disk.
pub fn status(shared: &Shared, id: u64) -> Result<JobStatus, ProtoError> {
    if let Some(st) = shared.jobs().status(id, &shared.rig_info) {
        return Ok(st);
    }
    let s = find_session(shared, id).ok_or_else(|| not_found(format!("no job {id}")))?;
    let state = match s.manifest.state {
        session::SessionState::Finished => JobState::Finished,
        session::SessionState::Cancelled => JobState::Cancelled,
        _ => JobState::Failed,
    };
    Ok(JobStatus {
        job_id: id,
        state,
        label: s.manifest.job.label.clone(),
        replay_of: s.manifest.replay_of.clone(),
        session: Some(s.manifest.name.clone()),
        frames_done: s.steps.len() as u32,
        total_frames: s.manifest.plan.total_frames,
        reason: s.manifest.reason.clone(),
        timing: session_timing(&s.manifest),
    })
}

/// A recorded job's start, end and run time, from its manifest.
pub fn session_timing(m: &session::Manifest) -> JobTiming {
    let ended = !matches!(m.state, session::SessionState::Running);
    JobTiming {
        started_at: rfc3339_unix(m.created_unix_s),
        ended_at: ended.then(|| rfc3339_unix(m.updated_unix_s)).flatten(),
        elapsed_s: ended.then(|| (m.updated_unix_s - m.created_unix_s).max(0.0)),
        ..JobTiming::default()
    }
}

fn find_session(shared: &Shared, id: u64) -> Option<Session> {
    listing::find(&shared.settings.data_root, id)
}

/// A session name from a client, confined to the data root.
fn session_dir(shared: &Shared, name: &str) -> Result<std::path::PathBuf, ProtoError> {
    if crate::bounds::one_component("session", name).is_err() {
        return Err(ProtoError::new(
            ErrorCode::Rejected,
            format!("{name:?} is not a session name (one plain folder name in the data root)"),
        ));
    }
    let dir = shared.settings.data_root.join(name);
    if !dir.join(session::MANIFEST).is_file() {
        return Err(not_found(format!("no session {name}")));
    }
    Ok(dir)
}
