//! CARTO dynamic capture `.rtx`.
//!
//! ```text
//! HEADER::\r\n
//! Owner: ...\r\n  Version no: ...\r\n  Sample rate: 1000\r\n  Actual sample rate: 1000.0\r\n
//! Sample no: 5000\r\n  Trigger point: 0\r\n  Date: 21/11/2026 10:00:00\r\n  Axis: X\r\n ...
//! Data:\r\n<little-endian f64 samples>EOF::\r\n
//! ```
//! The `Data:` line ends like every header line (its CR LF, or a bare LF, is the line's
//! end); the samples start right after it, whatever their bytes (a first sample whose low
//! bytes are 0D 0A is a sample). The samples end where the header's `Sample no` says
//! (exactly, when it is given), or, in a capture still growing (`Sample no: 0`), at an
//! `EOF::` followed by nothing but a line end: a trailer is the last thing in the file, so
//! `EOF::` bytes with data after them are a sample.
//! Samples are taken at the actual sample rate; sample i is at i / rate seconds after the
//! header's date. Their unit is the header's `Units` (or `Unit`) key when present, else
//! millimetres (the unit CARTO shows linear data in). The parser is incremental: in a growing
//! file only complete 8-byte samples are read, and a half-written trailer is waited for.

use super::{
    length_unit_um, note_metadata, parse_datetime, parse_number, Reading, Xl80Format, Xl80Log,
};

#[derive(Debug, Clone, Copy, PartialEq)]
enum State {
    /// Before the `HEADER::` line.
    Start,
    Header,
    Data,
    Done,
}

pub struct RtxParser {
    pending: Vec<u8>,
    state: State,
    line_no: usize,
    samples: usize,
    um_per_unit: f64,
    declared_samples: Option<usize>,
    log: Xl80Log,
    /// Set when the input is not an RTX file at all.
    fatal: Option<String>,
}

impl Default for RtxParser {
    fn default() -> Self {
        Self::new()
    }
}

const EOF_MARK: &[u8] = b"EOF::";
const TRAILER: &[u8] = b"EOF::\r\n";

/// The rest of the input is the trailer: `EOF::` and at most a line end (CR, LF) after it.
fn is_trailer(rest: &[u8]) -> bool {
    rest.starts_with(EOF_MARK)
        && rest[EOF_MARK.len()..]
            .iter()
            .all(|b| matches!(b, b'\r' | b'\n'))
}

impl RtxParser {
    pub fn new() -> Self {
        RtxParser {
            pending: Vec::new(),
            state: State::Start,
            line_no: 0,
            samples: 0,
            um_per_unit: 1000.0,
            declared_samples: None,
            log: Xl80Log::new(Xl80Format::Rtx),
            fatal: None,
        }
    }

    /// The unit of samples when the header names none (CARTO files do not): µm per unit.
    pub fn with_default_unit_um(mut self, um_per_unit: f64) -> Self {
        self.um_per_unit = um_per_unit;
        self
    }

    pub fn log(&self) -> &Xl80Log {
        &self.log
    }

    /// Drop the samples parsed so far (a follower that has handed them on), keeping the
    /// header and the sample count (sample times stay right).
    pub fn forget_readings(&mut self) {
        self.log.readings = Vec::new();
    }

    /// Whether the `EOF::` trailer has been read.
    pub fn is_done(&self) -> bool {
        self.state == State::Done
    }

    /// Whether the header has been read (samples can follow).
    pub fn in_data(&self) -> bool {
        matches!(self.state, State::Data | State::Done)
    }

