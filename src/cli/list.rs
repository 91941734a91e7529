//! `rigctl list`: jobs of this daemon run and the sessions on disk, newest first (every
//! page of the daemon's paged `list`), as aligned tables; `--json` for machines.

use crate::cli::client::{Client, SocketArg};
use crate::daemon::protocol::EtaBasis;
use crate::daemon::protocol::JobStatus;
use crate::daemon::protocol::{ListReply, Request, SessionSummary, LIST_MAX};
use crate::text::{duration, short_time, wire_name, Table};

#[derive(clap::Args, Debug)]
pub struct ListArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// Print the reply as JSON (every page in one object: jobs, sessions).
    #[arg(long)]
    pub json: bool,
}

/// Every page of `list`, newest first: the jobs and the sessions of all pages together.
pub fn fetch_all(c: &mut Client) -> anyhow::Result<(Vec<JobStatus>, Vec<SessionSummary>)> {
    let (mut jobs, mut sessions) = (Vec::new(), Vec::new());
    let mut before = None;
    loop {
        let r = c.request(&Request::List {
            limit: Some(LIST_MAX),
            before,
        })?;
        let page: ListReply = serde_json::from_value(r)?;
        jobs.extend(page.jobs);
        sessions.extend(page.sessions);
        match page.next_before {
            // Ids fall page after page; one that does not is a daemon bug, not a loop.
            Some(b) if before.is_none_or(|p| b < p) => before = Some(b),
            _ => break,
        }
    }
    Ok((jobs, sessions))
}

/// The jobs as a table: state, frames, when each started (or is expected to), how long it
/// has run and how long it has left.
pub fn jobs_table(jobs: &[JobStatus]) -> Table {
    let mut t = Table::new(&[
        ">job",
        "state",
        ">frames",
        "started (UTC)",
        ">elapsed",
        ">ETA",
        "ETA from",
        "session / label",
    ]);
    for j in jobs {
        let tm = &j.timing;
        let started = match (&tm.started_at, &tm.expected_start_at) {
            (Some(s), _) => short_time(s),
            (None, Some(s)) => format!("~{}", short_time(s)),
            (None, None) => "—".into(),
        };
        let basis = tm.eta_basis.map(|b| match b {
            EtaBasis::Measured => "this job",
            EtaBasis::Rig => "rig's steps",
            EtaBasis::Settings => "settings",
        });
        let what = match (&j.session, &j.label) {
            (Some(s), Some(l)) => format!("{s} ({l})"),
            (Some(s), None) => s.clone(),
            (None, Some(l)) => l.clone(),
            (None, None) => "—".into(),
        };
        t.row(vec![
            j.job_id.to_string(),
            wire_name(&j.state),
            format!("{}/{}", j.frames_done, j.total_frames),
            started,
            tm.elapsed_s.map_or("—".into(), duration),
            tm.eta_s.map_or("—".into(), duration),
            basis.unwrap_or("—").into(),
            what,
        ]);
    }
    t
}

/// The sessions on disk as a table.
pub fn sessions_table(sessions: &[SessionSummary]) -> Table {
    let mut t = Table::new(&[
        "session",
        ">job",
        "state",
        ">frames",
        "started (UTC)",
        ">took",
        "reason / label",
    ]);
    for s in sessions {
        let origin = match (&s.resumed_from, &s.replay_of) {
            (Some(r), _) => Some(format!(
                "resumes {} from frame {}",
                r.session, r.first_index
            )),
            (None, Some(of)) => Some(format!("replay of {of}")),
            (None, None) => None,
        };
        let note = [origin.as_ref(), s.reason.as_ref().or(s.label.as_ref())]
            .into_iter()
            .flatten()
            .cloned()
            .collect::<Vec<_>>()
            .join("; ");
        t.row(vec![
            s.name.clone(),
            s.job_id.to_string(),
            wire_name(&s.state),
            format!("{}/{}", s.frames_captured, s.total_frames),
            s.timing
                .started_at
                .as_deref()
                .map_or("—".into(), short_time),
            s.timing.elapsed_s.map_or("—".into(), duration),
            note,
        ]);
    }
    t
}

pub fn run(a: ListArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let (jobs, sessions) = fetch_all(&mut c)?;
    if a.json {
        let v = serde_json::json!({"jobs": jobs, "sessions": sessions});
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    match jobs.is_empty() {
        true => println!("No jobs since this daemon started."),
        false => print!("Jobs of this daemon run:\n{}", jobs_table(&jobs).render()),
    }
    match sessions.is_empty() {
        true => println!("\nNo sessions on disk."),
        false => print!(
            "\nSessions on disk:\n{}",
            sessions_table(&sessions).render()
        ),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::session::{ResumedFrom, SessionState};

    #[test]
    fn a_resumed_session_names_the_one_it_resumes_and_its_first_frame() {
        let s = SessionSummary {
            name: "20261207T100000Z-job9".into(),
            job_id: 9,
            state: SessionState::Finished,
            reason: None,
            frames_captured: 14,
            total_frames: 20,
            replay_of: None,
            resumed_from: Some(ResumedFrom {
                session: "20261207T090000Z-job4".into(),
                first_index: 6,
            }),
            label: Some("scan".into()),
            timing: Default::default(),
        };
        let text = sessions_table(&[s]).render();
        assert!(
            text.contains("resumes 20261207T090000Z-job4 from frame 6; scan"),
            "{text}"
        );
    }
}
