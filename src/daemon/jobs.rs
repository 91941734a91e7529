//! The job table and queue: what was submitted, what runs, what waits. One job runs at a
//! time because the rig is exclusive.

use crate::acquisition::plan::Plan;
use crate::acquisition::{JobSpec, Processing, StopFlag};
use crate::daemon::job_ids::{JobIdError, JobIds};
use crate::daemon::resuming::Origin;
use crate::daemon::timing::{self, JobClock, JobTiming, Pending, Repeats, RigPace};
use crate::rig::RigInfo;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Instant, SystemTime};

/// Finished jobs kept in memory; older ones are still listed from their sessions on disk.
const KEEP_FINISHED: usize = 256;
/// Jobs that may wait in the queue: each holds its plan (a position per frame) in memory,
/// so the queue must not grow with what clients send.
pub const MAX_QUEUED: usize = 256;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    Queued,
    Running,
    /// Running, paused between steps or on a controller's feed hold.
    Paused,
    Finished,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn is_done(self) -> bool {
        matches!(
            self,
            JobState::Finished | JobState::Failed | JobState::Cancelled
        )
    }
}

#[derive(Debug, Clone)]
pub enum JobSource {
    Live,
    Replay {
        dir: PathBuf,
        overrides: Processing,
    },
    /// A live job resuming an interrupted session (`daemon::resuming`).
    Resume(Arc<Origin>),
}

impl JobSource {
    /// The job runs on the rig (a replay runs on its recorded session).
    pub fn uses_rig(&self) -> bool {
        !matches!(self, JobSource::Replay { .. })
    }
}

#[derive(Debug, Clone)]
pub struct JobRecord {
    pub id: u64,
    pub spec: JobSpec,
    pub plan: Plan,
    pub source: JobSource,
    pub state: JobState,
    pub session: Option<String>,
    pub frames_done: u32,
    pub reason: Option<String>,
    pub stop: Arc<StopFlag>,
    /// What the job writes, estimated at submit (`acquisition::budget::disk_bytes`).
    pub disk_bytes: u64,
    /// When it started and ended, its step intervals (`daemon::timing`).
    pub clock: JobClock,
    /// Its capture is over and its end decided: the worker closes its session. Too late
    /// for a cancel.
    pub closing: bool,
}

/// Why a cancel is refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CancelRefused {
    /// No such job, or it has ended.
    NotFound(String),
    /// It has captured everything it will and is closing its session.
    TooLate(String),
}

/// The public view of a job (status and list replies).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct JobStatus {
    pub job_id: u64,
    pub state: JobState,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub label: Option<String>,
    pub replay_of: Option<String>,
    pub session: Option<String>,
    pub frames_done: u32,
    pub total_frames: u32,
    pub reason: Option<String>,
    /// started_at, elapsed_s, eta_s & co. (`daemon::timing`).
    #[serde(flatten)]
    pub timing: JobTiming,
}

impl JobRecord {
    /// Its repeats as the timing counts them: frames in each and the interval between them.
    pub fn repeats(&self) -> Repeats {
        let count = self
            .plan
            .runs
            .iter()
            .map(|r| r.repeat + 1)
            .max()
            .unwrap_or(1);
        Repeats::of(self.plan.total_frames, count, self.spec.interval_s)
    }

    /// Its status with the timing it knows alone (start, end, elapsed); the table's
    /// [`Jobs::status`] adds the estimates, which need the queue.
    pub fn status(&self) -> JobStatus {
        JobStatus {
            job_id: self.id,
            state: self.state,
            label: self.spec.label.clone(),
            replay_of: match &self.source {
                JobSource::Replay { dir, .. } => {
                    dir.file_name().map(|n| n.to_string_lossy().into_owned())
                }
                JobSource::Live | JobSource::Resume(_) => None,
            },
            session: self.session.clone(),
            frames_done: self.frames_done,
            total_frames: self.plan.total_frames,
            reason: self.reason.clone(),
            timing: timing::ended_or_running(&self.clock, Instant::now()),
        }
    }
}

/// Why a job was not queued.
#[derive(Debug, thiserror::Error)]
pub enum QueueError {
    #[error("the queue is full ({MAX_QUEUED} jobs wait): submit again once some have run")]
    Full,
    #[error(transparent)]
    Id(#[from] JobIdError),
}

pub struct Jobs {
    ids: JobIds,
    table: BTreeMap<u64, JobRecord>,
    queue: VecDeque<u64>,
    running: Option<u64>,
    finished_order: VecDeque<u64>,
    /// The rig's recent step intervals, for the estimates of jobs not yet measured.
    pace: RigPace,
}

impl Jobs {
    /// A table handing out `ids`.
    pub fn new(ids: JobIds) -> Jobs {
        Jobs {
            ids,
            table: BTreeMap::new(),
            queue: VecDeque::new(),
            running: None,
            finished_order: VecDeque::new(),
            pace: RigPace::default(),
        }
    }

