//! XL-80 CSV export: metadata lines, then a header row, then one reading per line.
//!
//! ```text
//! Axis: X
//! Air temperature: 20,3 °C
//! Pressure: 1013,2 mbar
//! Time (s);Position (mm);Air temp (°C)
//! 0,000;0,000000;20,3
//! ```
//! Driven by the header row: columns are found by name (case-insensitive), units come from the
//! parentheses, the separator is `,`, `;` or tab, and numbers may use a decimal comma. Files
//! written by Windows software in Latin-1 read too. The parser is incremental: `feed` any
//! number of bytes, only complete lines are parsed.

use super::{
    length_unit_um, note_metadata, parse_datetime, parse_number, parse_time_of_day, Reading,
    Xl80Format, Xl80Log,
};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

#[derive(Debug, Clone, PartialEq)]
enum TimeKind {
    /// Numbers in seconds times this factor.
    Seconds(f64),
    /// Date-times or times of day, detected per value.
    Clock,
}

#[derive(Debug, Clone)]
struct Table {
    sep: u8,
    fields: usize,
    position: usize,
    position_um_per_unit: f64,
    time: Option<(usize, TimeKind)>,
}

/// Incremental CSV reader.
pub struct CsvParser {
    pending: Vec<u8>,
    line_no: usize,
    table: Option<Table>,
    log: Xl80Log,
}

impl Default for CsvParser {
    fn default() -> Self {
        Self::new()
    }
}

impl CsvParser {
    pub fn new() -> Self {
        CsvParser {
            pending: Vec::new(),
            line_no: 0,
            table: None,
            log: Xl80Log::new(Xl80Format::Csv),
        }
    }

    /// Parse every complete line in `bytes` (plus what an earlier call left incomplete);
    /// returns how many readings were added.
    pub fn feed(&mut self, bytes: &[u8]) -> usize {
        let before = self.log.readings.len();
        self.pending.extend_from_slice(bytes);
        let mut start = 0;
        while let Some(nl) = self.pending[start..].iter().position(|&b| b == b'\n') {
            let line = self.pending[start..start + nl].to_vec();
            start += nl + 1;
            self.line(&line);
        }
        self.pending.drain(..start);
        self.log.readings.len() - before
    }

    /// The log so far (complete lines only).
    pub fn log(&self) -> &Xl80Log {
        &self.log
    }

    /// Drop the readings parsed so far (a follower that has handed them on), keeping the
    /// metadata and the parsing state.
    pub fn forget_readings(&mut self) {
        self.log.readings = Vec::new();
    }

    /// Whether the header row has been seen.
    pub fn has_table(&self) -> bool {
        self.table.is_some()
    }

    /// End of input: parse a last line without a newline, and require a table.
    pub fn finish(mut self) -> Result<Xl80Log, String> {
        if !self.pending.is_empty() {
            let line = std::mem::take(&mut self.pending);
            self.line(&line);
        }
        if self.table.is_none() {
            return Err(format!(
                "no header row with a position column in {} lines (expected e.g. `Time (s),Position (mm)`)",
                self.line_no
            ));
        }
        Ok(self.log)
    }

    fn line(&mut self, raw: &[u8]) {
        self.line_no += 1;
        let mut raw = raw;
        if self.line_no == 1 {
            raw = raw.strip_prefix(&[0xEF, 0xBB, 0xBF]).unwrap_or(raw);
        }
        let text = decode(raw);
        let text = text.trim_end_matches(['\r', '\n']);
        if text.trim().is_empty() {
            return;
        }
        match self.table.clone() {
            None => self.before_table(text),
            Some(t) => self.row(&t, text),
        }
    }

    fn before_table(&mut self, text: &str) {
        let sep = guess_separator(text);
        let fields = split(text, sep);
        if let Some(table) = header(&fields, sep) {
            self.log.um_per_unit = Some(table.position_um_per_unit);
            self.table = Some(table);
            return;
        }
        // A metadata line: `Key: value`, or `Key<sep>value<sep>unit`.
        let key_end = text.find(':');
        let (key, value) = match key_end {
            Some(i) if !text[..i].contains(['\t', ';', ',']) => {
                (text[..i].to_string(), text[i + 1..].to_string())
            }
            _ if fields.len() >= 2 => (fields[0].clone(), fields[1..].join(" ")),
            _ => {
                // A title line or free text: keep it, it is not a reading.
                self.log
                    .meta
                    .fields
                    .push((String::new(), text.trim().to_string()));
                return;
            }
        };
        note_metadata(&mut self.log.meta, &key, &value);
        let k = key.trim().to_ascii_lowercase();
        if self.log.start.is_none() && k.starts_with("date") {
            self.log.start = parse_datetime(&value);
        }
        if k.contains("sample rate") || k.contains("sampling rate") {
            self.log.sample_rate_hz = parse_number(&value).filter(|hz| *hz > 0.0);
        }
    }