    /// Parse what is complete; returns how many samples were added.
    pub fn feed(&mut self, bytes: &[u8]) -> usize {
        let before = self.log.readings.len();
        if self.fatal.is_some() || self.state == State::Done {
            return 0;
        }
        self.pending.extend_from_slice(bytes);
        let mut pos = 0;
        loop {
            let rest = &self.pending[pos..];
            match self.state {
                State::Start | State::Header => {
                    let Some(nl) = rest.iter().position(|&b| b == b'\n') else {
                        break;
                    };
                    let line = String::from_utf8_lossy(&rest[..nl])
                        .trim_end_matches('\r')
                        .to_string();
                    pos += nl + 1;
                    self.line_no += 1;
                    self.header_line(&line);
                    if self.fatal.is_some() {
                        break;
                    }
                }
                State::Data => {
                    // With a count, the trailer comes after that many samples; without (a
                    // growing capture) only a whole `EOF::\r\n` with nothing after it is one:
                    // `EOF::` alone may be a sample's first bytes, its rest not written yet.
                    let end = match self.declared_samples.filter(|&n| n > 0) {
                        Some(n) => self.samples >= n && is_trailer(rest),
                        None => rest.starts_with(TRAILER) && is_trailer(rest),
                    };
                    if end {
                        self.state = State::Done;
                        pos = self.pending.len();
                        break;
                    }
                    if rest.len() < 8 {
                        break;
                    }
                    let v = f64::from_le_bytes(rest[..8].try_into().expect("8 bytes"));
                    pos += 8;
                    let i = self.samples;
                    self.samples += 1;
                    if !v.is_finite() {
                        self.log.garbled.record(
                            i,
                            &format!("{:02x?}", &rest[..8]),
                            "sample is not a finite number",
                        );
                        continue;
                    }
                    let t_s = self.log.sample_rate_hz.map(|hz| i as f64 / hz);
                    self.log.readings.push(Reading {
                        t_s,
                        position_um: v * self.um_per_unit,
                        line: i,
                    });
                }
                State::Done => break,
            }
        }
        self.pending.drain(..pos);
        self.log.readings.len() - before
    }

    fn header_line(&mut self, line: &str) {
        let trimmed = line.trim();
        match self.state {
            State::Start => {
                if trimmed == "HEADER::" {
                    self.state = State::Header;
                } else if !trimmed.is_empty() {
                    self.fatal = Some(format!(
                        "line {}: expected `HEADER::`, found {:?}: not a CARTO .rtx capture",
                        self.line_no,
                        trimmed.chars().take(40).collect::<String>()
                    ));
                }
            }
            State::Header => {
                if trimmed.eq_ignore_ascii_case("Data:") {
                    self.log.um_per_unit = Some(self.um_per_unit);
                    self.state = State::Data;
                    return;
                }
                if let Some(rest) = trimmed.strip_prefix("Data:") {
                    // `Data:` with the samples on the same line: not produced by CARTO, and
                    // the line split would have cut the binary; refuse clearly.
                    self.fatal = Some(format!(
                        "line {}: `Data:` is followed by {} bytes on its line; expected a line break",
                        self.line_no,
                        rest.len()
                    ));
                    return;
                }
                if trimmed.is_empty() {
                    return;
                }
                let Some((key, value)) = trimmed.split_once(':') else {
                    self.log.garbled.record(
                        self.line_no,
                        trimmed,
                        "header line is not `Key: value`",
                    );
                    return;
                };
                note_metadata(&mut self.log.meta, key, value);
                let k = key.trim().to_ascii_lowercase();
                let v = value.trim();
                match k.as_str() {
                    "actual sample rate" => match parse_number(v) {
                        Some(hz) if hz > 0.0 => self.log.sample_rate_hz = Some(hz),
                        _ => self.log.garbled.record(
                            self.line_no,
                            trimmed,
                            "actual sample rate is not a positive number",
                        ),
                    },
                    // The nominal rate, until (or unless) the actual one is given.
                    "sample rate" if self.log.sample_rate_hz.is_none() => {
                        self.log.sample_rate_hz = parse_number(v).filter(|hz| *hz > 0.0);
                    }
                    "sample no" => self.declared_samples = parse_number(v).map(|n| n as usize),
                    "date" => self.log.start = parse_datetime(v),
                    "units" | "unit" => match length_unit_um(v) {
                        Some(f) => self.um_per_unit = f,
                        None => {
                            self.log
                                .garbled
                                .record(self.line_no, trimmed, "unknown length unit")
                        }
                    },
                    _ => {}
                }
            }
            _ => {}
        }
    }

    /// End of input. An RTX without `HEADER::` or `Data:` is an error; a missing `EOF::`
    /// (capture cut short), a partial last sample, or fewer samples than `Sample no` are
    /// reported as garbled.
    pub fn finish(mut self) -> Result<Xl80Log, String> {
        if let Some(f) = self.fatal {
            return Err(f);
        }
        match self.state {
            State::Start => return Err("no `HEADER::` line: not a CARTO .rtx capture".into()),
            State::Header => return Err("no `Data:` line after the header".into()),
            // The trailer before `Sample no` samples: the count check below says so.
            State::Data if is_trailer(&self.pending) => {}
            State::Data => {
                let n = self.pending.len();
                if n > 0 {
                    self.log.garbled.record(
                        self.samples,
                        &format!("{n} bytes"),
                        "trailing bytes are not a whole sample",
                    );
                }
                self.log.garbled.record(
                    self.samples,
                    "",
                    "no `EOF::` trailer: the capture is cut short",
                );
            }
            State::Done => {}
        }
        // `Sample no: 0` is a capture written while it grew: its count is unknown.
        if let Some(want) = self.declared_samples.filter(|&n| n > 0) {
            if want != self.samples {
                self.log.garbled.record(
                    self.samples,
                    "",
                    format!(
                        "header says Sample no: {want}, the data holds {}",
                        self.samples
                    ),
                );
            }
        }
        Ok(self.log)
    }

