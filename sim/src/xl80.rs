//! A Renishaw XL-80 laser interferometer log synthesizer, fed by the simulated axis' true
//! position: readings = true displacement along the beam + interferometer noise.
//!
//! It writes the two formats rigd reads (and shares no code with rigd's readers):
//! - a CSV export: metadata lines (date, axis, air and material temperature, pressure,
//!   humidity, sample rate), a blank line, then a header row `Sample,Time (s),Position (mm)`
//!   and one row per sample; unit (mm or µm), separator and decimal comma configurable;
//! - a CARTO dynamic capture `.rtx`: `HEADER::`, CRLF `Key: value` lines, `Data:`, the
//!   samples as little-endian f64 (in `rtx_unit`, mm by default), then `EOF::`, all CRLF.
//!
//! `LiveLog` writes either file while the job runs: a thread samples the position at the
//! sample rate and appends and flushes (about ten times a second, as the real software does,
//! or as `LiveOptions` say). While it grows, a `.rtx`
//! has no `EOF::` yet and its `Sample no` is 0; on `finish` the count is patched in (the
//! field is padded with spaces so the header keeps its length) and `EOF::` appended.

use crate::motion::TruePosition;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime};

/// The environment the XL-80's weather station reports (it compensates the wavelength).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Environment {
    pub air_temp_c: f64,
    pub material_temp_c: f64,
    pub pressure_mbar: f64,
    pub humidity_pct: f64,
}

impl Default for Environment {
    fn default() -> Self {
        Environment {
            air_temp_c: 20.4,
            material_temp_c: 20.1,
            pressure_mbar: 1012.8,
            humidity_pct: 46.0,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum LengthUnit {
    #[default]
    Mm,
    Um,
}

impl LengthUnit {
    fn per_um(self) -> f64 {
        match self {
            LengthUnit::Mm => 1e-3,
            LengthUnit::Um => 1.0,
        }
    }
    fn label(self) -> &'static str {
        match self {
            LengthUnit::Mm => "mm",
            LengthUnit::Um => "µm",
        }
    }
    fn decimals(self) -> usize {
        match self {
            LengthUnit::Mm => 6,
            LengthUnit::Um => 3,
        }
    }
}

/// How the CSV export is written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CsvFormat {
    pub unit: LengthUnit,
    /// Field separator: ',' ';' or '\t'.
    pub separator: char,
    /// Write decimals with a comma (a European locale); needs a separator other than ','.
    pub decimal_comma: bool,
}

impl Default for CsvFormat {
    fn default() -> Self {
        CsvFormat {
            unit: LengthUnit::Mm,
            separator: ',',
            decimal_comma: false,
        }
    }
}

/// Everything about the synthesized interferometer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Xl80Params {
    pub sample_rate_hz: f64,
    /// Interferometer reading noise, µm RMS (white).
    pub noise_rms_um: f64,
    /// Unit vector of the beam in line-of-sight coordinates: reading = dot(position, beam).
    pub beam_dir: [f64; 2],
    /// Reading subtracted from every sample (where the laser was datumed), µm.
    pub datum_um: f64,
    pub environment: Environment,
    pub csv: CsvFormat,
    /// Unit of the `.rtx` samples (the file does not say).
    pub rtx_unit: LengthUnit,
    pub owner: String,
    pub version: String,
    pub machine: String,
    pub serial_no: String,
    pub by: String,
    pub axis: String,
    pub location: String,
    /// `dd/mm/yyyy HH:MM:SS`; `None` takes the capture start (UTC).
    pub date: Option<String>,
    pub seed: u64,
}

