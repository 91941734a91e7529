//! A blocking client of the daemon's socket, shared by the rigctl subcommands.

use crate::daemon::protocol::{Event, EventBody, Request, ServerLine};
use anyhow::{anyhow, bail, Context};
use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};

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

    fn read_line(&mut self) -> anyhow::Result<ServerLine> {
        let mut line = String::new();
        if self.reader.read_line(&mut line)? == 0 {
            bail!("rigd closed the connection");
        }
        serde_json::from_str(&line).with_context(|| format!("unreadable line from rigd: {line}"))
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
                        (false, _, Some(e)) => Err(anyhow!("rigd: {:?}: {}", e.code, e.message)),
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
    let bar = if quiet {
        indicatif::ProgressBar::hidden()
    } else {
        let b = indicatif::ProgressBar::new(total as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{prefix} [{bar:40}] {pos}/{len} frames {per_sec} ETA {eta} {msg}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        b.set_prefix(format!("job {id}"));
        b
    };
    loop {
        let e = c.next_event()?;
        if e.job_id != id {
            continue;
        }
        match &e.body {
            EventBody::Started { session, .. } => bar.set_message(session.clone()),
            EventBody::Step {
                index,
                case,
                repeat,
                ..
            } => {
                bar.set_position(*index as u64 + 1);
                bar.set_message(format!("{case} r{repeat}"));
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

/// Print how a job ended; an error if it did not finish.
pub fn report_end(id: u64, end: &Ended) -> anyhow::Result<()> {
    match &end.body {
        EventBody::Finished { session } => {
            eprintln!("job {id} finished: session {session}");
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