    fn row(&mut self, t: &Table, text: &str) {
        let fields = split(text, t.sep);
        let line = self.line_no;
        if fields.len() <= t.position {
            self.log.garbled.record(
                line,
                text,
                format!("{} fields, the header has {}", fields.len(), t.fields),
            );
            return;
        }
        let Some(pos) = parse_number(&fields[t.position]) else {
            self.log.garbled.record(
                line,
                text,
                format!("position {:?} is not a number", fields[t.position]),
            );
            return;
        };
        let t_s = match &t.time {
            None => None,
            Some((col, kind)) => match fields.get(*col).and_then(|f| self.time(kind, f)) {
                Some(v) => Some(v),
                None => {
                    self.log.garbled.record(
                        line,
                        text,
                        format!("time {:?} is not a time", fields.get(*col)),
                    );
                    return;
                }
            },
        };
        self.log.readings.push(Reading {
            t_s,
            position_um: pos * t.position_um_per_unit,
            line,
        });
    }

    /// Seconds since the log's start; the first absolute time seen becomes the start when the
    /// metadata gave none.
    fn time(&mut self, kind: &TimeKind, field: &str) -> Option<f64> {
        match kind {
            TimeKind::Seconds(f) => parse_number(field).map(|v| v * f),
            TimeKind::Clock => {
                let abs = match parse_datetime(field) {
                    Some(t) => t,
                    None => {
                        // A time of day: on the metadata's date.
                        let tod = parse_time_of_day(field)?;
                        let day = self.log.start.unwrap_or(UNIX_EPOCH);
                        let day_s = day.duration_since(UNIX_EPOCH).ok()?.as_secs() / 86_400;
                        UNIX_EPOCH
                            .checked_add(Duration::from_secs(day_s * 86_400))?
                            .checked_add(Duration::try_from_secs_f64(tod).ok()?)?
                    }
                };
                let start = *self.log.start.get_or_insert(abs);
                Some(signed_secs(abs, start))
            }
        }
    }
}

fn signed_secs(a: SystemTime, b: SystemTime) -> f64 {
    match a.duration_since(b) {
        Ok(d) => d.as_secs_f64(),
        Err(e) => -e.duration().as_secs_f64(),
    }
}

/// UTF-8 when it is, else Latin-1 (Windows exports write `µ` and `°` as single bytes).
fn decode(raw: &[u8]) -> String {
    match std::str::from_utf8(raw) {
        Ok(s) => s.to_string(),
        Err(_) => raw.iter().map(|&b| char::from(b)).collect(),
    }
}

/// Tab if any, else `;` if any, else `,` (a `;` file keeps commas for decimals).
fn guess_separator(line: &str) -> u8 {
    if line.contains('\t') {
        b'\t'
    } else if line.contains(';') {
        b';'
    } else {
        b','
    }
}

/// Split one line with the csv crate (quotes handled).
fn split(line: &str, sep: u8) -> Vec<String> {
    let mut rdr = ::csv::ReaderBuilder::new()
        .delimiter(sep)
        .has_headers(false)
        .flexible(true)
        .from_reader(line.as_bytes());
    match rdr.records().next() {
        Some(Ok(rec)) => rec.iter().map(|f| f.trim().to_string()).collect(),
        _ => vec![line.to_string()],
    }
}

/// `Position (mm)` -> ("position", Some("mm")); `Time [s]` likewise.
fn name_and_unit(field: &str) -> (String, Option<String>) {
    let f = field.trim();
    for (open, close) in [('(', ')'), ('[', ']')] {
        if let (Some(a), Some(b)) = (f.find(open), f.rfind(close)) {
            if a < b {
                return (
                    f[..a].trim().to_lowercase(),
                    Some(f[a + 1..b].trim().to_string()),
                );
            }
        }
    }
    (f.to_lowercase(), None)
}

