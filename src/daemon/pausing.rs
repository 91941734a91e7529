//! `pause` and `resume`: a running job pauses at its next step boundary (the
//! engine takes the pause: `acquisition::pause`), a paused one goes on with its next frame.
//! The engine tells the daemon through a listener installed for the job's run: the job's
//! state becomes `paused` (and `running` again) and the `paused`/`resumed` events go out.
//! A paused job can be cancelled: it ends `cancelled` at once, the stage where it was.

use crate::acquisition::{PauseCause, PauseEvent, PauseState};
use crate::daemon::jobs::{JobRecord, JobState};
use crate::daemon::protocol::{ErrorCode, EventBody, ProtoError};
use crate::daemon::Shared;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Where a pause or resume leaves the job.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum PauseReplyState {
    /// Asked: the job pauses at its next step boundary (the `paused` event says when).
    Pausing,
    /// Already paused.
    Paused,
    /// Going on (or a pause not yet taken withdrawn).
    Resumed,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct PauseReply {
    pub job_id: u64,
    pub state: PauseReplyState,
}

fn not_running(id: u64, r: Option<&JobRecord>, what: &str) -> ProtoError {
    match r {
        None => ProtoError::new(ErrorCode::NotFound, format!("no job {id}")),
        Some(r) => ProtoError::new(
            ErrorCode::Rejected,
            format!(
                "job {id} is {}: only a running job can be {what}",
                state_name(r.state)
            ),
        ),
    }
}

pub fn state_name(s: JobState) -> &'static str {
    match s {
        JobState::Queued => "queued",
        JobState::Running => "running",
        JobState::Paused => "paused",
        JobState::Finished => "finished",
        JobState::Failed => "failed",
        JobState::Cancelled => "cancelled",
    }
}

pub fn pause(shared: &Shared, id: u64) -> Result<PauseReply, ProtoError> {
    let jobs = shared.jobs();
    let rec = jobs.get(id);
    match rec.map(|r| r.state) {
        Some(JobState::Running | JobState::Paused) => {}
        _ => return Err(not_running(id, rec, "paused")),
    }
    let rec = rec.expect("checked above");
    if rec.stop.cause().is_some() {
        return Err(ProtoError::new(
            ErrorCode::Rejected,
            format!("job {id} is stopping: it cannot be paused"),
        ));
    }
    let state = match rec.stop.pause.request() {
        PauseState::Paused => PauseReplyState::Paused,
        _ => PauseReplyState::Pausing,
    };
    Ok(PauseReply { job_id: id, state })
}

pub fn resume(shared: &Shared, id: u64) -> Result<PauseReply, ProtoError> {
    let jobs = shared.jobs();
    let rec = jobs.get(id);
    match rec.map(|r| r.state) {
        Some(JobState::Running | JobState::Paused) => {}
        _ => return Err(not_running(id, rec, "resumed")),
    }
    let rec = rec.expect("checked above");
    if rec.stop.cause().is_some() {
        return Err(ProtoError::new(
            ErrorCode::Rejected,
            format!("job {id} is stopping (cancelled): it cannot be resumed"),
        ));
    }
    match rec.stop.pause.release() {
        PauseState::Running => Err(ProtoError::new(
            ErrorCode::Rejected,
            format!("job {id} is not paused"),
        )),
        _ => Ok(PauseReply {
            job_id: id,
            state: PauseReplyState::Resumed,
        }),
    }
}

/// Hear the engine's pauses for job `id` (until [`unlisten`]).
pub fn listen(shared: &Arc<Shared>, job: &JobRecord) {
    let id = job.id;
    let sh = shared.clone();
    job.stop.pause.listen(Some(Box::new(move |ev| {
        let (state, body) = event(ev);
        if let Some(r) = sh.jobs().get_mut(id) {
            if !r.state.is_done() {
                r.state = state;
                // The estimate stands still while paused.
                let now = std::time::Instant::now();
                match state {
                    JobState::Paused => r.clock.pause(now),
                    _ => r.clock.resume(now),
                }
            }
        }
        sh.events.emit(id, body);
    })));
}

/// The job's run is over: drop the listener (it holds the daemon's state).
pub fn unlisten(job: &JobRecord) {
    job.stop.pause.listen(None);
}

fn event(ev: &PauseEvent) -> (JobState, EventBody) {
    match ev {
        PauseEvent::Paused {
            next_index,
            at_um,
            cause,
        } => (
            JobState::Paused,
            EventBody::Paused {
                next_index: *next_index,
                at_um: *at_um,
                cause: match cause {
                    PauseCause::Client => "client",
                    PauseCause::FeedHold { .. } => "feed_hold",
                }
                .into(),
                reason: ev.reason(),
            },
        ),
        PauseEvent::Resumed { next_index } => (
            JobState::Running,
            EventBody::Resumed {
                next_index: *next_index,
            },
        ),
    }
}
