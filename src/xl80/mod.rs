//! Renishaw XL-80 interferometer logs: what the laser measured while the axis stepped.
//!
//! - [`csv`]: a LaserXL/CARTO CSV export (metadata lines, then a header row, then readings).
//! - [`rtx`]: a CARTO dynamic capture `.rtx` (text header, then little-endian f64 samples).
//! - [`follow`]: read a log that is still being written during a job.
//! - [`align`]: give each commanded step its measured position, by time or by the step
//!   pattern (plateaus) in the trace.
//!
//! Both readers are incremental (`feed` bytes, get readings), so reading a whole file and
//! following a growing one share one code path. Garbled input is counted and reported in
//! [`Garbled`], never fatal; only an unreadable file or a log with no recognisable table is.

pub mod align;
pub mod csv;
pub mod follow;
pub mod rtx;

pub use align::{
    align_by_pattern, align_by_time, AlignError, PatternOptions, StepAlignment, StepWindow,
};
pub use follow::Follower;

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use time::format_description::BorrowedFormatItem;
use time::macros::format_description;
use time::{Date, OffsetDateTime, PrimitiveDateTime, Time};

/// The log file's format (`[xl80] format`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Xl80Format {
    /// LaserXL/CARTO CSV export.
    Csv,
    /// CARTO dynamic capture (.rtx).
    Rtx,
}

#[derive(Debug, thiserror::Error)]
pub enum Xl80Error {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The file is not the format it was said to be (no header row, no `HEADER::`...).
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
}

/// One interferometer reading.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Reading {
    /// Seconds since the log's start ([`Xl80Log::start`]), when the log has times.
    pub t_s: Option<f64>,
    /// The laser's reading along the beam, micrometres (its own datum and sign).
    pub position_um: f64,
    /// 1-based line number (CSV) or 0-based sample number (RTX), for messages.
    pub line: usize,
}

/// The conditions and identity recorded above the readings.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Metadata {
    pub air_temp_c: Option<f64>,
    pub material_temp_c: Option<f64>,
    pub pressure_mbar: Option<f64>,
    pub humidity_pct: Option<f64>,
    /// The date as written in the file.
    pub date: Option<String>,
    pub axis: Option<String>,
    /// Every `key: value` pair as written, in file order (RTX header keys included).
    pub fields: Vec<(String, String)>,
}

/// A line (or a stretch of binary data) that could not be read, kept for the report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GarbledLine {
    pub line: usize,
    pub text: String,
    pub reason: String,
}

/// Garbled input: how much, and the first few examples.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Garbled {
    pub count: usize,
    pub examples: Vec<GarbledLine>,
}

impl Garbled {
    const KEEP: usize = 10;

    pub fn record(&mut self, line: usize, text: &str, reason: impl Into<String>) {
        self.count += 1;
        if self.examples.len() < Self::KEEP {
            let mut text = text.to_string();
            if text.len() > 120 {
                let mut cut = 120;
                while !text.is_char_boundary(cut) {
                    cut -= 1;
                }
                text.truncate(cut);
                text.push('…');
            }
            self.examples.push(GarbledLine {
                line,
                text,
                reason: reason.into(),
            });
        }
    }
}

/// A whole (or so-far) log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Xl80Log {
    pub format: Xl80Format,
    pub meta: Metadata,
    /// When reading 0 was taken, if the log says (dates are read as UTC).
    pub start: Option<SystemTime>,
    /// Samples per second as the log declares it (RTX: the actual sample rate; CSV: its
    /// `Sample rate` line). Without one, [`Xl80Log::rate_of_times`] estimates it.
    pub sample_rate_hz: Option<f64>,
    /// µm per unit of the file's positions, once the table header (CSV) or `Data:` (RTX) is
    /// read: from the column's or the header's unit, else the assumed/configured one.
    #[serde(default)]
    pub um_per_unit: Option<f64>,
    pub readings: Vec<Reading>,
    pub garbled: Garbled,
}

impl Xl80Log {
    fn new(format: Xl80Format) -> Self {
        Xl80Log {
            format,
            meta: Metadata::default(),
            start: None,
            sample_rate_hz: None,
            um_per_unit: None,
            readings: Vec::new(),
            garbled: Garbled::default(),
        }
    }

    /// The wall-clock time of a reading, when the log has a start and times.
    pub fn time_of(&self, r: &Reading) -> Option<SystemTime> {
        let t = r.t_s?;
        let start = self.start?;
        // A log's time is a number in a file: one no Duration holds has no wall time.
        if t >= 0.0 {
            start.checked_add(Duration::try_from_secs_f64(t).ok()?)
        } else {
            start.checked_sub(Duration::try_from_secs_f64(-t).ok()?)
        }
    }

    /// The lowest and highest reading, µm (what the axis covered).
    pub fn span_um(&self) -> Option<(f64, f64)> {
        let mut it = self.readings.iter().map(|r| r.position_um);
        let first = it.next()?;
        Some(it.fold((first, first), |(lo, hi), v| (lo.min(v), hi.max(v))))
    }

