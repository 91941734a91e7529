//! What each request does. Quick and synchronous: nothing here touches the rig; jobs are
//! only queued for the worker.

use crate::daemon::jobs::{JobSource, JobState};
use crate::daemon::plan::{estimated_bytes, plan, resolve_defaults};
use crate::daemon::protocol::{ErrorCode, EventBody, ProtoError, Request, PROTOCOL_VERSION};
use crate::daemon::replay::{replay_plan, replay_spec};
use crate::daemon::session::{self, Session};
use crate::daemon::Shared;
use serde_json::{json, Value};
use std::sync::atomic::Ordering;

fn not_found(msg: String) -> ProtoError {
    ProtoError::new(ErrorCode::NotFound, msg)
}

/// Handle every request but `subscribe` (the connection owns subscriptions).
pub fn handle(shared: &Shared, req: Request) -> Result<Value, ProtoError> {
    match req {
        Request::Hello => {
            let i = &shared.rig_info;
            Ok(json!({
                "protocol": PROTOCOL_VERSION,
                "rigd": env!("CARGO_PKG_VERSION"),
                "rig": {
                    "mode": i.mode,
                    "axis_limits_um": i.axis_limits_um,
                    "piezo_limits_um": i.piezo_limits_um,
                    "default_start_um": i.default_start_um,
                    "scale_um_per_px": i.scale_um_per_px,
                    "frame_size": i.frame_size,
                    "job_defaults": i.job_defaults,
                },
                "data_root": shared.settings.data_root,
            }))
        }
        Request::Submit { job } => {
            refuse_if_stopping(shared)?;
            // What the client leaves out, the rig's configuration decides; the job is
            // recorded and echoed as resolved.
            let job = resolve_defaults(&job, &shared.rig_info.job_defaults);
            // The disk must hold this job next to what the queued and running ones will
            // still write; the table stays locked from the check to the queueing so two
            // submits cannot both count on the same free space.
            let info = &shared.rig_info;
            let mut jobs = shared.jobs();
            let committed: u64 = jobs
                .frames_left()
                .into_iter()
                .map(|n| estimated_bytes(n, info.frame_size))
                .sum();
            let plan = plan(&job, info, &shared.settings.data_root, committed)?;
            let total = plan.total_frames;
            let (id, ahead) = jobs.submit(job.clone(), plan, JobSource::Live);
            drop(jobs);
            Ok(announce(shared, id, ahead, job, total))
        }
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
            if let Some(k) = processing.k {
                if k == 0 || k > 64 {
                    return Err(ProtoError::new(
                        ErrorCode::Rejected,
                        format!("`k` must be 1..=64, got {k}"),
                    ));
                }
            }
            let spec = replay_spec(&s, &processing);
            let plan = replay_plan(&s, &processing);
            let total = plan.total_frames;
            let source = JobSource::Replay {
                dir,
                overrides: processing,
            };
            Ok(enqueue(shared, spec, plan, source, total))
        }
        Request::Status { job_id: None } => {
            let jobs = shared.jobs();
            Ok(json!({
                "running": jobs.running().and_then(|id| jobs.get(id)).map(|r| r.status()),
                "queued": jobs.queued(),
                "shutting_down": shared.shutting_down.load(Ordering::SeqCst),
            }))
        }
        Request::Status { job_id: Some(id) } => status(shared, id),
        Request::List => {
            let jobs: Vec<_> = shared.jobs().all().map(|r| r.status()).collect();
            let sessions: Vec<Value> = session::list(&shared.settings.data_root)
                .into_iter()
                .map(|s| {
                    let m = &s.manifest;
                    json!({
                        "name": m.name,
                        "job_id": m.job_id,
                        "state": m.state,
                        "reason": m.reason,
                        "frames_captured": s.steps.len(),
                        "total_frames": m.plan.total_frames,
                        "replay_of": m.replay_of,
                        "label": m.job.label,
                    })
                })
                .collect();
            Ok(json!({ "jobs": jobs, "sessions": sessions }))
        }
        Request::Cancel { job_id } => {
            let ended = shared
                .jobs()
                .cancel(job_id)
                .map_err(|e| ProtoError::new(ErrorCode::NotFound, e))?;
            if ended {
                shared
                    .events
                    .emit(job_id, EventBody::Cancelled { session: None });
            }
            Ok(json!({
                "job_id": job_id,
                "state": if ended { "cancelled" } else { "cancelling" },
            }))
        }
        Request::Result { job_id } => {
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
            Ok(json!({
                "job_id": job_id,
                "session": s.manifest.name,
                "state": s.manifest.state,
                "reason": s.manifest.reason,
                "result": s.result(),
            }))
        }
        Request::Subscribe { .. } => Err(ProtoError::new(
            ErrorCode::Internal,
            "subscribe is handled by the connection",
        )),
    }
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

fn enqueue(
    shared: &Shared,
    spec: crate::daemon::protocol::JobSpec,
    plan: crate::daemon::plan::Plan,
    source: JobSource,
    total: u32,
) -> Value {
    let (id, ahead) = shared.jobs().submit(spec.clone(), plan, source);
    announce(shared, id, ahead, spec, total)
}

/// Tell subscribers and the worker about a queued job; the submit reply.
fn announce(
    shared: &Shared,
    id: u64,
    ahead: usize,
    spec: crate::daemon::protocol::JobSpec,
    total: u32,
) -> Value {
    let job = serde_json::to_value(&spec).expect("plain data");
    shared.events.emit(
        id,
        EventBody::Accepted {
            queue_position: ahead,
            total_frames: total,
            job: Some(Box::new(spec)),
        },
    );
    shared.wake.notify_one();
    json!({ "job_id": id, "queue_position": ahead, "total_frames": total, "job": job })
}

/// A job's status: from the table, else from its session on disk.
pub fn status(shared: &Shared, id: u64) -> Result<Value, ProtoError> {
    if let Some(r) = shared.jobs().get(id) {
        return Ok(serde_json::to_value(r.status()).expect("plain data"));
    }
    let s = find_session(shared, id).ok_or_else(|| not_found(format!("no job {id}")))?;
    let state = match s.manifest.state {
        session::SessionState::Finished => JobState::Finished,
        session::SessionState::Cancelled => JobState::Cancelled,
        _ => JobState::Failed,
    };
    Ok(json!({
        "job_id": id,
        "state": state,
        "session": s.manifest.name,
        "frames_done": s.steps.len(),
        "total_frames": s.manifest.plan.total_frames,
        "reason": s.manifest.reason,
    }))
}

fn find_session(shared: &Shared, id: u64) -> Option<Session> {
    session::list(&shared.settings.data_root)
        .into_iter()
        .rev()
        .find(|s| s.manifest.job_id == id)
}

/// A session name from a client, confined to the data root.
fn session_dir(shared: &Shared, name: &str) -> Result<std::path::PathBuf, ProtoError> {
    if name.is_empty() || name.contains('/') || name.starts_with('.') {
        return Err(ProtoError::new(
            ErrorCode::Rejected,
            format!("{name:?} is not a session name"),
        ));
    }
    let dir = shared.settings.data_root.join(name);
    if !dir.join(session::MANIFEST).is_file() {
        return Err(not_found(format!("no session {name}")));
    }
    Ok(dir)
}
