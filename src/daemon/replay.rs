//! Replay: a recorded session run again, through the same runner and pipeline, with the
//! recorded processing settings or others. The rig it runs on is `rig::replay`; here, the job
//! it runs: the recorded spec and plan, cut to the frames the session holds.

use crate::daemon::protocol::{JobSpec, Processing};
use crate::daemon::session::Session;

/// The job spec to replay a session with: the recorded one, processing overridden, and
/// only as many frames as were captured (an incomplete session replays what it holds).
pub fn replay_spec(session: &Session, ov: &Processing) -> JobSpec {
    let mut spec = session.manifest.job.clone();
    if let Some(e) = ov.estimator {
        spec.estimator = Some(e);
    }
    if let Some(c) = ov.combine {
        spec.combine = Some(c);
    }
    if let Some(r) = ov.registration {
        spec.registration = Some(r);
    }
    if let Some(w) = ov.whole_frame {
        spec.whole_frame = Some(w);
    }
    spec.process = true;
    // The frames are already settled: replay as fast as the pipeline goes.
    spec.settle_ms = 0;
    spec
}

/// The recorded plan cut to the frames the session holds, with `k` overridden.
pub fn replay_plan(session: &Session, ov: &Processing) -> crate::daemon::plan::Plan {
    let mut plan = session.manifest.plan.clone();
    let mut left = session.steps.len();
    plan.runs.retain_mut(|r| {
        if left == 0 {
            return false;
        }
        let n = r.positions_um.len().min(left);
        r.positions_um.truncate(n);
        r.case.frames = n as u32;
        left -= n;
        if let Some(k) = ov.k {
            r.case.k = k;
        }
        true
    });
    plan.total_frames = plan.runs.iter().map(|r| r.positions_um.len() as u32).sum();
    plan
}