    /// The sample rate from the times of the readings: one over the median interval.
    pub fn rate_of_times(&self) -> Option<f64> {
        let times: Vec<f64> = self.readings.iter().filter_map(|r| r.t_s).collect();
        let mut dt: Vec<f64> = times
            .windows(2)
            .map(|w| w[1] - w[0])
            .filter(|d| *d > 0.0)
            .collect();
        if dt.is_empty() {
            return None;
        }
        dt.sort_by(f64::total_cmp);
        Some(1.0 / dt[dt.len() / 2])
    }

    /// One line for logs and `rigctl`: what was read and what was not. The span is the
    /// lowest to the highest reading (an out-and-back run spans its travel), then the first
    /// and the last.
    pub fn summary(&self) -> String {
        let mut s = format!("{} readings", self.readings.len());
        if let (Some((lo, hi)), Some(a), Some(b)) =
            (self.span_um(), self.readings.first(), self.readings.last())
        {
            s += &format!(
                ", span {lo:.3} .. {hi:.3} µm (first {:.3}, last {:.3} µm)",
                a.position_um, b.position_um
            );
        }
        match (self.sample_rate_hz, self.rate_of_times()) {
            (Some(hz), _) => s += &format!(" at {hz} Hz"),
            (None, Some(hz)) => s += &format!(" at {hz:.4} Hz (from the timestamps)"),
            (None, None) => s += ", no sample rate (no `Sample rate` line, no timestamps)",
        }
        if self.garbled.count > 0 {
            s += &format!(", {} garbled", self.garbled.count);
            if let Some(g) = self.garbled.examples.first() {
                s += &format!(" (first: line {}: {})", g.line, g.reason);
            }
        }
        s
    }
}

/// Read a whole log file in the given format (RTX samples in mm unless the header says).
pub fn read(path: impl AsRef<Path>, format: Xl80Format) -> Result<Xl80Log, Xl80Error> {
    read_with(path, format, 1000.0)
}

/// [`read`] with the unit of RTX samples when the header names none, in µm per unit
/// (`[xl80] rtx_unit`: 1000 for mm, 1 for µm).
pub fn read_with(
    path: impl AsRef<Path>,
    format: Xl80Format,
    rtx_um_per_unit: f64,
) -> Result<Xl80Log, Xl80Error> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|source| Xl80Error::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let log = match format {
        Xl80Format::Csv => {
            let mut p = csv::CsvParser::new();
            p.feed(&bytes);
            p.finish()
        }
        Xl80Format::Rtx => {
            let mut p = rtx::RtxParser::new().with_default_unit_um(rtx_um_per_unit);
            p.feed(&bytes);
            p.finish()
        }
    };
    log.map_err(|message| Xl80Error::Format {
        path: path.to_path_buf(),
        message,
    })
}

/// A length unit as written in a column header or an RTX header, to micrometres.
pub fn length_unit_um(unit: &str) -> Option<f64> {
    match unit.trim().to_ascii_lowercase().as_str() {
        "m" => Some(1e6),
        "mm" => Some(1e3),
        "µm" | "μm" | "um" | "micron" | "microns" => Some(1.0),
        "nm" => Some(1e-3),
        "in" | "inch" => Some(25_400.0),
        _ => None,
    }
}

/// A number as the XL-80 software writes it in any locale: `12.5`, `12,5`, `+1.2E-3`,
/// optionally followed by a unit (`20.1 °C`, `1013 mbar`).
pub fn parse_number(s: &str) -> Option<f64> {
    let s = s.trim().trim_matches('"').trim();
    let end = s
        .char_indices()
        .find(|(_, c)| !(c.is_ascii_digit() || matches!(c, '+' | '-' | '.' | ',' | 'e' | 'E')))
        .map(|(i, _)| i)
        .unwrap_or(s.len());
    let num = s[..end].trim();
    if num.is_empty() {
        return None;
    }
    // A decimal comma: only when there is no point (no thousands separators in these files).
    let num = if num.contains(',') && !num.contains('.') {
        num.replacen(',', ".", 1)
    } else {
        num.to_string()
    };
    let v: f64 = num.parse().ok()?;
    v.is_finite().then_some(v)
}

/// Dates as these files write them: year first (`2026-11-21`) or day first (`21/11/2026`,
/// `21.11.2026`), with `-`, `/` or `.`.
const DATE: &[BorrowedFormatItem<'static>] = format_description!(
    version = 2,
    "[first \
        [[year][first [-] [/] [.]][month padding:none][first [-] [/] [.]][day padding:none]] \
        [[day padding:none][first [-] [/] [.]][month padding:none][first [-] [/] [.]][year]] \
    ]"
);

