//! The gateway's connections to the daemon's socket: the protocol's JSON lines over tokio.
//! One short connection per browser request; one long one per open page (events and the
//! preview). The daemon's socket permissions stay the gate: the gateway speaks as its user.

use crate::daemon::protocol::{Request, PROTOCOL_VERSION};
use serde_json::Value;
use std::path::{Path, PathBuf};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::unix::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::UnixStream;

/// One connection to the daemon.
pub struct Link {
    reader: BufReader<OwnedReadHalf>,
    writer: OwnedWriteHalf,
    next_id: u64,
    /// The line being read: kept across calls, so a `select!` that drops a read loses
    /// nothing (`read_until` appends).
    partial: Vec<u8>,
}

impl Link {
    pub async fn connect(socket: &Path) -> anyhow::Result<Link> {
        let s = UnixStream::connect(socket).await.map_err(|e| {
            anyhow::anyhow!(
                "cannot connect to rigd at {} (is it running?): {e}",
                socket.display()
            )
        })?;
        let (r, w) = s.into_split();
        Ok(Link {
            reader: BufReader::new(r),
            writer: w,
            next_id: 1,
            partial: Vec::new(),
        })
    }

    /// Send a request (a protocol object with `kind`); the id it was given.
    pub async fn send(&mut self, req: &Value) -> anyhow::Result<u64> {
        let id = self.next_id;
        self.next_id += 1;
        let mut v = req.clone();
        v["id"] = id.into();
        v["v"] = PROTOCOL_VERSION.into();
        let mut bytes = serde_json::to_vec(&v)?;
        bytes.push(b'\n');
        self.writer.write_all(&bytes).await?;
        Ok(id)
    }

    /// Send a typed request.
    pub async fn send_request(&mut self, req: &Request) -> anyhow::Result<u64> {
        self.send(&serde_json::to_value(req)?).await
    }

    /// The next line from the daemon, verbatim (without its newline). Cancel-safe.
    pub async fn next_line(&mut self) -> anyhow::Result<String> {
        if self.reader.read_until(b'\n', &mut self.partial).await? == 0
            || self.partial.last() != Some(&b'\n')
        {
            anyhow::bail!("rigd closed the connection");
        }
        let bytes = std::mem::take(&mut self.partial);
        let line = String::from_utf8(bytes)
            .map_err(|_| anyhow::anyhow!("a line from rigd that is not UTF-8"))?;
        Ok(line.trim_end().to_string())
    }

    /// Send `req` and wait for its reply line (events before it are dropped: this
    /// connection is not subscribed). The reply as the daemon wrote it.
    pub async fn ask(&mut self, req: &Value) -> anyhow::Result<Value> {
        let id = self.send(req).await?;
        loop {
            let line = self.next_line().await?;
            let v: Value = serde_json::from_str(&line)
                .map_err(|e| anyhow::anyhow!("unreadable line from rigd: {e}"))?;
            if v["type"] == "reply" && v["id"] == id {
                return Ok(v);
            }
        }
    }
}

/// Where the daemon is, shared by every handler.
#[derive(Clone, Debug)]
pub struct Daemon {
    pub socket: PathBuf,
}

impl Daemon {
    /// One request on a connection of its own: the daemon's reply object.
    pub async fn ask(&self, req: &Value) -> anyhow::Result<Value> {
        Link::connect(&self.socket).await?.ask(req).await
    }

    /// A typed request's `result`, or the daemon's error as text.
    pub async fn result(&self, req: &Request) -> anyhow::Result<Value> {
        let reply = self.ask(&serde_json::to_value(req)?).await?;
        if reply["ok"] == true {
            return Ok(reply["result"].clone());
        }
        anyhow::bail!(
            "rigd: {}: {}",
            reply["error"]["code"].as_str().unwrap_or("error"),
            reply["error"]["message"].as_str().unwrap_or("refused")
        )
    }

    /// The data root the daemon writes sessions under (its `hello`).
    pub async fn data_root(&self) -> anyhow::Result<PathBuf> {
        let hello = self.result(&Request::Hello {}).await?;
        hello["data_root"]
            .as_str()
            .map(PathBuf::from)
            .ok_or_else(|| anyhow::anyhow!("rigd's hello names no data_root"))
    }
}
