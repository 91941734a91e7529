//! How rigd prints values to people: enums by their wire names, vectors as `(x, y)`,
//! durations, rates and times without Rust's Debug forms, numbers that stay short, and
//! tables whose columns line up.

use serde::Serialize;

/// The name a unit enum variant has on the wire and in configs (its serde name), e.g.
/// `ErrorCode::NotFound` -> `not_found`, `Estimator::Fit` -> `fit`.
pub fn wire_name<T: Serialize>(v: &T) -> String {
    match serde_json::to_value(v) {
        Ok(serde_json::Value::String(s)) => s,
        Ok(other) => other.to_string(),
        Err(_) => "?".into(),
    }
}

/// A number with no more digits than it needs: `-1`, `0`, `0.25`, `1e-7` (negative zero
/// prints as `0`).
pub fn num(x: f64) -> String {
    if x == 0.0 {
        return "0".into();
    }
    if !x.is_finite() {
        return "—".into();
    }
    let s = format!("{x}");
    if s.len() > 12 {
        format!("{x:.6}")
            .trim_end_matches('0')
            .trim_end_matches('.')
            .into()
    } else {
        s
    }
}

/// A 2-vector as `(x, y)`.
pub fn pair(v: [f64; 2]) -> String {
    format!("({}, {})", num(v[0]), num(v[1]))
}

/// A value to `digits` decimals, or `—` when it is undefined (NaN: e.g. the standard
/// deviation of one repeat) or missing.
pub fn fixed(x: Option<f64>, digits: usize) -> String {
    match x {
        Some(x) if x.is_finite() => {
            let s = format!("{x:.digits$}");
            // Rounded to zero prints without a sign: `0.0`, not `-0.0`.
            match s
                .trim_start_matches('-')
                .chars()
                .all(|c| c == '0' || c == '.')
            {
                true => s.trim_start_matches('-').to_string(),
                false => s,
            }
        }
        _ => "—".into(),
    }
}

/// Seconds as people read them: `42 s`, `3 min 05 s`, `2 h 07 min`.
pub fn duration(s: f64) -> String {
    if !s.is_finite() || s < 0.0 {
        return "—".into();
    }
    let t = s.round() as u64;
    match t {
        0..60 => format!("{t} s"),
        60..3600 => format!("{} min {:02} s", t / 60, t % 60),
        _ => format!("{} h {:02} min", t / 3600, (t % 3600) / 60),
    }
}

/// A frame rate with the precision it deserves: `12 frames/s`, `3.4 frames/s`,
/// `0.25 frames/s`; slow rates as seconds per frame.
pub fn rate(frames_per_s: f64) -> String {
    if !frames_per_s.is_finite() || frames_per_s <= 0.0 {
        return "—".into();
    }
    match frames_per_s {
        r if r >= 10.0 => format!("{r:.0} frames/s"),
        r if r >= 1.0 => format!("{r:.1} frames/s"),
        r if r >= 0.1 => format!("{r:.2} frames/s"),
        r => format!("{:.0} s/frame", 1.0 / r),
    }
}

/// An RFC 3339 UTC time as a short `YYYY-MM-DD HH:MM:SS` (UTC implied by the column).
pub fn short_time(rfc3339: &str) -> String {
    let s = rfc3339.trim_end_matches('Z');
    let s = s.split('.').next().unwrap_or(s);
    s.replacen('T', " ", 1)
}

/// Columns aligned to their widest cell: text left, numbers right (`right[i]`).
pub struct Table {
    header: Vec<String>,
    right: Vec<bool>,
    rows: Vec<Vec<String>>,
}

impl Table {
    /// A table with these column heads; a head starting with '>' is right-aligned.
    pub fn new(heads: &[&str]) -> Table {
        Table {
            header: heads
                .iter()
                .map(|h| h.trim_start_matches('>').to_string())
                .collect(),
            right: heads.iter().map(|h| h.starts_with('>')).collect(),
            rows: Vec::new(),
        }
    }

    pub fn row(&mut self, cells: Vec<String>) {
        self.rows.push(cells);
    }

    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// The table as text, two spaces between columns, no trailing blanks.
    pub fn render(&self) -> String {
        let cols = self.header.len();
        let width = |i: usize| {
            std::iter::once(&self.header)
                .chain(&self.rows)
                .filter_map(|r| r.get(i))
                .map(|c| c.chars().count())
                .max()
                .unwrap_or(0)
        };
        let widths: Vec<usize> = (0..cols).map(width).collect();
        let mut out = String::new();
        for r in std::iter::once(&self.header).chain(&self.rows) {
            let mut line = String::new();
            for (i, w) in widths.iter().enumerate() {
                let c = r.get(i).map(String::as_str).unwrap_or("");
                let pad = w.saturating_sub(c.chars().count());
                if i > 0 {
                    line.push_str("  ");
                }
                match self.right[i] {
                    true => line.extend(std::iter::repeat_n(' ', pad).chain(c.chars())),
                    false => line.extend(c.chars().chain(std::iter::repeat_n(' ', pad))),
                }
            }
            out.push_str(line.trim_end());
            out.push('\n');
        }
        out
    }
}