/// `hh:mm[:ss[.fff]]`, a decimal comma allowed.
const TIME_OF_DAY: &[BorrowedFormatItem<'static>] = format_description!(
    version = 2,
    "[hour padding:none]:[minute padding:none]\
     [optional [:[second padding:none][optional [[first [.] [,]][subsecond]]]]]"
);

/// A date and time as these files write it: `2026-11-21 10:15:30.25`, `2026-11-21T10:15:30Z`,
/// `21/11/2026 10:15:30`, `21.11.2026 10:15`. Read as UTC. Date alone gives midnight.
pub fn parse_datetime(s: &str) -> Option<SystemTime> {
    let s = s.trim().trim_matches('"').trim();
    let s = s.strip_suffix('Z').unwrap_or(s);
    let (date, time) = match s.split_once(['T', ' ']) {
        Some((date, time)) => (date, Time::parse(time.trim(), TIME_OF_DAY).ok()?),
        None => (s, Time::MIDNIGHT),
    };
    let date = Date::parse(date, DATE).ok()?;
    let t = PrimitiveDateTime::new(date, time).assume_utc();
    let since_epoch = t - OffsetDateTime::UNIX_EPOCH;
    since_epoch
        .try_into()
        .ok()
        .map(|d: Duration| UNIX_EPOCH + d)
}

/// `hh:mm[:ss[.fff]]` to seconds of the day.
pub fn parse_time_of_day(s: &str) -> Option<f64> {
    let t = Time::parse(s.trim(), TIME_OF_DAY).ok()?;
    Some((t - Time::MIDNIGHT).as_seconds_f64())
}

/// Fill the known metadata fields from a `key: value` pair (case-insensitive key match).
pub(crate) fn note_metadata(meta: &mut Metadata, key: &str, value: &str) {
    let k = key.trim().to_ascii_lowercase();
    let v = value.trim();
    meta.fields.push((key.trim().to_string(), v.to_string()));
    if k.contains("temp") && k.contains("air") {
        meta.air_temp_c = parse_number(v);
    } else if k.contains("temp") && (k.contains("material") || k.contains("mat")) {
        meta.material_temp_c = parse_number(v);
    } else if k.contains("pressure") {
        meta.pressure_mbar = parse_number(v).map(|p| {
            let lv = v.to_ascii_lowercase();
            if lv.contains("kpa") {
                p * 10.0
            } else if lv.contains("mmhg") {
                p * 1.333_224
            } else if lv.contains("pa") && !lv.contains("hpa") {
                p / 100.0
            } else {
                p // mbar and hPa
            }
        });
    } else if k.contains("humidity") || k == "rh" {
        meta.humidity_pct = parse_number(v);
    } else if k == "date" || k.starts_with("date") {
        meta.date = Some(v.to_string());
    } else if k == "axis" {
        meta.axis = Some(v.to_string());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_in_any_locale() {
        assert_eq!(parse_number("12.5"), Some(12.5));
        assert_eq!(parse_number(" 12,5 "), Some(12.5));
        assert_eq!(parse_number("-1,25E-3"), Some(-0.00125));
        assert_eq!(parse_number("20.1 °C"), Some(20.1));
        assert_eq!(parse_number("\"1013,2\" mbar"), Some(1013.2));
        assert_eq!(parse_number("abc"), None);
        assert_eq!(parse_number(""), None);
        assert_eq!(parse_number("1.2.3"), None);
    }

    #[test]
    fn dates() {
        let t = |s| {
            parse_datetime(s)
                .unwrap()
                .duration_since(UNIX_EPOCH)
                .unwrap()
                .as_secs_f64()
        };
        assert_eq!(t("1970-01-02"), 86_400.0);
        assert_eq!(t("2026-11-21 10:15:30.25"), 1_795_256_130.25);
        assert_eq!(t("21/11/2026 10:15:30.25"), 1_795_256_130.25);
        assert_eq!(t("2026-11-21T10:15:30.25Z"), 1_795_256_130.25);
        assert_eq!(t("21.11.2026 10:15"), 1_795_256_100.0);
        assert_eq!(t("2026-1-2 9:05:07,5"), 1_767_344_707.5);
        assert!(parse_datetime("2026-13-01").is_none());
        assert!(parse_datetime("2026-02-30").is_none());
        assert!(parse_datetime("2026-11-21 24:00").is_none());
        assert!(parse_datetime("yesterday").is_none());
        assert!(parse_datetime("1969-12-31").is_none(), "before the epoch");
        assert_eq!(parse_time_of_day("10:15:30.25"), Some(36_930.25));
        assert_eq!(parse_time_of_day("10:15"), Some(36_900.0));
        assert_eq!(parse_time_of_day("10:61"), None);
    }

    #[test]
    fn units() {
        assert_eq!(length_unit_um("mm"), Some(1000.0));
        assert_eq!(length_unit_um("µm"), Some(1.0));
        assert_eq!(length_unit_um("UM"), Some(1.0));
        assert_eq!(length_unit_um("furlong"), None);
    }
}
