//! Follow a log the interferometer software is still writing during a job.
//!
//! A [`Follower`] keeps its byte offset and hands the new bytes to the incremental parser,
//! which reads only complete lines (CSV) or complete 8-byte samples (RTX): a half-written
//! last line or sample is read on a later poll. A file that does not exist yet is simply
//! empty; a file that shrank (the software started a new capture) is read again from the top.

use super::csv::CsvParser;
use super::rtx::RtxParser;
use super::{Reading, Xl80Error, Xl80Format, Xl80Log};
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

enum Parser {
    Csv(CsvParser),
    Rtx(RtxParser),
}

impl Parser {
    fn new(format: Xl80Format, rtx_um_per_unit: f64) -> Self {
        match format {
            Xl80Format::Csv => Parser::Csv(CsvParser::new()),
            Xl80Format::Rtx => Parser::Rtx(RtxParser::new().with_default_unit_um(rtx_um_per_unit)),
        }
    }
    fn feed(&mut self, b: &[u8]) -> usize {
        match self {
            Parser::Csv(p) => p.feed(b),
            Parser::Rtx(p) => p.feed(b),
        }
    }
    fn log(&self) -> &Xl80Log {
        match self {
            Parser::Csv(p) => p.log(),
            Parser::Rtx(p) => p.log(),
        }
    }
    fn forget_readings(&mut self) {
        match self {
            Parser::Csv(p) => p.forget_readings(),
            Parser::Rtx(p) => p.forget_readings(),
        }
    }
}

pub struct Follower {
    path: PathBuf,
    format: Xl80Format,
    offset: u64,
    parser: Parser,
    restarts: usize,
    rtx_um_per_unit: f64,
}

impl Follower {
    /// Follow `path` from its beginning (it need not exist yet).
    pub fn new(path: impl AsRef<Path>, format: Xl80Format) -> Self {
        Follower {
            path: path.as_ref().to_path_buf(),
            format,
            offset: 0,
            parser: Parser::new(format, 1000.0),
            restarts: 0,
            rtx_um_per_unit: 1000.0,
        }
    }

    /// The unit of RTX samples when the header names none, µm per unit (default mm: 1000).
    pub fn with_rtx_unit_um(mut self, um_per_unit: f64) -> Self {
        self.rtx_um_per_unit = um_per_unit;
        self.parser = Parser::new(self.format, um_per_unit);
        self
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Bytes consumed so far.
    pub fn offset(&self) -> u64 {
        self.offset
    }

    /// How many times the file shrank and was read again from the top.
    pub fn restarts(&self) -> usize {
        self.restarts
    }

    /// Read what was appended since the last poll; returns the new readings.
    pub fn poll(&mut self) -> Result<Vec<Reading>, Xl80Error> {
        let io = |source| Xl80Error::Io {
            path: self.path.clone(),
            source,
        };
        let mut file = match std::fs::File::open(&self.path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(io(e)),
        };
        let len = file.metadata().map_err(io)?.len();
        if len < self.offset {
            tracing::warn!(
                "{}: shrank from {} to {len} bytes; reading it again from the start",
                self.path.display(),
                self.offset
            );
            self.offset = 0;
            self.parser = Parser::new(self.format, self.rtx_um_per_unit);
            self.restarts += 1;
        }
        if len == self.offset {
            return Ok(Vec::new());
        }
        file.seek(SeekFrom::Start(self.offset)).map_err(io)?;
        let mut buf = Vec::with_capacity((len - self.offset) as usize);
        file.take(len - self.offset)
            .read_to_end(&mut buf)
            .map_err(io)?;
        self.offset += buf.len() as u64;
        let added = self.parser.feed(&buf);
        if let Parser::Rtx(p) = &self.parser {
            if let Some(msg) = p.fatal() {
                return Err(Xl80Error::Format {
                    path: self.path.clone(),
                    message: msg.to_string(),
                });
            }
        }
        let all = &self.parser.log().readings;
        Ok(all[all.len() - added..].to_vec())
    }

    /// Everything read so far: metadata, readings, garbled lines.
    pub fn log(&self) -> &Xl80Log {
        self.parser.log()
    }

    /// Drop the readings read so far, keeping the metadata and the place in the file: a
    /// long-running follower that hands readings on (`poll` returns them) stays small.
    pub fn forget_readings(&mut self) {
        self.parser.forget_readings();
    }

    /// Whether the writer has finished (RTX `EOF::` seen; a CSV has no end marker).
    pub fn is_complete(&self) -> bool {
        matches!(&self.parser, Parser::Rtx(p) if p.is_done())
    }
}
