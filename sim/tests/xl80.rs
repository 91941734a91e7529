//! The XL-80 files have the exact structure rigd reads; the live log grows while it runs.
//! The checks here read the bytes by hand on purpose: no parser is shared with rigd.

use rigd_sim::motion::{Axis, AxisParams, TruePosition};
use rigd_sim::xl80::{write_log, CsvFormat, LengthUnit, LiveLog, LogFormat, Xl80, Xl80Params};
use std::sync::Arc;
use std::time::{Duration, Instant, UNIX_EPOCH};

fn params() -> Xl80Params {
    Xl80Params {
        date: Some("21/11/2026 23:40:00".into()),
        ..Default::default()
    }
}

/// Split an .rtx into header lines (without CRLF) and the data bytes, checking the frame.
fn split_rtx(bytes: &[u8]) -> (Vec<String>, &[u8], bool) {
    assert!(bytes.starts_with(b"HEADER::\r\n"), "starts with HEADER::");
    let data_at = bytes
        .windows(7)
        .position(|w| w == b"Data:\r\n")
        .expect("a Data: line");
    let head = std::str::from_utf8(&bytes[10..data_at]).expect("ASCII header");
    assert!(head.ends_with("\r\n"));
    // Every line ends in CRLF: no bare LF anywhere in the header.
    assert_eq!(head.matches('\n').count(), head.matches("\r\n").count());
    let lines = head
        .trim_end_matches("\r\n")
        .split("\r\n")
        .map(String::from)
        .collect();
    let rest = &bytes[data_at + 7..];
    let done = rest.ends_with(b"EOF::\r\n");
    let data = if done { &rest[..rest.len() - 7] } else { rest };
    (lines, data, done)
}

fn field<'a>(lines: &'a [String], key: &str) -> &'a str {
    lines
        .iter()
        .find_map(|l| l.strip_prefix(&format!("{key}: ")))
        .unwrap_or_else(|| panic!("no {key} in {lines:?}"))
        .trim()
}

fn samples_mm(data: &[u8]) -> Vec<f64> {
    assert_eq!(data.len() % 8, 0, "whole f64 samples");
    data.chunks(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

#[test]
fn rtx_has_the_carto_structure() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.rtx");
    let readings: Vec<f64> = (0..250).map(|i| i as f64 * 4.0).collect();
    write_log(&path, LogFormat::Rtx, &params(), UNIX_EPOCH, &readings).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let (lines, data, done) = split_rtx(&bytes);
    assert!(done, "ends with EOF::");
    let keys: Vec<&str> = lines
        .iter()
        .map(|l| l.split(": ").next().unwrap())
        .collect();
    assert_eq!(
        keys,
        [
            "Owner",
            "Version no",
            "File Type",
            "Velocity",
            "Sample rate",
            "Sample no",
            "Trigger point",
            "Trigger interval",
            "Actual sample rate",
            "Flags",
            "Machine",
            "Serial No",
            "Date",
            "By",
            "Axis",
            "Location"
        ]
    );
    assert_eq!(field(&lines, "Sample no"), "250");
    assert_eq!(field(&lines, "Sample rate"), "100");
    assert_eq!(field(&lines, "Actual sample rate"), "100");
    assert_eq!(field(&lines, "Trigger interval"), "0.01");
    assert_eq!(field(&lines, "Date"), "21/11/2026 23:40:00");
    let s = samples_mm(data);
    assert_eq!(s.len(), 250);
    // Samples in mm by default.
    assert_eq!(s[10], 0.04);
}

#[test]
fn csv_export_has_metadata_then_header_and_honours_units_and_decimal_comma() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.csv");
    let p = Xl80Params {
        csv: CsvFormat {
            unit: LengthUnit::Um,
            separator: ';',
            decimal_comma: true,
        },
        ..params()
    };
    write_log(&path, LogFormat::Csv, &p, UNIX_EPOCH, &[0.0, 12.5, 1000.25]).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    assert_eq!(text.matches('\n').count(), text.matches("\r\n").count());
    let lines: Vec<&str> = text.split("\r\n").collect();
    let header = lines
        .iter()
        .position(|l| *l == "Sample;Time (s);Position (µm)")
        .expect("header row");
    let meta = &lines[..header];
    for key in [
        "Air temperature (°C);20,40",
        "Material temperature (°C);20,10",
        "Air pressure (mbar);1012,80",
        "Humidity (%);46,0",
        "Date;21/11/2026 23:40:00",
        "Axis;X",
    ] {
        assert!(meta.contains(&key), "{key} in {meta:?}");
    }
    assert_eq!(lines[header + 1], "1;0,0000;0,000");
    assert_eq!(lines[header + 2], "2;0,0100;12,500");
    assert_eq!(lines[header + 3], "3;0,0200;1000,250");
    assert_eq!(lines[header + 4], "");

    // The default: commas, point decimals, millimetres.
    write_log(&path, LogFormat::Csv, &params(), UNIX_EPOCH, &[1000.25]).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.contains("\r\nSample,Time (s),Position (mm)\r\n1,0.0000,1.000250\r\n"));
}