    /// The error that makes this input unreadable, if any (for a follower).
    pub fn fatal(&self) -> Option<&str> {
        self.fatal.as_deref()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rtx(header: &[(&str, &str)], samples: &[f64], trailer: bool) -> Vec<u8> {
        let mut b = b"HEADER::\r\n".to_vec();
        for (k, v) in header {
            b.extend_from_slice(format!("{k}: {v}\r\n").as_bytes());
        }
        b.extend_from_slice(b"Data:\r\n");
        for s in samples {
            b.extend_from_slice(&s.to_le_bytes());
        }
        if trailer {
            b.extend_from_slice(b"EOF::\r\n");
        }
        b
    }

    #[test]
    fn reads_header_and_samples() {
        let bytes = rtx(
            &[
                ("Owner", "Renishaw"),
                ("Sample rate", "100"),
                ("Actual sample rate", "250,0"),
                ("Sample no", "3"),
                ("Axis", "X"),
                ("Date", "2026-11-21 10:00:00"),
            ],
            &[0.0, 0.05, 0.1],
            true,
        );
        let mut p = RtxParser::new();
        p.feed(&bytes);
        let log = p.finish().unwrap();
        assert_eq!(log.sample_rate_hz, Some(250.0));
        assert_eq!(log.meta.axis.as_deref(), Some("X"));
        assert_eq!(log.readings.len(), 3);
        assert!((log.readings[2].position_um - 100.0).abs() < 1e-9);
        assert_eq!(log.readings[2].t_s, Some(2.0 / 250.0));
        assert_eq!(log.garbled.count, 0);
    }

    #[test]
    fn default_unit_applies_without_a_units_key() {
        let bytes = rtx(&[("Axis", "X")], &[1.5], true);
        let mut p = RtxParser::new().with_default_unit_um(1.0);
        p.feed(&bytes);
        assert_eq!(p.finish().unwrap().readings[0].position_um, 1.5);
        let bytes = rtx(&[("Units", "mm")], &[1.5], true);
        let mut p = RtxParser::new().with_default_unit_um(1.0);
        p.feed(&bytes);
        assert_eq!(p.finish().unwrap().readings[0].position_um, 1500.0);
    }

    #[test]
    fn byte_at_a_time_equals_whole() {
        let bytes = rtx(
            &[("Actual sample rate", "10"), ("Units", "um")],
            &[1.5, -2.0, 3.25, 4.0],
            true,
        );
        let mut whole = RtxParser::new();
        whole.feed(&bytes);
        let mut drip = RtxParser::new();
        for b in &bytes {
            drip.feed(std::slice::from_ref(b));
        }
        assert!(drip.is_done());
        let (a, b) = (whole.finish().unwrap(), drip.finish().unwrap());
        assert_eq!(a, b);
        assert_eq!(
            a.readings.iter().map(|r| r.position_um).collect::<Vec<_>>(),
            vec![1.5, -2.0, 3.25, 4.0]
        );
    }

    #[test]
    fn cut_short_and_count_mismatch_are_reported() {
        let mut bytes = rtx(&[("Sample no", "5")], &[1.0, 2.0], false);
        bytes.extend_from_slice(&[1, 2, 3]);
        let mut p = RtxParser::new();
        p.feed(&bytes);
        let log = p.finish().unwrap();
        assert_eq!(log.readings.len(), 2);
        assert_eq!(log.readings[0].t_s, None);
        assert_eq!(log.garbled.count, 3, "{:?}", log.garbled);
    }

    #[test]
    fn not_rtx_is_an_error() {
        let mut p = RtxParser::new();
        p.feed(b"Time (s),Position (mm)\r\n");
        assert!(p.finish().unwrap_err().contains("HEADER::"));
        let mut p = RtxParser::new();
        p.feed(b"HEADER::\r\nOwner: x\r\n");
        assert!(p.finish().unwrap_err().contains("Data:"));
    }
}
