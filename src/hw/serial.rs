//! Line I/O over a serial port, with a deadline on every read.
//!
//! Controllers answer in lines (GRBL `\r\n`, PI GCS `\n`); this splits the byte stream at
//! `\n`, drops a trailing `\r`, and turns the port's failures into [`HwError`]s: nothing
//! within the deadline is `Timeout`, a hangup or I/O error is `PortGone` (the port must be
//! reopened), a read of zero bytes (EOF) likewise.
//!
//! [`SerialLink`] keeps one such port for a driver: opened on first use, dropped when it
//! vanishes and reopened on the next call, drained when a reply may still be in flight.
//! [`OverSerial`] is what a driver adds to it: the handshake after each open.

use super::HwError;
use serialport::SerialPort;
use std::io::{Read, Write};
use std::time::{Duration, Instant};

/// One open serial port, read line by line.
pub struct SerialLines {
    device: String,
    path: String,
    port: Box<dyn SerialPort>,
    buf: Vec<u8>,
}

impl std::fmt::Debug for SerialLines {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SerialLines")
            .field("device", &self.device)
            .field("path", &self.path)
            .finish()
    }
}

/// Longest line we buffer before declaring the stream garbage.
const MAX_LINE: usize = 4096;

impl SerialLines {
    /// Open `path` at `baud`, 8N1, no flow control. `device` names it in errors.
    pub fn open(device: &str, path: &str, baud: u32) -> Result<SerialLines, HwError> {
        let port = serialport::new(path, baud)
            .timeout(Duration::from_millis(10))
            .open()
            .map_err(|e| HwError::PortGone {
                device: device.to_string(),
                message: format!("cannot open {path}: {e}"),
            })?;
        Ok(SerialLines {
            device: device.to_string(),
            path: path.to_string(),
            port,
            buf: Vec::new(),
        })
    }

    pub fn path(&self) -> &str {
        &self.path
    }

    fn gone(&self, what: &str, e: impl std::fmt::Display) -> HwError {
        HwError::PortGone {
            device: self.device.clone(),
            message: format!("{what} {}: {e}", self.path),
        }
    }

    /// Write all bytes and flush them out.
    pub fn write(&mut self, bytes: &[u8]) -> Result<(), HwError> {
        self.port
            .write_all(bytes)
            .and_then(|_| self.port.flush())
            .map_err(|e| self.gone("writing to", e))
    }

    /// The next line (without its terminator), waiting until `deadline` at most.
    pub fn read_line(&mut self, deadline: Deadline, waiting_for: &str) -> Result<Vec<u8>, HwError> {
        loop {
            if let Some(i) = self.buf.iter().position(|&b| b == b'\n') {
                let mut line: Vec<u8> = self.buf.drain(..=i).collect();
                line.pop();
                if line.last() == Some(&b'\r') {
                    line.pop();
                }
                return Ok(line);
            }
            if self.buf.len() > MAX_LINE {
                let junk = std::mem::take(&mut self.buf);
                return Err(HwError::Protocol {
                    device: self.device.clone(),
                    reply: String::from_utf8_lossy(&junk[..64]).into_owned(),
                    waiting_for: format!("{waiting_for} (no line end in {MAX_LINE} bytes)"),
                });
            }
            self.fill(deadline, waiting_for)?;
        }
    }

    /// Read whatever arrives before `deadline` into the buffer (at least one byte).
    fn fill(&mut self, deadline: Deadline, waiting_for: &str) -> Result<(), HwError> {
        let now = Instant::now();
        if now >= deadline.at {
            return Err(self.timeout(deadline, waiting_for));
        }
        let left = (deadline.at - now).max(Duration::from_millis(1));
        self.port
            .set_timeout(left)
            .map_err(|e| self.gone("configuring", e))?;
        let mut tmp = [0u8; 256];
        match self.port.read(&mut tmp) {
            Ok(0) => Err(self.gone("end of file on", "the other end closed")),
            Ok(n) => {
                self.buf.extend_from_slice(&tmp[..n]);
                Ok(())
            }
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {
                Err(self.timeout(deadline, waiting_for))
            }
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => Ok(()),
            Err(e) => Err(self.gone("reading from", e)),
        }
    }

    fn timeout(&self, deadline: Deadline, waiting_for: &str) -> HwError {
        HwError::Timeout {
            device: self.device.clone(),
            timeout_ms: deadline.budget.as_millis() as u64,
            waiting_for: waiting_for.to_string(),
        }
    }