/// Recognise the header row: a position column by name, and no field that is a number.
fn header(fields: &[String], sep: u8) -> Option<Table> {
    if fields.len() < 2 || fields.iter().any(|f| parse_number(f).is_some()) {
        return None;
    }
    let cols: Vec<(String, Option<String>)> = fields.iter().map(|f| name_and_unit(f)).collect();
    const POSITION: [&str; 6] = [
        "position",
        "reading",
        "displacement",
        "measured",
        "linear",
        "value",
    ];
    let position = cols.iter().position(|(n, _)| {
        !n.contains("target") && !n.contains("error") && POSITION.iter().any(|p| n.contains(p))
    })?;
    let position_um_per_unit = match &cols[position].1 {
        Some(u) => length_unit_um(u)?,
        None => {
            tracing::warn!(
                "XL-80 CSV: column {:?} has no unit; assuming mm",
                fields[position]
            );
            1000.0
        }
    };
    let time = cols
        .iter()
        .position(|(n, _)| n.contains("time") && !n.contains("temp"))
        .map(|i| {
            let kind = match cols[i].1.as_deref().map(|u| u.to_ascii_lowercase()) {
                Some(u) if u == "s" || u == "sec" => TimeKind::Seconds(1.0),
                Some(u) if u == "ms" => TimeKind::Seconds(1e-3),
                Some(u) if u == "us" || u == "µs" => TimeKind::Seconds(1e-6),
                _ => TimeKind::Clock,
            };
            (i, kind)
        });
    Some(Table {
        sep,
        fields: fields.len(),
        position,
        position_um_per_unit,
        time,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Xl80Log {
        let mut p = CsvParser::new();
        p.feed(text.as_bytes());
        p.finish().unwrap()
    }

    #[test]
    fn semicolons_and_decimal_commas() {
        let log = parse(
            "Axis: X\r\nAir temperature: 20,3 °C\r\nMaterial temperature: 20,1 °C\r\n\
             Pressure: 1013,2 mbar\r\nHumidity: 45 %\r\nDate: 21/11/2026 10:00:00\r\n\
             Time (s);Position (mm)\r\n0,0;0,000000\r\n0,5;0,100250\r\n",
        );
        assert_eq!(log.meta.axis.as_deref(), Some("X"));
        assert_eq!(log.meta.air_temp_c, Some(20.3));
        assert_eq!(log.meta.material_temp_c, Some(20.1));
        assert_eq!(log.meta.pressure_mbar, Some(1013.2));
        assert_eq!(log.meta.humidity_pct, Some(45.0));
        assert!(log.start.is_some());
        assert_eq!(log.readings.len(), 2);
        assert!((log.readings[1].position_um - 100.25).abs() < 1e-9);
        assert_eq!(log.readings[1].t_s, Some(0.5));
        assert_eq!(log.readings[1].line, 9);
    }

    #[test]
    fn commas_micrometres_and_extra_columns() {
        let log = parse("Target (mm),Reading (um),Error (um)\n0,0.5,0.5\n0.05,49.2,-0.8\n");
        assert_eq!(
            log.readings
                .iter()
                .map(|r| r.position_um)
                .collect::<Vec<_>>(),
            vec![0.5, 49.2]
        );
        assert_eq!(log.readings[0].t_s, None);
    }

    #[test]
    fn tabs_clock_times_and_latin1() {
        let mut bytes = b"Date\t2026-11-21\nTime\tPosition (".to_vec();
        bytes.push(0xB5); // µ in Latin-1
        bytes.extend_from_slice(b"m)\n10:00:00.0\t1.5\n10:00:01.5\t2.5\n");
        let mut p = CsvParser::new();
        p.feed(&bytes);
        let log = p.finish().unwrap();
        assert_eq!(log.readings.len(), 2);
        assert_eq!(log.readings[1].position_um, 2.5);
        // Times of day count from the metadata date's midnight.
        assert_eq!(log.readings[0].t_s, Some(36_000.0));
        assert_eq!(log.readings[1].t_s, Some(36_001.5));
        let t0 = log.time_of(&log.readings[0]).unwrap();
        assert_eq!(
            t0.duration_since(UNIX_EPOCH).unwrap().as_secs(),
            parse_datetime("2026-11-21 10:00:00")
                .unwrap()
                .duration_since(UNIX_EPOCH)
                .unwrap()
                .as_secs()
        );
    }

    #[test]
    fn garbled_lines_are_counted_not_fatal() {
        let log = parse("Time (s),Position (mm)\n0,1\nxx,yy\n1\n2,3\n#!@\n");
        assert_eq!(log.readings.len(), 2);
        assert_eq!(log.garbled.count, 3);
        assert_eq!(log.garbled.examples[0].line, 3);
        assert!(
            log.garbled.examples[1].reason.contains("fields"),
            "{:?}",
            log.garbled
        );
    }

    #[test]
    fn incremental_feed_parses_only_complete_lines() {
        let mut p = CsvParser::new();
        assert_eq!(p.feed(b"Time (s),Position (mm)\n0,0.0"), 0);
        assert!(p.has_table());
        assert_eq!(p.feed(b"01\n1,0.0"), 1);
        assert_eq!(p.log().readings[0].position_um, 1.0);
        assert_eq!(p.feed(b"02\n"), 1);
        assert_eq!(p.log().readings[1].position_um, 2.0);
    }

    #[test]
    fn no_header_is_an_error() {
        let mut p = CsvParser::new();
        p.feed(b"hello\n1,2\n");
        assert!(p.finish().unwrap_err().contains("no header row"));
    }
}
