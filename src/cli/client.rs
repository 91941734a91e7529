//! A blocking client of the daemon's socket, shared by the rigctl subcommands.

use crate::cli::server_line::{self, Decoded};
use crate::daemon::protocol::{Event, EventBody, Request, ServerLine};
use anyhow::{anyhow, bail, Context};
use std::collections::VecDeque;
use std::io::{BufRead, BufReader, IsTerminal, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::text;

/// `--socket PATH`, taken by every subcommand that talks to the daemon.
#[derive(clap::Args, Debug, Clone)]
pub struct SocketArg {
    /// The daemon's socket (default: $RIGD_SOCKET, $XDG_RUNTIME_DIR/rigd.sock, /tmp/rigd-UID.sock).
    #[arg(long, value_name = "PATH")]
    pub socket: Option<PathBuf>,
}

impl SocketArg {
    pub fn path(&self) -> PathBuf {
        self.socket
            .clone()
            .unwrap_or_else(crate::config::default_socket)
    }
    pub fn connect(&self) -> anyhow::Result<Client> {
        Client::connect(&self.path())
    }
}

pub struct Client {
    reader: BufReader<UnixStream>,
    writer: UnixStream,
    next_id: u64,
    events: VecDeque<Event>,
}

impl Client {
    pub fn connect(path: &Path) -> anyhow::Result<Client> {
        let s = UnixStream::connect(path).with_context(|| {
            format!(
                "cannot connect to rigd at {} (is it running?)",
                path.display()
            )
        })?;
        Ok(Client {
            reader: BufReader::new(s.try_clone()?),
            writer: s,
            next_id: 1,
            events: VecDeque::new(),
        })
    }

    /// The next line this client knows: lines and event kinds of a newer daemon are skipped
    /// (`server_line`).
    fn read_line(&mut self) -> anyhow::Result<ServerLine> {
        loop {
            let mut line = String::new();
            if self.reader.read_line(&mut line)? == 0 {
                bail!("rigd closed the connection");
            }
            match server_line::decode(&line) {
                Ok(Decoded::Line(l)) => return Ok(*l),
                Ok(Decoded::Skipped(what)) => tracing::debug!("skipped {what} from rigd"),
                Err(e) => bail!("unreadable line from rigd: {e}: {}", line.trim_end()),
            }
        }
    }

    /// Send a request and wait for its reply; events read meanwhile are kept for later.
    pub fn request(&mut self, req: &Request) -> anyhow::Result<serde_json::Value> {
        let id = self.next_id;
        self.next_id += 1;
        let mut v = serde_json::to_value(req)?;
        v["id"] = id.into();
        v["v"] = crate::daemon::protocol::PROTOCOL_VERSION.into();
        let mut bytes = serde_json::to_vec(&v)?;
        bytes.push(b'\n');
        self.writer.write_all(&bytes)?;
        loop {
            match self.read_line()? {
                ServerLine::Event(e) => self.events.push_back(e),
                ServerLine::Reply(r) if r.id == Some(id.into()) => {
                    return match (r.ok, r.result, r.error) {
                        (true, Some(v), _) => Ok(v),
                        (true, None, _) => Ok(serde_json::Value::Null),
                        (false, _, Some(e)) => Err(anyhow!(
                            "rigd: {}: {}",
                            crate::text::wire_name(&e.code),
                            e.message
                        )),
                        (false, _, None) => Err(anyhow!("rigd refused the request")),
                    };
                }
                ServerLine::Reply(r) => {
                    if let Some(e) = r.error {
                        tracing::warn!("rigd: {}", e.message);
                    }
                }
            }
        }
    }

    /// The next event (after a `subscribe`).
    pub fn next_event(&mut self) -> anyhow::Result<Event> {
        if let Some(e) = self.events.pop_front() {
            return Ok(e);
        }
        loop {
            match self.read_line()? {
                ServerLine::Event(e) => return Ok(e),
                ServerLine::Reply(r) => {
                    if let Some(e) = r.error {
                        eprintln!("rigd: {}", e.message);
                    }
                }
            }
        }
    }
}

/// How a followed job ended.
pub struct Ended {
    pub body: EventBody,
}

impl Ended {
    pub fn ok(&self) -> bool {
        matches!(self.body, EventBody::Finished { .. })
    }
}

/// Follow job `id` until it ends, with a progress bar and ETA on stderr (unless `quiet`).
/// The client must already be subscribed (to this job or to all).
pub fn follow(c: &mut Client, id: u64, total: u32, quiet: bool) -> anyhow::Result<Ended> {
    follow_from(c, id, total, quiet, Pace::default(), 0)
}

/// The job's pace on this client's clock: frames per second since the job started, so
/// frames done before a client attached do not count as instant.
#[derive(Debug, Clone, Copy, Default)]
pub struct Pace {
    started: Option<Instant>,
    /// Frames of the plan done before the job started (a resumed session's original's):
    /// they do not count towards its rate.
    before: u32,
}

impl Pace {
    /// A job that has run `elapsed_s` (its status' `elapsed_s`) as of `now`.
    pub fn running_for(elapsed_s: f64, now: Instant) -> Pace {
        // The daemon's number: one no Duration holds counts as none.
        let back = Duration::try_from_secs_f64(elapsed_s.max(0.0)).unwrap_or_default();
        Pace {
            started: Some(now.checked_sub(back).unwrap_or(now)),
            before: 0,
        }
    }

    /// The same pace for a plan whose first `before` frames another session took.
    pub fn taken_before(self, before: u32) -> Pace {
        Pace { before, ..self }
    }

    /// Frames per second and seconds left, once the job has started and done a frame.
    pub fn rate_eta(&self, done: u32, total: u32, now: Instant) -> Option<(f64, f64)> {
        let dt = now.saturating_duration_since(self.started?).as_secs_f64();
        let taken = done.saturating_sub(self.before);
        if taken == 0 || dt <= 0.0 {
            return None;
        }
        let rate = taken as f64 / dt;
        Some((rate, total.saturating_sub(done) as f64 / rate))
    }

    /// "3.5 frames/s, 12 s left", or what is known before the first frame.
    pub fn describe(&self, done: u32, total: u32, now: Instant) -> String {
        match (self.started, self.rate_eta(done, total, now)) {
            (None, _) => "queued".into(),
            (Some(_), None) => "started".into(),
            (Some(_), Some((r, eta))) => {
                format!("{}, {} left", text::rate(r), text::duration(eta))
            }
        }
    }
}

/// [`follow`] a job that may have started already: `pace` from its status, `done` frames
/// on disk when the client attached.
pub fn follow_from(
    c: &mut Client,
    id: u64,
    total: u32,
    quiet: bool,
    mut pace: Pace,
    done: u32,
) -> anyhow::Result<Ended> {
    let log_lines = !quiet && !std::io::stderr().is_terminal();
    let bar = if quiet {
        indicatif::ProgressBar::hidden()
    } else {
        let b = indicatif::ProgressBar::new(total as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{prefix} [{bar:40}] {pos}/{len} frames  {msg}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        b.set_prefix(format!("job {id}"));
        b.set_position(done as u64);
        b.set_message(pace.describe(done, total, Instant::now()));
        b
    };
    loop {
        let e = c.next_event()?;
        if e.job_id != id {
            continue;
        }
        match &e.body {
            EventBody::Started { session: s, .. } => {
                pace = Pace::running_for(0.0, Instant::now()).taken_before(pace.before);
                bar.set_message(format!("started: session {s}"));
            }
            EventBody::Step {
                index,
                case,
                repeat,
                ..
            } => {
                let done = index + 1;
                bar.set_position(done as u64);
                let p = pace.describe(done, total, Instant::now());
                bar.set_message(format!("{p}  ({case}, repeat {repeat})"));
                // No bar off a terminal: a line at every tenth of the job instead.
                if log_lines && tenth(done, total) != tenth(done - 1, total) {
                    eprintln!("job {id}: {done}/{total} frames, {p}");
                }
            }
            EventBody::Result {
                run,
                error: Some(err),
                ..
            } => bar.println(format!("run {run}: {err}")),
            EventBody::Paused { reason, .. } => {
                bar.println(format!("job {id} paused: {reason} (rigctl resume {id})"))
            }
            EventBody::Resumed { next_index } => {
                bar.println(format!("job {id} resumed at frame {next_index}"))
            }
            b if b.is_terminal() => {
                bar.finish_and_clear();
                return Ok(Ended { body: e.body });
            }
            _ => {}
        }
    }
}

/// Which tenth of `total` frames `done` is in.
fn tenth(done: u32, total: u32) -> u64 {
    u64::from(done) * 10 / u64::from(total.max(1))
}

/// Print how a job ended; an error if it did not finish.
pub fn report_end(id: u64, end: &Ended) -> anyhow::Result<()> {
    match &end.body {
        EventBody::Finished { .. } => {
            eprintln!("job {id} finished");
            Ok(())
        }
        EventBody::Failed {
            reason, session, ..
        } => bail!(
            "job {id} failed: {reason}{}",
            session
                .as_ref()
                .map(|s| format!(" (session {s} keeps what was captured)"))
                .unwrap_or_default()
        ),
        EventBody::Cancelled {
            session, reason, ..
        } => bail!(
            "job {id} was cancelled{}{}",
            reason
                .as_ref()
                .map(|r| format!(": {r}"))
                .unwrap_or_default(),
            session
                .as_ref()
                .map(|s| format!(" (session {s})"))
                .unwrap_or_default()
        ),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_done_before_attaching_took_the_jobs_elapsed_time() {
        // Attached to a job that has run 10 s and done 20 of 40 frames: 2 frames/s, not
        // 20 frames in no time.
        let now = Instant::now() + Duration::from_secs(100);
        let pace = Pace::running_for(10.0, now);
        let (rate, eta) = pace.rate_eta(20, 40, now).unwrap();
        assert!((rate - 2.0).abs() < 1e-9 && (eta - 10.0).abs() < 1e-9);
        assert_eq!(pace.describe(20, 40, now), "2.0 frames/s, 10 s left");
        let later = now + Duration::from_secs(5);
        assert_eq!(pace.describe(30, 40, later), "2.0 frames/s, 5 s left");
        assert_eq!(Pace::default().describe(0, 40, now), "queued");
        assert_eq!(Pace::running_for(0.0, now).describe(0, 40, now), "started");
    }
}