    /// Discard input until the line has been quiet for `quiet` (stale replies after a
    /// timeout, noise after a reset). Returns the number of bytes dropped.
    pub fn drain(&mut self, quiet: Duration) -> Result<usize, HwError> {
        let mut dropped = std::mem::take(&mut self.buf).len();
        loop {
            let before = self.buf.len();
            match self.fill(Deadline::after(quiet), "quiet") {
                Ok(()) => {
                    dropped += self.buf.len() - before;
                    self.buf.clear();
                }
                Err(HwError::Timeout { .. }) => return Ok(dropped),
                Err(e) => return Err(e),
            }
        }
    }
}

/// A driver's connection: the port while it is open, and whether stale input may be waiting.
pub struct SerialLink {
    device: String,
    path: String,
    baud: u32,
    /// How long the line must stay quiet to count as drained.
    drain_quiet: Duration,
    lines: Option<SerialLines>,
    /// A reply may still be in flight (after a timeout, an alarm, a garbled line): drain first.
    stale: bool,
}

impl std::fmt::Debug for SerialLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SerialLink")
            .field("device", &self.device)
            .field("path", &self.path)
            .field("connected", &self.is_open())
            .finish()
    }
}

impl SerialLink {
    /// A closed link to `path` at `baud`; `device` names it in errors.
    pub fn new(device: &str, path: &str, baud: u32, drain_quiet: Duration) -> SerialLink {
        SerialLink {
            device: device.to_string(),
            path: path.to_string(),
            baud,
            drain_quiet,
            lines: None,
            stale: false,
        }
    }

    pub fn is_open(&self) -> bool {
        self.lines.is_some()
    }

    /// Drop the port; the next [`OverSerial::ensure_connected`] reopens it.
    pub fn close(&mut self) {
        self.lines = None;
    }

    /// Open the port afresh (nothing stale yet).
    fn open(&mut self) -> Result<(), HwError> {
        self.lines = Some(SerialLines::open(&self.device, &self.path, self.baud)?);
        self.stale = false;
        Ok(())
    }

    /// Whatever is waiting in the buffers is not ours: drain before the next write.
    pub fn mark_stale(&mut self) {
        self.stale = true;
    }

    fn port(&mut self) -> Result<&mut SerialLines, HwError> {
        self.lines.as_mut().ok_or_else(|| HwError::PortGone {
            device: self.device.clone(),
            message: "not connected".into(),
        })
    }

    /// Write `bytes` (after draining stale input, so the reply read next is this one's).
    pub fn write(&mut self, bytes: &[u8]) -> Result<(), HwError> {
        if self.stale {
            let quiet = self.drain_quiet;
            let n = self.port()?.drain(quiet)?;
            if n > 0 {
                tracing::debug!(device = %self.device, bytes = n, "drained stale input");
            }
            self.stale = false;
        }
        self.port()?.write(bytes)
    }

    /// Write one command line, `\n`-terminated.
    pub fn write_line(&mut self, line: &str) -> Result<(), HwError> {
        let mut bytes = Vec::with_capacity(line.len() + 1);
        bytes.extend_from_slice(line.as_bytes());
        bytes.push(b'\n');
        self.write(&bytes)
    }

    /// The next line; see [`SerialLines::read_line`].
    pub fn read_line(&mut self, deadline: Deadline, waiting_for: &str) -> Result<Vec<u8>, HwError> {
        self.port()?.read_line(deadline, waiting_for)
    }

    /// Keep the link consistent with an operation's failure: a vanished port is dropped
    /// (returns true), a failure that may leave a reply in flight marks the input stale.
    fn failed(&mut self, e: &HwError) -> bool {
        match e {
            HwError::PortGone { message, .. } => {
                tracing::warn!(device = %self.device, %message, "port gone; will reopen on next use");
                self.lines = None;
                true
            }
            HwError::Timeout { .. }
            | HwError::NotSettled { .. }
            | HwError::Alarm { .. }
            | HwError::Protocol { .. } => {
                self.stale = true;
                false
            }
            _ => false,
        }
    }
}

/// A driver speaking its protocol over a [`SerialLink`]. It supplies the handshake; the
/// provided methods keep the connection (lazy open, reopen after the port vanished).
pub(crate) trait OverSerial {
    fn link(&mut self) -> &mut SerialLink;

    /// What to say after the port (re)opened (banner, identification, servo on). A failure
    /// closes the port again, so the next call starts over.
    fn handshake(&mut self) -> Result<(), HwError>;

    /// The port vanished: forget what was known about the controller's state.
    fn port_lost(&mut self);

    /// Open the port and run the handshake unless already connected.
    fn ensure_connected(&mut self) -> Result<(), HwError> {
        if self.link().is_open() {
            return Ok(());
        }
        self.link().open()?;
        let r = self.handshake();
        if r.is_err() {
            self.link().close();
        }
        r
    }

