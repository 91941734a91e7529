//! `list` in pages, and finding a job's session, without reading every session on disk:
//! session folders are named `<UTC stamp>-job<id>[-n]`, so the job ids come from the names
//! (a folder named otherwise, renamed by hand, has its manifest read), and only the sessions
//! on the page are opened.

use crate::daemon::jobs::JobStatus;
use crate::daemon::protocol::{
    ErrorCode, ListReply, ProtoError, SessionSummary, LIST_DEFAULT, LIST_MAX,
};
use crate::session::{self, Session};
use std::path::Path;

/// Every session folder under `data_root` with its job id, newest (highest id) first; the
/// sessions of one id (recorded before ids were unique across restarts) newest name first.
pub fn index(data_root: &Path) -> Vec<(u64, String)> {
    let Ok(rd) = std::fs::read_dir(data_root) else {
        return Vec::new();
    };
    let mut v: Vec<(u64, String)> = rd
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().into_string().ok()?;
            if name.starts_with('.') || !e.path().join(session::MANIFEST).is_file() {
                return None;
            }
            let id = id_in_name(&name).or_else(|| manifest_job_id(&e.path()))?;
            Some((id, name))
        })
        .collect();
    v.sort_unstable_by(|a, b| b.cmp(a));
    v
}

/// `20261201T112233Z-job5` and `...-job5-2` name job 5.
fn id_in_name(name: &str) -> Option<u64> {
    let (_, rest) = name.split_once("-job")?;
    let digits = rest.split('-').next()?;
    digits.parse().ok()
}

fn manifest_job_id(dir: &Path) -> Option<u64> {
    #[derive(serde::Deserialize)]
    struct JobId {
        job_id: u64,
    }
    let max = crate::bounds::MAX_DOCUMENT_BYTES;
    let bytes = crate::nofollow::read_in_max(dir, session::MANIFEST, max).ok()?;
    serde_json::from_slice::<JobId>(&bytes)
        .ok()
        .map(|j| j.job_id)
}

/// The newest session of job `id`.
pub fn find(data_root: &Path, id: u64) -> Option<Session> {
    index(data_root)
        .into_iter()
        .filter(|(j, _)| *j == id)
        .find_map(|(_, name)| Session::open(&data_root.join(name)).ok())
        .filter(|s| s.manifest.job_id == id)
}

/// One page: up to `limit` jobs of the table and `limit` sessions, each with a job id below
/// `before`, newest first. `next_before` is set while either has more.
pub fn page(
    jobs: Vec<JobStatus>,
    data_root: &Path,
    limit: Option<u32>,
    before: Option<u64>,
) -> Result<ListReply, ProtoError> {
    let limit = limit.unwrap_or(LIST_DEFAULT);
    if limit == 0 || limit > LIST_MAX {
        return Err(ProtoError::new(
            ErrorCode::BadRequest,
            format!("`limit` must be 1..={LIST_MAX}, got {limit}"),
        ));
    }
    let limit = limit as usize;
    let below = |id: u64| before.is_none_or(|b| id < b);
    let mut jobs: Vec<JobStatus> = jobs.into_iter().filter(|j| below(j.job_id)).collect();
    jobs.sort_unstable_by_key(|j| std::cmp::Reverse(j.job_id));
    let more_jobs = jobs.len() > limit;
    jobs.truncate(limit);
    let on_disk: Vec<(u64, String)> = index(data_root)
        .into_iter()
        .filter(|(id, _)| below(*id))
        .collect();
    // A page ends between two job ids, never inside one's sessions.
    let mut cut = on_disk.len().min(limit);
    while cut > 0 && cut < on_disk.len() && on_disk[cut].0 == on_disk[cut - 1].0 {
        cut += 1;
    }
    let more_sessions = cut < on_disk.len();
    // The page is every job and session with an id in [next_before, before): the boundary
    // is the higher last id among the lists that go on, the other list cut to it.
    let boundary = [
        more_jobs.then(|| jobs.last().map(|j| j.job_id)).flatten(),
        more_sessions.then(|| on_disk[cut - 1].0),
    ]
    .into_iter()
    .flatten()
    .max();
    let at_or_above = |id: u64| boundary.is_none_or(|b| id >= b);
    jobs.retain(|j| at_or_above(j.job_id));
    let sessions: Vec<SessionSummary> = on_disk[..cut]
        .iter()
        .filter(|(id, _)| at_or_above(*id))
        .filter_map(|(_, name)| Session::open(&data_root.join(name)).ok())
        .map(|s| summary(&s))
        .collect();
    Ok(ListReply {
        jobs,
        sessions,
        next_before: boundary,
    })
}

fn summary(s: &Session) -> SessionSummary {
    let m = &s.manifest;
    SessionSummary {
        name: m.name.clone(),
        job_id: m.job_id,
        state: m.state,
        reason: m.reason.clone(),
        frames_captured: s.steps.len(),
        total_frames: m.plan.total_frames,
        replay_of: m.replay_of.clone(),
        resumed_from: m.resumed_from.clone(),
        label: m.job.label.clone(),
        timing: crate::daemon::commands::session_timing(m),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn job_ids_are_read_from_session_names() {
        assert_eq!(id_in_name("20261201T112233Z-job5"), Some(5));
        assert_eq!(id_in_name("20261201T112233Z-job5-2"), Some(5));
        assert_eq!(id_in_name("my-copy"), None);
    }
}