impl Default for Xl80Params {
    fn default() -> Self {
        Xl80Params {
            sample_rate_hz: 100.0,
            noise_rms_um: 0.2,
            beam_dir: [1.0, 0.0],
            datum_um: 0.0,
            environment: Environment::default(),
            csv: CsvFormat::default(),
            rtx_unit: LengthUnit::Mm,
            owner: "CARTO-Dynamic".into(),
            version: "4.13.0.0".into(),
            machine: "rigd sim rig".into(),
            serial_no: "XL80-SIM-0001".into(),
            by: "rigd-sim".into(),
            axis: "X".into(),
            location: "Lab".into(),
            date: None,
            seed: 80,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum Xl80Error {
    #[error("xl80 parameter {field}: {message}")]
    Param {
        field: &'static str,
        message: String,
    },
    #[error("xl80 log {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}

impl Xl80Params {
    pub fn validate(&self) -> Result<(), Xl80Error> {
        let bad = |field, message: String| Err(Xl80Error::Param { field, message });
        if !self.sample_rate_hz.is_finite()
            || self.sample_rate_hz <= 0.0
            || self.sample_rate_hz > 50_000.0
        {
            return bad(
                "sample_rate_hz",
                format!("{} is not in (0, 50000]", self.sample_rate_hz),
            );
        }
        if !self.noise_rms_um.is_finite() || self.noise_rms_um < 0.0 {
            return bad("noise_rms_um", format!("{} is not >= 0", self.noise_rms_um));
        }
        let n = self.beam_dir[0].hypot(self.beam_dir[1]);
        if !n.is_finite() || (n - 1.0).abs() >= 1e-6 {
            return bad(
                "beam_dir",
                format!("{:?} is not a unit vector", self.beam_dir),
            );
        }
        if ![',', ';', '\t'].contains(&self.csv.separator) {
            return bad(
                "csv.separator",
                format!("{:?} is not one of ',' ';' tab", self.csv.separator),
            );
        }
        if self.csv.decimal_comma && self.csv.separator == ',' {
            return bad(
                "csv.decimal_comma",
                "needs a separator other than ','".into(),
            );
        }
        for (field, v) in [
            ("owner", &self.owner),
            ("version", &self.version),
            ("machine", &self.machine),
            ("serial_no", &self.serial_no),
            ("by", &self.by),
            ("axis", &self.axis),
            ("location", &self.location),
        ] {
            if v.contains(['\r', '\n']) {
                return bad(field, format!("{v:?} holds a line break"));
            }
        }
        Ok(())
    }

    fn period(&self) -> Duration {
        Duration::from_secs_f64(1.0 / self.sample_rate_hz)
    }

    fn date_or(&self, start: SystemTime) -> String {
        self.date.clone().unwrap_or_else(|| format_date(start))
    }
}

/// `dd/mm/yyyy HH:MM:SS` in UTC, as CARTO writes dates.
pub fn format_date(t: SystemTime) -> String {
    let t = time::OffsetDateTime::from(t);
    format!(
        "{:02}/{:02}/{:04} {:02}:{:02}:{:02}",
        t.day(),
        u8::from(t.month()),
        t.year(),
        t.hour(),
        t.minute(),
        t.second()
    )
}

/// The interferometer itself: true position in, noisy reading out.
pub struct Xl80 {
    params: Xl80Params,
    rng: ChaCha8Rng,
}

impl Xl80 {
    pub fn new(params: Xl80Params) -> Result<Xl80, Xl80Error> {
        params.validate()?;
        let rng = ChaCha8Rng::seed_from_u64(params.seed);
        Ok(Xl80 { params, rng })
    }

    pub fn params(&self) -> &Xl80Params {
        &self.params
    }

    /// The reading (µm) for a true line-of-sight position.
    pub fn read_um(&mut self, los_um: [f64; 2]) -> f64 {
        let b = self.params.beam_dir;
        let z: f64 = StandardNormal.sample(&mut self.rng);
        los_um[0] * b[0] + los_um[1] * b[1] - self.params.datum_um + self.params.noise_rms_um * z
    }

    /// Readings at the sample rate from `start` for `count` samples of `source`.
    pub fn capture(&mut self, source: &dyn TruePosition, start: Instant, count: usize) -> Vec<f64> {
        let period = self.params.period();
        (0..count)
            .map(|i| self.read_um(source.true_position_um(start + period.mul_f64(i as f64))))
            .collect()
    }
}

/// Which file a log is written as.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    Csv,
    Rtx,
}

impl LogFormat {
    pub fn extension(self) -> &'static str {
        match self {
            LogFormat::Csv => "csv",
            LogFormat::Rtx => "rtx",
        }
    }
}

fn number(v: f64, decimals: usize, fmt: &CsvFormat) -> String {
    let s = format!("{v:.decimals$}");
    if fmt.decimal_comma {
        s.replace('.', ",")
    } else {
        s
    }
}

/// The CSV export's metadata lines and header row.
pub fn write_csv_header(w: &mut impl Write, p: &Xl80Params, date: &str) -> std::io::Result<()> {
    let f = &p.csv;
    let sep = f.separator;
    let e = &p.environment;
    let lines: [(&str, String); 9] = [
        ("Renishaw XL-80 capture", String::new()),
        ("Date", date.to_string()),
        ("Axis", p.axis.clone()),
        ("Serial No", p.serial_no.clone()),
        ("Air temperature (°C)", number(e.air_temp_c, 2, f)),
        ("Material temperature (°C)", number(e.material_temp_c, 2, f)),
        ("Air pressure (mbar)", number(e.pressure_mbar, 2, f)),
        ("Humidity (%)", number(e.humidity_pct, 1, f)),
        ("Sample rate (Hz)", number(p.sample_rate_hz, 3, f)),
    ];
    for (k, v) in lines {
        if v.is_empty() {
            write!(w, "{k}\r\n")?;
        } else {
            write!(w, "{k}{sep}{v}\r\n")?;
        }
    }
    write!(
        w,
        "\r\nSample{sep}Time (s){sep}Position ({})\r\n",
        f.unit.label()
    )
}

/// One CSV data row; `index` counts from 1 as the export does.
pub fn write_csv_row(
    w: &mut impl Write,
    p: &Xl80Params,
    index: usize,
    reading_um: f64,
) -> std::io::Result<()> {
    let f = &p.csv;
    let t = (index - 1) as f64 / p.sample_rate_hz;
    write!(
        w,
        "{index}{sep}{}{sep}{}\r\n",
        number(t, 4, f),
        number(reading_um * f.unit.per_um(), f.unit.decimals(), f),
        sep = f.separator
    )
}

/// A whole CSV export of `readings_um`.
pub fn write_csv(
    w: &mut impl Write,
    p: &Xl80Params,
    date: &str,
    readings_um: &[f64],
) -> std::io::Result<()> {
    write_csv_header(w, p, date)?;
    for (i, &r) in readings_um.iter().enumerate() {
        write_csv_row(w, p, i + 1, r)?;
    }
    Ok(())
}

/// Width of the `Sample no` field, so a live file can be patched in place.
const SAMPLE_NO_WIDTH: usize = 12;

/// The `.rtx` header through `Data:\r\n`. Returns the byte offset of the `Sample no` value.
pub fn write_rtx_header(
    w: &mut impl Write,
    p: &Xl80Params,
    date: &str,
    sample_no: usize,
) -> std::io::Result<u64> {
    let rate = p.sample_rate_hz;
    let mut head = String::from("HEADER::\r\n");
    let mut kv = |k: &str, v: &str| {
        head.push_str(k);
        head.push_str(": ");
        head.push_str(v);
        head.push_str("\r\n");
    };
    kv("Owner", &p.owner);
    kv("Version no", &p.version);
    kv("File Type", "Linear");
    kv("Velocity", "0");
    kv("Sample rate", &format!("{rate}"));
    kv(
        "Sample no",
        &format!("{:<width$}", sample_no, width = SAMPLE_NO_WIDTH),
    );
    kv("Trigger point", "0");
    kv("Trigger interval", &format!("{}", 1.0 / rate));
    kv("Actual sample rate", &format!("{rate}"));
    kv("Flags", "0 1 2 0 2");
    kv("Machine", &p.machine);
    kv("Serial No", &p.serial_no);
    kv("Date", date);
    kv("By", &p.by);
    kv("Axis", &p.axis);
    kv("Location", &p.location);
    head.push_str("Data:\r\n");
    let at = head.find("\r\nSample no: ").expect("written above") + "\r\nSample no: ".len();
    w.write_all(head.as_bytes())?;
    Ok(at as u64)
}

fn write_rtx_sample(w: &mut impl Write, p: &Xl80Params, reading_um: f64) -> std::io::Result<()> {
    w.write_all(&(reading_um * p.rtx_unit.per_um()).to_le_bytes())
}

/// A whole `.rtx` dynamic capture of `readings_um`.
pub fn write_rtx(
    w: &mut impl Write,
    p: &Xl80Params,
    date: &str,
    readings_um: &[f64],
) -> std::io::Result<()> {
    write_rtx_header(w, p, date, readings_um.len())?;
    for &r in readings_um {
        write_rtx_sample(w, p, r)?;
    }
    w.write_all(b"EOF::\r\n")
}

/// Write a finished log of `readings_um` to `path`.
pub fn write_log(
    path: &Path,
    format: LogFormat,
    p: &Xl80Params,
    start: SystemTime,
    readings_um: &[f64],
) -> Result<(), Xl80Error> {
    p.validate()?;
    let io = |source| Xl80Error::Io {
        path: path.display().to_string(),
        source,
    };
    let mut w = BufWriter::new(File::create(path).map_err(io)?);
    let date = p.date_or(start);
    match format {
        LogFormat::Csv => write_csv(&mut w, p, &date, readings_um),
        LogFormat::Rtx => write_rtx(&mut w, p, &date, readings_um),
    }
    .and_then(|_| w.flush())
    .map_err(io)
}

/// What a finished live log holds.
#[derive(Debug, Clone, PartialEq)]
pub struct LogSummary {
    pub path: PathBuf,
    pub samples: usize,
    /// Instant of sample 1 (the capture start).
    pub started_at: Instant,
    pub started_sys: SystemTime,
}

/// How a live log is written.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LiveOptions {
    /// Flush at least this often (zero: after every sample). The capture software updates
    /// its file about ten times a second; a daemon that waits for the sample at a frame's
    /// time wants it sooner.
    pub flush_period: Duration,
    /// Date the capture on the whole second before it starts and synthesise the samples
    /// since then, so the log's whole-second `Date` plus the sample times is exact.
    pub start_on_whole_second: bool,
}

impl Default for LiveOptions {
    fn default() -> Self {
        LiveOptions {
            flush_period: Duration::from_millis(100),
            start_on_whole_second: false,
        }
    }
}

/// A log written live by a sampling thread; `finish` stops it and completes the file.
pub struct LiveLog {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<Result<LogSummary, Xl80Error>>>,
    path: PathBuf,
}

impl LiveLog {
    /// Start capturing `source` into `path` now.
    pub fn start(
        path: impl Into<PathBuf>,
        format: LogFormat,
        params: Xl80Params,
        source: Arc<dyn TruePosition>,
    ) -> Result<LiveLog, Xl80Error> {
        Self::start_with(path, format, params, source, LiveOptions::default())
    }

