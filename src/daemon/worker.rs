//! The worker: takes queued jobs one at a time and runs each on a blocking thread with the
//! rig, then records how it ended.

use crate::daemon::jobs::{JobRecord, JobSource, JobState};
use crate::daemon::protocol::EventBody;
use crate::daemon::runner::{run_job, JobContext, Outcome};
use crate::daemon::session::{Session, SessionState, SessionWriter};
use crate::daemon::Shared;
use crate::rig::Rig;
use std::sync::atomic::Ordering;
use std::sync::Arc;

/// Run jobs until the daemon shuts down; returns the rig (stopped).
pub async fn run(shared: Arc<Shared>, mut rig: Rig) -> Rig {
    loop {
        let notified = shared.wake.notified();
        if shared.shutting_down.load(Ordering::SeqCst) {
            return rig;
        }
        let next = shared.jobs().start_next();
        let Some(job) = next else {
            notified.await;
            continue;
        };
        let sh = shared.clone();
        let handle = tokio::task::spawn_blocking(move || {
            execute(&sh, &job, &mut rig);
            rig
        });
        match handle.await {
            Ok(r) => rig = r,
            // The rig went down with a panicking job: nothing safe is left to drive.
            Err(e) => panic!("job thread panicked: {e}"),
        }
    }
}

/// Run one job start to finish, on the calling (blocking) thread.
fn execute(shared: &Shared, job: &JobRecord, live: &mut Rig) {
    let id = job.id;
    let emit = |body: EventBody| {
        if let EventBody::Step { index, .. } = &body {
            if let Some(r) = shared.jobs().get_mut(id) {
                r.frames_done = index + 1;
            }
        }
        shared.events.emit(id, body);
    };
    let fail = |reason: String, session: Option<String>| {
        tracing::warn!(job = id, %reason, "job failed");
        shared
            .jobs()
            .finish(id, JobState::Failed, Some(reason.clone()));
        shared
            .events
            .emit(id, EventBody::Failed { reason, session });
    };
    // A replay runs on a rig made of the recorded session; a live job on the rig.
    let mut replay;
    let (rig, replay_of): (&mut Rig, Option<String>) = match &job.source {
        JobSource::Live => (live, None),
        JobSource::Replay { dir, .. } => match Session::open(dir).and_then(|s| {
            let rig = crate::rig::replay(&s)?;
            Ok((rig, s.manifest.name))
        }) {
            Ok((r, name)) => {
                replay = r;
                (&mut replay, Some(name))
            }
            Err(e) => return fail(e.to_string(), None),
        },
    };
    let mut session = match SessionWriter::create(
        &shared.settings.data_root,
        id,
        &job.spec,
        &job.plan,
        &rig.info,
        replay_of,
    ) {
        Ok(s) => s,
        Err(e) => return fail(format!("disk: {e}"), None),
    };
    let name = session.name().to_string();
    if let Some(r) = shared.jobs().get_mut(id) {
        r.session = Some(name.clone());
    }
    tracing::info!(job = id, session = %name, frames = job.plan.total_frames, "job started");
    shared.events.emit(
        id,
        EventBody::Started {
            session: name.clone(),
            total_frames: job.plan.total_frames,
        },
    );
    let ctx = JobContext {
        spec: &job.spec,
        plan: &job.plan,
        stop: &job.stop,
        emit: &emit,
    };
    let out = run_job(&ctx, rig, &mut session);
    let images: Vec<_> = out.images;
    let wrote = session.write_result(&out.result, &images);
    // A write failing while closing keeps the job's own reason first (on a full disk that
    // names the frame that did not fit).
    let earlier = match &out.outcome {
        Outcome::Finished => String::new(),
        Outcome::Failed(r) | Outcome::Cancelled(r) => format!("{r}; "),
    };
    let (state, jstate, reason) = match (&out.outcome, wrote) {
        (_, Err(e)) => (
            SessionState::Failed,
            JobState::Failed,
            Some(format!("{earlier}disk: {e}")),
        ),
        (Outcome::Finished, Ok(())) => (SessionState::Finished, JobState::Finished, None),
        (Outcome::Failed(r), Ok(())) => (SessionState::Failed, JobState::Failed, Some(r.clone())),
        (Outcome::Cancelled(r), Ok(())) => (
            SessionState::Cancelled,
            JobState::Cancelled,
            Some(r.clone()),
        ),
    };
    let closed = session.close(state, reason.clone());
    let (jstate, reason) = match closed {
        Err(e) => {
            let earlier = reason.map(|r| format!("{r}; ")).unwrap_or_default();
            (JobState::Failed, Some(format!("{earlier}disk: {e}")))
        }
        Ok(()) => (jstate, reason),
    };
    tracing::info!(job = id, state = ?jstate, reason = ?reason, "job ended");
    shared.jobs().finish(id, jstate, reason.clone());
    let body = match jstate {
        JobState::Finished => EventBody::Finished { session: name },
        JobState::Cancelled => EventBody::Cancelled {
            session: Some(name),
        },
        _ => EventBody::Failed {
            reason: reason.unwrap_or_default(),
            session: Some(name),
        },
    };
    shared.events.emit(id, body);
}
