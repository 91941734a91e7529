//! Line I/O over a serial port, with a deadline on every read.
//!
//! Controllers answer in lines (GRBL `\r\n`, PI GCS `\n`); this splits the byte stream at
//! `\n`, drops a trailing `\r`, and turns the port's failures into [`HwError`]s: nothing
//! within the deadline is `Timeout`, a hangup or I/O error is `PortGone` (the port must be
//! reopened), a read of zero bytes (EOF) likewise.

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
}
