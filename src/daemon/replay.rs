//! Replay: a recorded session run again, through the same runner and pipeline, with the
//! recorded processing settings or others. The rig it runs on is `rig::replay`; here, the job
//! it runs: the recorded spec and plan, cut to the frames the session holds.

use crate::acquisition::plan::{Plan, PlanError};
use crate::acquisition::{JobSpec, Processing};
use crate::session::Session;

/// The job and plan to replay a session with: the recorded job with processing
/// overridden, cut to the frames the session holds (an incomplete session replays what it
/// holds), every run's processing options rebuilt and checked as at submit.
pub fn replay_job(session: &Session, ov: &Processing) -> Result<(JobSpec, Plan), PlanError> {
    let mut spec = session.manifest.job.overridden(ov);
    spec.process = true;
    // The frames are already settled: replay as fast as the pipeline goes.
    spec.settle_ms = 0;
    let plan =
        session
            .manifest
            .plan
            .for_replay(session.steps.len(), &spec, ov, &session.manifest.rig)?;
    Ok((spec, plan))
}