    /// Close the port and open it again, handshake included.
    fn reopen(&mut self) -> Result<(), HwError>
    where
        Self: Sized,
    {
        self.link().close();
        self.guard(|s| s.ensure_connected())
    }

    /// Run an operation; keep the connection state consistent with its failure.
    fn guard<T>(&mut self, f: impl FnOnce(&mut Self) -> Result<T, HwError>) -> Result<T, HwError>
    where
        Self: Sized,
    {
        let r = f(self);
        if let Err(e) = &r {
            if self.link().failed(e) {
                self.port_lost();
            }
        }
        r
    }
}

/// When a wait ends, and the budget it was given (for the error message).
#[derive(Debug, Clone, Copy)]
pub struct Deadline {
    pub at: Instant,
    pub budget: Duration,
}

impl Deadline {
    pub fn after(budget: Duration) -> Deadline {
        Deadline {
            at: Instant::now() + budget,
            budget,
        }
    }
    pub fn expired(&self) -> bool {
        Instant::now() >= self.at
    }
    /// The same deadline, `d` later (time spent waiting for a turn is not a reply's).
    pub fn later_by(self, d: Duration) -> Deadline {
        Deadline {
            at: self.at + d,
            budget: self.budget + d,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigd_sim::pty::Pty;

    /// The least driver: counts handshakes and lost ports.
    struct Probe {
        link: SerialLink,
        handshakes: u32,
        lost: u32,
    }

    impl OverSerial for Probe {
        fn link(&mut self) -> &mut SerialLink {
            &mut self.link
        }
        fn handshake(&mut self) -> Result<(), HwError> {
            self.handshakes += 1;
            Ok(())
        }
        fn port_lost(&mut self) {
            self.lost += 1;
        }
    }

    fn probe(pty: &Pty) -> Probe {
        let path = pty.slave_path().to_str().unwrap();
        Probe {
            link: SerialLink::new("probe", path, 115_200, Duration::from_millis(20)),
            handshakes: 0,
            lost: 0,
        }
    }

    fn ask(p: &mut Probe, line: &str, ms: u64) -> Result<Vec<u8>, HwError> {
        p.guard(|p| {
            p.ensure_connected()?;
            p.link.write_line(line)?;
            p.link
                .read_line(Deadline::after(Duration::from_millis(ms)), "the answer")
        })
    }

    #[test]
    fn a_late_reply_is_drained_before_the_next_command() {
        let pty = Pty::open().unwrap();
        let mut p = probe(&pty);
        match ask(&mut p, "A", 20).unwrap_err() {
            HwError::Timeout {
                device,
                timeout_ms,
                waiting_for,
            } => {
                assert_eq!((device.as_str(), timeout_ms), ("probe", 20));
                assert_eq!(waiting_for, "the answer");
            }
            e => panic!("expected a timeout, got {e}"),
        }
        // The answer to A arrives late; B's own answer comes after B was sent.
        pty.write_all(b"answer A\r\n").unwrap();
        std::thread::sleep(Duration::from_millis(10));
        p.guard(|p| p.link.write_line("B")).unwrap();
        pty.write_all(b"answer B\r\n").unwrap();
        let line = p
            .link
            .read_line(Deadline::after(Duration::from_millis(500)), "B")
            .unwrap();
        assert_eq!(line, b"answer B");
        assert_eq!((p.handshakes, p.lost), (1, 0));
        let mut sent = [0u8; 16];
        let n = pty.read(&mut sent).unwrap();
        assert_eq!(&sent[..n], b"A\nB\n");
    }

    #[test]
    fn a_vanished_port_is_dropped_and_reopening_names_it() {
        let pty = Pty::open().unwrap();
        let path = pty.slave_path().display().to_string();
        let mut p = probe(&pty);
        p.guard(|p| p.ensure_connected()).unwrap();
        assert!(p.link.is_open());
        drop(pty);
        let e = ask(&mut p, "A", 200).unwrap_err();
        assert!(matches!(e, HwError::PortGone { .. }), "{e}");
        assert!(!p.link.is_open());
        assert_eq!(p.lost, 1);
        // The next call tries to reopen, and says which port it could not open.
        let e = ask(&mut p, "A", 200).unwrap_err();
        assert!(e.to_string().contains(&path), "{e}");
        assert!(!p.link.is_open());
        assert_eq!((p.handshakes, p.lost), (1, 2));
    }

    #[test]
    fn a_closed_link_says_so() {
        let mut link = SerialLink::new("probe", "/nonexistent", 9_600, Duration::ZERO);
        let e = link.write(b"?").unwrap_err();
        assert_eq!(e.to_string(), "probe: port gone: not connected");
    }
}