/// A length for a message: plain up to a kilometre, scientific beyond (a refusal of `1e308`
/// says `1e308`, not 309 digits).
pub fn short_um(v: f64) -> String {
    if v.is_finite() && v.abs() < 1e9 {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// The text of a panic payload.
pub fn panic_message(p: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = p.downcast_ref::<&str>() {
        s.to_string()
    } else if let Some(s) = p.downcast_ref::<String>() {
        s.clone()
    } else {
        "a panic without a message".into()
    }
}

/// An error and its causes as one line, `a: b: c`, leaving out a cause whose text the line
/// already holds (an error that quotes its source, as most of ours do, would otherwise
/// print it twice).
pub fn error_chain<'a>(
    chain: impl IntoIterator<Item = &'a (dyn std::error::Error + 'static)>,
) -> String {
    let mut line = String::new();
    for e in chain {
        let text = e.to_string();
        if line.contains(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::protocol::ErrorCode;
    use crate::pipeline::{Combine, Estimator};

    #[test]
    fn enums_print_their_wire_names() {
        assert_eq!(wire_name(&ErrorCode::NotFound), "not_found");
        assert_eq!(wire_name(&ErrorCode::Rejected), "rejected");
        assert_eq!(wire_name(&Estimator::Fit), "fit");
        assert_eq!(wire_name(&Combine::Interp), "interp");
    }

    #[test]
    fn vectors_and_numbers_print_short() {
        assert_eq!(pair([-1.0, -0.0]), "(-1, 0)");
        assert_eq!(pair([0.5, 2.0]), "(0.5, 2)");
        assert_eq!(num(0.1 + 0.2), "0.3");
        assert_eq!(fixed(Some(f64::NAN), 1), "—");
        assert_eq!(fixed(None, 1), "—");
        assert_eq!(fixed(Some(1.26), 1), "1.3");
        assert_eq!(fixed(Some(-0.04), 1), "0.0");
        assert_eq!(fixed(Some(-0.06), 1), "-0.1");
    }

    #[test]
    fn durations_and_rates_have_sensible_precision() {
        assert_eq!(duration(4.4), "4 s");
        assert_eq!(duration(185.0), "3 min 05 s");
        assert_eq!(duration(7620.0), "2 h 07 min");
        assert_eq!(duration(f64::NAN), "—");
        assert_eq!(rate(641.234), "641 frames/s");
        assert_eq!(rate(3.4567), "3.5 frames/s");
        assert_eq!(rate(0.25), "0.25 frames/s");
        assert_eq!(rate(0.02), "50 s/frame");
        assert_eq!(rate(0.0), "—");
        assert_eq!(
            short_time("2026-12-01T23:58:02.123Z"),
            "2026-12-01 23:58:02"
        );
    }

    #[test]
    fn table_columns_line_up() {
        let mut t = Table::new(&["job", "state", ">frames", "session"]);
        t.row(vec![
            "2".into(),
            "finished".into(),
            "5/5".into(),
            "s2".into(),
        ]);
        t.row(vec![
            "10".into(),
            "running".into(),
            "120/400".into(),
            "-".into(),
        ]);
        let text = t.render();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(
            lines,
            [
                "job  state      frames  session",
                "2    finished      5/5  s2",
                "10   running   120/400  -",
            ]
        );
        // Every column starts at the same offset on every line.
        let at = |l: &str| l.find("s2").or(l.find('-')).or(l.find("session"));
        assert_eq!(at(lines[0]), at(lines[1]));
        assert_eq!(at(lines[1]), at(lines[2]));
    }

    #[test]
    fn an_error_chain_names_each_cause_once() {
        #[derive(Debug, thiserror::Error)]
        #[error("session s: {source}")]
        struct Quoting {
            source: std::io::Error,
        }
        let io = || std::io::Error::new(std::io::ErrorKind::NotFound, "gone");
        let e = anyhow::Error::new(Quoting { source: io() }).context("export");
        assert_eq!(error_chain(e.chain()), "export: session s: gone");
        let e = anyhow::Error::new(io()).context("reading x");
        assert_eq!(error_chain(e.chain()), "reading x: gone");
    }
}