#[test]
fn readings_follow_the_axis_with_the_set_noise() {
    let axis = Axis::new(AxisParams::default());
    axis.set_position(1234.0);
    let mut xl = Xl80::new(Xl80Params {
        noise_rms_um: 0.3,
        ..params()
    })
    .unwrap();
    let r = xl.capture(&axis, Instant::now(), 2000);
    let mean = r.iter().sum::<f64>() / r.len() as f64;
    let sd = (r.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / r.len() as f64).sqrt();
    assert!((mean - 1234.0).abs() < 0.05, "mean {mean}");
    assert!((sd - 0.3).abs() < 0.03, "sd {sd}");
}

#[test]
fn live_rtx_grows_while_the_axis_moves_and_is_completed_on_finish() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("live.rtx");
    let axis = Arc::new(Axis::new(AxisParams {
        position_error_rms_um: 0.0,
        ..Default::default()
    }));
    let p = Xl80Params {
        sample_rate_hz: 500.0,
        ..params()
    };
    let src: Arc<dyn TruePosition> = axis.clone();
    let log = LiveLog::start(&path, LogFormat::Rtx, p, src).unwrap();
    std::thread::sleep(Duration::from_millis(150));
    let early = std::fs::read(&path).unwrap();
    let (lines, data, done) = split_rtx(&early);
    assert!(!done, "no EOF:: while capturing");
    assert_eq!(field(&lines, "Sample no"), "0");
    let n_early = data.len() / 8;
    assert!(n_early > 10, "{n_early} samples after 150 ms at 500 Hz");

    let d = axis.command_move(2_000.0).unwrap();
    std::thread::sleep(d + Duration::from_millis(150));
    let later = std::fs::read(&path).unwrap();
    assert!(later.len() > early.len() + 8 * 40, "the file grows");
    let summary = log.finish().unwrap();

    let bytes = std::fs::read(&path).unwrap();
    let (lines, data, done) = split_rtx(&bytes);
    assert!(done, "EOF:: after finish");
    let s = samples_mm(data);
    assert_eq!(field(&lines, "Sample no"), s.len().to_string());
    assert_eq!(summary.samples, s.len());
    // Starts at 0 mm, ends at 2 mm (0.2 µm noise), passing through the move.
    assert!(s[0].abs() < 0.002 && (s[s.len() - 1] - 2.0).abs() < 0.002);
    assert!(
        s.iter().any(|&x| x > 0.5 && x < 1.5),
        "samples during the move"
    );
    // The header was patched in place: the same length as when it was first written.
    assert_eq!(
        early.windows(7).position(|w| w == b"Data:\r\n"),
        bytes.windows(7).position(|w| w == b"Data:\r\n")
    );
}

#[test]
fn live_csv_grows_and_bad_params_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("live.csv");
    let axis: Arc<dyn TruePosition> = Arc::new(Axis::new(AxisParams::default()));
    let log = LiveLog::start(&path, LogFormat::Csv, params(), axis.clone()).unwrap();
    std::thread::sleep(Duration::from_millis(300));
    let rows_early = std::fs::read_to_string(&path).unwrap().lines().count();
    std::thread::sleep(Duration::from_millis(300));
    let rows_later = std::fs::read_to_string(&path).unwrap().lines().count();
    assert!(
        rows_later > rows_early,
        "{rows_early} -> {rows_later} lines"
    );
    let s = log.finish().unwrap();
    let rows = std::fs::read_to_string(&path).unwrap().lines().count();
    assert_eq!(
        rows,
        11 + s.samples,
        "9 metadata lines + blank + header + samples"
    );

    let bad = Xl80Params {
        sample_rate_hz: -1.0,
        ..params()
    };
    let e = LiveLog::start(dir.path().join("x.csv"), LogFormat::Csv, bad, axis)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("sample_rate_hz"), "{e}");
}