    /// Queue a job; returns its id and how many jobs are ahead of it. Refused when the
    /// queue is full or the id cannot be recorded.
    pub fn submit(
        &mut self,
        spec: JobSpec,
        plan: Plan,
        source: JobSource,
        disk_bytes: u64,
    ) -> Result<(u64, usize), QueueError> {
        if self.queue.len() >= MAX_QUEUED {
            return Err(QueueError::Full);
        }
        let id = self.ids.take()?;
        // A resumed plan's frames before its first one are done (the original's).
        let frames_done = plan.first_index;
        self.table.insert(
            id,
            JobRecord {
                id,
                spec,
                plan,
                source,
                state: JobState::Queued,
                session: None,
                frames_done,
                reason: None,
                stop: Arc::new(StopFlag::default()),
                disk_bytes,
                clock: JobClock::default(),
                closing: false,
            },
        );
        let ahead = self.queue.len() + usize::from(self.running.is_some());
        self.queue.push_back(id);
        Ok((id, ahead))
    }

    /// Take the next queued job and mark it running.
    pub fn start_next(&mut self) -> Option<JobRecord> {
        let id = self.queue.pop_front()?;
        self.running = Some(id);
        let rec = self.table.get_mut(&id)?;
        rec.state = JobState::Running;
        rec.clock.start(Instant::now(), SystemTime::now());
        Some(rec.clone())
    }

    pub fn get(&self, id: u64) -> Option<&JobRecord> {
        self.table.get(&id)
    }

    pub fn get_mut(&mut self, id: u64) -> Option<&mut JobRecord> {
        self.table.get_mut(&id)
    }

    pub fn running(&self) -> Option<u64> {
        self.running
    }

    pub fn queued(&self) -> Vec<u64> {
        self.queue.iter().copied().collect()
    }

    /// What the running and queued jobs have yet to write: each one's estimate, less the
    /// share of the frames it has captured.
    pub fn committed_disk_bytes(&self) -> u64 {
        self.pending()
            .map(|r| {
                // Of the frames this job takes (a resumed one's from its first missing one).
                let total = r.plan.frames_to_capture().max(1) as u128;
                let done = r.frames_done.max(r.plan.first_index);
                let left = r.plan.total_frames.saturating_sub(done) as u128;
                (r.disk_bytes as u128 * left / total) as u64
            })
            .sum()
    }

    pub fn all(&self) -> impl Iterator<Item = &JobRecord> {
        self.table.values()
    }

    /// The running job and the queued ones.
    pub fn pending(&self) -> impl Iterator<Item = &JobRecord> {
        self.running
            .iter()
            .chain(self.queue.iter())
            .filter_map(|id| self.table.get(id))
    }

    /// Cancel: a queued job ends now (returns true); a running one is told to stop after
    /// its current step (returns false). Err if unknown or already done.
    pub fn cancel(&mut self, id: u64) -> Result<bool, CancelRefused> {
        let rec = self
            .table
            .get_mut(&id)
            .ok_or_else(|| CancelRefused::NotFound(format!("no job {id}")))?;
        match rec.state {
            JobState::Queued => {
                self.queue.retain(|&q| q != id);
                rec.state = JobState::Cancelled;
                rec.reason = Some("cancelled by a client before it started".into());
                self.retire(id);
                Ok(true)
            }
            JobState::Running | JobState::Paused if rec.closing => {
                Err(CancelRefused::TooLate(format!(
                    "job {id} has taken its last frame and is closing its session: too late \
                     to cancel (it ends as its capture did)"
                )))
            }
            JobState::Running | JobState::Paused => {
                rec.stop.cancel();
                Ok(false)
            }
            s => Err(CancelRefused::NotFound(
                format!("job {id} is already {s:?}").to_lowercase(),
            )),
        }
    }

    /// Record the end of the running job.
    pub fn finish(&mut self, id: u64, state: JobState, reason: Option<String>) {
        if let Some(rec) = self.table.get_mut(&id) {
            rec.state = state;
            rec.reason = reason;
        }
        if self.running == Some(id) {
            self.running = None;
        }
        self.retire(id);
    }

    /// Job `id` has `frames_done` frames on disk: count them, time the step.
    pub fn step_recorded(&mut self, id: u64, frames_done: u32) {
        let Some(rec) = self.table.get_mut(&id) else {
            return;
        };
        rec.frames_done = frames_done;
        let repeats = rec.repeats();
        let interval = rec.clock.step(Instant::now(), frames_done, &repeats);
        // A replay's pace is the disk's, not the rig's.
        if let (Some(dt), true) = (interval, rec.source.uses_rig()) {
            self.pace.record(dt, rec.spec.settle_ms as f64 / 1000.0);
        }
    }

    /// Job `id`'s status, with its start and end estimated from the queue ahead of it.
    pub fn status(&self, id: u64, rig: &RigInfo) -> Option<JobStatus> {
        let rec = self.table.get(&id)?;
        let mut st = rec.status();
        if !rec.state.is_done() {
            if let Some(t) = self.estimates(rig).remove(&id) {
                st.timing = t;
            }
        }
        Some(st)
    }