    /// [`LiveLog::start`] with [`LiveOptions`].
    pub fn start_with(
        path: impl Into<PathBuf>,
        format: LogFormat,
        params: Xl80Params,
        source: Arc<dyn TruePosition>,
        opts: LiveOptions,
    ) -> Result<LiveLog, Xl80Error> {
        let path = path.into();
        let mut xl = Xl80::new(params)?;
        let io = {
            let path = path.clone();
            move |source| Xl80Error::Io {
                path: path.display().to_string(),
                source,
            }
        };
        let mut file = File::create(&path).map_err(&io)?;
        let (started_at, started_sys) = capture_start(opts.start_on_whole_second);
        let date = xl.params.date_or(started_sys);
        let sample_no_at = {
            let mut head = Vec::new();
            let at = match format {
                LogFormat::Csv => {
                    write_csv_header(&mut head, &xl.params, &date).map_err(&io)?;
                    0
                }
                LogFormat::Rtx => write_rtx_header(&mut head, &xl.params, &date, 0).map_err(&io)?,
            };
            file.write_all(&head).map_err(&io)?;
            file.flush().map_err(&io)?;
            at
        };
        let stop = Arc::new(AtomicBool::new(false));
        let stop2 = Arc::clone(&stop);
        let path2 = path.clone();
        let thread = std::thread::Builder::new()
            .name("sim-xl80".into())
            .spawn(move || {
                let period = xl.params.period();
                let flush_every = ((opts.flush_period.as_secs_f64() / period.as_secs_f64()).ceil()
                    as usize)
                    .max(1);
                let mut w = BufWriter::new(file);
                let mut n = 0usize;
                let mut since_flush = 0usize;
                loop {
                    let t = started_at + period.mul_f64(n as f64);
                    let now = Instant::now();
                    if t > now {
                        if stop2.load(Ordering::Acquire) {
                            break;
                        }
                        std::thread::sleep((t - now).min(Duration::from_millis(20)));
                        continue;
                    }
                    let r = xl.read_um(source.true_position_um(t));
                    n += 1;
                    match format {
                        LogFormat::Csv => write_csv_row(&mut w, &xl.params, n, r),
                        LogFormat::Rtx => write_rtx_sample(&mut w, &xl.params, r),
                    }
                    .map_err(&io)?;
                    since_flush += 1;
                    if since_flush >= flush_every {
                        w.flush().map_err(&io)?;
                        since_flush = 0;
                    }
                }
                if format == LogFormat::Rtx {
                    w.write_all(b"EOF::\r\n").map_err(&io)?;
                    w.flush().map_err(&io)?;
                    let mut f = w.into_inner().map_err(|e| io(e.into_error()))?;
                    f.seek(SeekFrom::Start(sample_no_at)).map_err(&io)?;
                    f.write_all(format!("{:<width$}", n, width = SAMPLE_NO_WIDTH).as_bytes())
                        .map_err(&io)?;
                    f.flush().map_err(&io)?;
                } else {
                    w.flush().map_err(&io)?;
                }
                Ok(LogSummary {
                    path: path2,
                    samples: n,
                    started_at,
                    started_sys,
                })
            })
            .map_err(|source| Xl80Error::Io {
                path: path.display().to_string(),
                source,
            })?;
        Ok(LiveLog {
            stop,
            thread: Some(thread),
            path,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Stop sampling and complete the file.
    pub fn finish(mut self) -> Result<LogSummary, Xl80Error> {
        self.finish_inner()
    }

    fn finish_inner(&mut self) -> Result<LogSummary, Xl80Error> {
        self.stop.store(true, Ordering::Release);
        match self.thread.take() {
            Some(h) => h.join().unwrap_or_else(|_| {
                Err(Xl80Error::Io {
                    path: self.path.display().to_string(),
                    source: std::io::Error::other("the sampling thread panicked"),
                })
            }),
            None => Err(Xl80Error::Io {
                path: self.path.display().to_string(),
                source: std::io::Error::other("already finished"),
            }),
        }
    }
}

/// When sample 1 is taken, on both clocks: now, or the whole second before now.
fn capture_start(whole_second: bool) -> (Instant, SystemTime) {
    let (at, sys) = (Instant::now(), SystemTime::now());
    if !whole_second {
        return (at, sys);
    }
    let frac = sys
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| Duration::from_nanos(u64::from(d.subsec_nanos())))
        .unwrap_or_default();
    match at.checked_sub(frac) {
        Some(back) => (back, sys - frac),
        None => (at, sys),
    }
}

impl Drop for LiveLog {
    fn drop(&mut self) {
        if self.thread.is_some() {
            let _ = self.finish_inner();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::UNIX_EPOCH;

    #[test]
    fn dates_are_civil_utc() {
        assert_eq!(format_date(UNIX_EPOCH), "01/01/1970 00:00:00");
        // 2025-02-10 12:58:22 UTC
        let t = UNIX_EPOCH + Duration::from_secs(1_739_192_302);
        assert_eq!(format_date(t), "10/02/2025 12:58:22");
    }

    #[test]
    fn decimal_comma_with_comma_separator_is_refused() {
        let p = Xl80Params {
            csv: CsvFormat {
                decimal_comma: true,
                ..Default::default()
            },
            ..Default::default()
        };
        let e = p.validate().unwrap_err().to_string();
        assert!(e.contains("csv.decimal_comma"), "{e}");
    }
}