    /// Every job's status (in id order), estimates in.
    pub fn statuses(&self, rig: &RigInfo) -> Vec<JobStatus> {
        let mut est = self.estimates(rig);
        self.table
            .values()
            .map(|r| {
                let mut st = r.status();
                if let Some(t) = est.remove(&r.id) {
                    st.timing = t;
                }
                st
            })
            .collect()
    }

    /// The running and queued jobs' timings, by id.
    fn estimates(&self, rig: &RigInfo) -> BTreeMap<u64, JobTiming> {
        let pending = |id: &u64| {
            let r = self.table.get(id)?;
            let stage_ms = match r.spec.stage {
                crate::acquisition::StageKind::Axis => rig.axis_settle_ms,
                crate::acquisition::StageKind::Piezo => rig.piezo_settle_ms,
            };
            Some((
                *id,
                Pending {
                    clock: &r.clock,
                    // The estimate counts the frames this job takes.
                    frames_done: r.frames_done.saturating_sub(r.plan.first_index),
                    total_frames: r.plan.frames_to_capture(),
                    repeats: r.repeats(),
                    settle_s: r.spec.settle_ms as f64 / 1000.0,
                    stage_settle_s: stage_ms.unwrap_or(0) as f64 / 1000.0,
                },
            ))
        };
        let running = self.running.as_ref().and_then(pending);
        let (ids, queued): (Vec<u64>, Vec<Pending<'_>>) =
            self.queue.iter().filter_map(pending).unzip();
        let running_id = running.as_ref().map(|(id, _)| *id);
        let (r, q) = timing::estimate(
            &self.pace,
            running.map(|(_, p)| p),
            &queued,
            Instant::now(),
            SystemTime::now(),
        );
        let mut out: BTreeMap<u64, JobTiming> = ids.into_iter().zip(q).collect();
        if let (Some(id), Some(r)) = (running_id, r) {
            out.insert(id, r);
        }
        out
    }

    fn retire(&mut self, id: u64) {
        // A finished job's status needs only its frame count: its planned positions (8 bytes
        // a frame, up to 256 jobs kept) would let finished jobs hold hundreds of MB.
        if let Some(rec) = self.table.get_mut(&id) {
            rec.plan.runs = Vec::new();
            rec.clock.end(SystemTime::now());
        }
        self.finished_order.push_back(id);
        while self.finished_order.len() > KEEP_FINISHED {
            if let Some(old) = self.finished_order.pop_front() {
                self.table.remove(&old);
            }
        }
    }

    /// Take every queued job out (shutdown).
    pub fn drain_queue(&mut self) -> Vec<u64> {
        let ids: Vec<u64> = self.queue.drain(..).collect();
        for &id in &ids {
            if let Some(r) = self.table.get_mut(&id) {
                r.state = JobState::Cancelled;
                r.reason = Some("the daemon is shutting down".into());
            }
            self.retire(id);
        }
        ids
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquisition::plan::RunPlan;
    use crate::acquisition::CaseScan;
    use crate::daemon::job_ids::JobIds;

    fn plan(frames: u32) -> Plan {
        Plan {
            runs: vec![RunPlan {
                run: 0,
                case: CaseScan {
                    name: "scan".into(),
                    frames,
                    step_um: 50.0,
                    k: 1,
                },
                repeat: 0,
                positions_um: (0..frames).map(|i| 50.0 * i as f64).collect(),
                piezo_um: None,
                processing: None,
            }],
            total_frames: frames,
            first_index: 0,
        }
    }

    #[test]
    fn a_resumed_plan_counts_the_originals_frames_done_and_commits_only_its_own() {
        let mut jobs = Jobs::new(JobIds::in_memory(1));
        let resumed = Plan {
            first_index: 6,
            ..plan(12)
        };
        let (id, _) = jobs
            .submit(JobSpec::default(), resumed, JobSource::Live, 600)
            .unwrap();
        assert_eq!(jobs.get(id).unwrap().frames_done, 6);
        // Its 600 bytes are for the 6 frames it takes: all still to write.
        assert_eq!(jobs.committed_disk_bytes(), 600);
        jobs.start_next().unwrap();
        jobs.step_recorded(id, 9);
        assert_eq!(jobs.committed_disk_bytes(), 300);
        let st = jobs.get(id).unwrap().status();
        assert_eq!((st.frames_done, st.total_frames), (9, 12));
    }

    #[test]
    fn a_finished_job_keeps_its_frame_count_but_not_its_positions() {
        let mut jobs = Jobs::new(JobIds::in_memory(1));
        let spec = JobSpec::default();
        let (a, _) = jobs
            .submit(spec.clone(), plan(1000), JobSource::Live, 0)
            .unwrap();
        let (b, _) = jobs.submit(spec, plan(7), JobSource::Live, 0).unwrap();
        let running = jobs.start_next().unwrap();
        assert_eq!(running.plan.runs[0].positions_um.len(), 1000);
        jobs.finish(a, JobState::Finished, None);
        assert!(jobs.cancel(b).unwrap());
        for (id, frames) in [(a, 1000), (b, 7)] {
            let rec = jobs.get(id).unwrap();
            assert!(rec.plan.runs.is_empty(), "job {id} still holds its plan");
            assert_eq!(rec.status().total_frames, frames);
        }
    }
}
