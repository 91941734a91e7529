//! Reports: one processing result as text, and a study as the paper's Tables 1-3 (text and
//! JSON) and plots like its Figures 4 and 5 (PNG, drawn with the `image` crate: lines and
//! markers on a grid, no text; the docs say what the axes are).

use crate::cli::text::wire_name;
use crate::pipeline::stats::{StudyStats, TargetStats};
use crate::pipeline::ProcessResult;
use image::{Rgb, RgbImage};
use std::fmt::Write;

/// A processing result as a small table.
pub fn result_text(r: &ProcessResult) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{} frame(s) {}x{}, k = {}, estimator {}, combine {}, registration {}",
        r.frames,
        r.width,
        r.height,
        r.options.k,
        wire_name(&r.options.estimator),
        wire_name(&r.options.combine),
        wire_name(&r.options.registration)
    );
    let _ = writeln!(
        s,
        "{:<6} {:>9} {:>9} {:>10} {:>10} {:>8} {:>8} {:>10}",
        "target", "u_px", "v_px", "dx_um", "dy_um", "sx_um", "sy_um", "nominal"
    );
    for (i, o) in r.objects.iter().enumerate() {
        let name = o.name.clone().unwrap_or_else(|| format!("#{i}"));
        let (sx, sy) = match o.sigma_um {
            Some([a, b]) => (format!("{a:.1}"), format!("{b:.1}")),
            None => ("-".into(), "-".into()),
        };
        let nom = o
            .nominal_um
            .map(|n| format!("{:.0},{:.0}", n[0], n[1]))
            .unwrap_or_else(|| "-".into());
        let _ = writeln!(
            s,
            "{:<6} {:>9.2} {:>9.2} {:>10.1} {:>10.1} {:>8} {:>8} {:>10}",
            name, o.centre_px[0], o.centre_px[1], o.offset_um[0], o.offset_um[1], sx, sy, nom
        );
    }
    for k in &r.skipped {
        let _ = writeln!(
            s,
            "skipped at ({:.1}, {:.1}): {}",
            k.centre_px[0], k.centre_px[1], k.reason
        );
    }
    s
}

/// Tables 1-3 of the paper for a study, as fixed-width text.
pub fn study_tables(st: &StudyStats) -> String {
    let mut s = String::new();
    let names: Vec<&str> = st
        .cases
        .first()
        .map(|c| c.targets.iter().map(|t| t.name.as_str()).collect())
        .unwrap_or_default();
    table1(&mut s, st, &names);
    table2(&mut s, st, &names);
    table3(&mut s, st, &names);
    s
}

/// A target's statistics in case `c`.
fn cell<'a>(st: &'a StudyStats, c: usize, name: &str) -> Option<&'a TargetStats> {
    st.cases[c].targets.iter().find(|t| t.name == name)
}

fn table1(s: &mut String, st: &StudyStats, names: &[&str]) {
    let cases = &st.cases;
    let _ = writeln!(
        s,
        "Table 1: nominal and measured offsets (measured in pixels of each case's grid)"
    );
    let _ = write!(s, "{:<7} {:>9} {:>9}", "target", "nom_um", "nom_px");
    for c in cases {
        let _ = write!(s, " {:>12}", format!("{} (k={})", short(&c.name), c.k));
    }
    s.push('\n');
    for n in names {
        let t0 = cell(st, 0, n).expect("from case 0");
        let _ = write!(s, "{:<7} {:>9.0} {:>9.2}", n, t0.nominal_um, t0.nominal_px);
        for c in 0..cases.len() {
            let v = cell(st, c, n)
                .map(|t| t.measured_grid_px)
                .unwrap_or(f64::NAN);
            let _ = write!(s, " {:>12}", f(v, 2));
        }
        s.push('\n');
    }
}

fn table2(s: &mut String, st: &StudyStats, names: &[&str]) {
    let cases = &st.cases;
    let _ = writeln!(
        s,
        "\nTable 2: pixel ratio = nominal camera px / measured grid px"
    );
    let _ = write!(s, "{:<7} {:>9}", "target", "nom_px");
    for c in cases {
        let _ = write!(s, " {:>12}", short(&c.name));
    }
    s.push('\n');
    for n in names {
        let nominal_px = cell(st, 0, n).expect("case 0").nominal_px;
        let _ = write!(s, "{n:<7} {nominal_px:>9.2}");
        for c in 0..cases.len() {
            let v = cell(st, c, n).map(|t| t.pixel_ratio).unwrap_or(f64::NAN);
            let _ = write!(s, " {:>12}", f(v, 2));
        }
        s.push('\n');
    }
}

fn table3(s: &mut String, st: &StudyStats, names: &[&str]) {
    let cases = &st.cases;
    let _ = writeln!(
        s,
        "\nTable 3: standard deviation over runs (µm), and mean - nominal (µm)"
    );
    let _ = write!(s, "{:<7}", "target");
    for c in cases {
        let _ = write!(
            s,
            " {:>12} {:>9}",
            format!("std {}", short(&c.name)),
            "bias"
        );
    }
    s.push('\n');
    for n in names {
        let _ = write!(s, "{n:<7}");
        for c in 0..cases.len() {
            let (sd, b) = cell(st, c, n)
                .map(|t| (t.std_um, t.bias_um))
                .unwrap_or((f64::NAN, f64::NAN));
            let _ = write!(s, " {:>12} {:>9}", f(sd, 1), f(b, 1));
        }
        s.push('\n');
    }
    let _ = write!(s, "{:<7}", "RMS");
    for c in cases {
        let _ = write!(s, " {:>12} {:>9}", f(c.rms_std_um, 1), "");
    }
    s.push('\n');
    if cases.len() > 1 && cases[0].rms_std_um > 0.0 {
        let _ = write!(s, "{:<7}", "gain");
        for c in cases {
            let gain = cases[0].rms_std_um / c.rms_std_um;
            let _ = write!(s, " {:>12} {:>9}", format!("{}x", f(gain, 2)), "");
        }
        s.push('\n');
    }
}

/// A table figure, or `—` when it is undefined (the spread of a single repeat).
fn f(x: f64, digits: usize) -> String {
    crate::cli::text::fixed(Some(x), digits)
}

fn short(name: &str) -> String {
    name.chars().take(12).collect()
}

/// The study as JSON (the stats, per-run offsets included).
pub fn study_json(st: &StudyStats) -> String {
    serde_json::to_string_pretty(st).expect("stats serialise")
}

const COLOURS: [[u8; 3]; 12] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [127, 127, 127],
    [188, 189, 34],
    [23, 190, 207],
    [0, 0, 0],
    [100, 100, 255],
];

/// A minimal line plot: series of (x, y) on axes fitted to the data, with grid lines at
/// `grid` steps of y. No text.
pub struct Plot {
    pub width: u32,
    pub height: u32,
    pub series: Vec<Vec<(f64, f64)>>,
    pub y_grid: f64,
}

impl Plot {
    pub fn render(&self) -> RgbImage {
        let mut img = RgbImage::from_pixel(self.width, self.height, Rgb([255, 255, 255]));
        let pts = self
            .series
            .iter()
            .flatten()
            .filter(|p| p.0.is_finite() && p.1.is_finite());
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for &(x, y) in pts {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
        if x0 > x1 {
            return img;
        }
        if self.y_grid > 0.0 {
            y0 = (y0 / self.y_grid).floor() * self.y_grid;
            y1 = (y1 / self.y_grid).ceil() * self.y_grid;
        }
        if x1 == x0 {
            x1 = x0 + 1.0;
        }
        if y1 == y0 {
            y1 = y0 + 1.0;
        }
        let m = 30.0;
        let (w, h) = (self.width as f64 - 2.0 * m, self.height as f64 - 2.0 * m);
        let to = |x: f64, y: f64| (m + (x - x0) / (x1 - x0) * w, m + (y1 - y) / (y1 - y0) * h);
        let grey = Rgb([210, 210, 210]);
        if self.y_grid > 0.0 {
            let mut g = y0;
            while g <= y1 + 1e-9 {
                let (_, py) = to(x0, g);
                line(&mut img, (m, py), (m + w, py), grey);
                g += self.y_grid;
            }
        }
        let black = Rgb([0, 0, 0]);
        line(&mut img, (m, m), (m, m + h), black);
        line(&mut img, (m, m + h), (m + w, m + h), black);
        for (i, s) in self.series.iter().enumerate() {
            let c = Rgb(COLOURS[i % COLOURS.len()]);
            let p: Vec<(f64, f64)> = s
                .iter()
                .filter(|p| p.0.is_finite() && p.1.is_finite())
                .map(|&(x, y)| to(x, y))
                .collect();
            for q in p.windows(2) {
                line(&mut img, q[0], q[1], c);
            }
            for &(px, py) in &p {
                for dy in -2..=2 {
                    for dx in -2..=2 {
                        put(&mut img, px + dx as f64, py + dy as f64, c);
                    }
                }
            }
        }
        img
    }
}

fn put(img: &mut RgbImage, x: f64, y: f64, c: Rgb<u8>) {
    let (x, y) = (x.round(), y.round());
    if x >= 0.0 && y >= 0.0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, c);
    }
}

fn line(img: &mut RgbImage, a: (f64, f64), b: (f64, f64), c: Rgb<u8>) {
    let n = (b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil().max(1.0) as usize;
    for i in 0..=n {
        let t = i as f64 / n as f64;
        put(img, a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t, c);
    }
}

/// Figure 4 of the paper for one case: each target's measured offset (µm, minus its
/// nominal so all targets share one axis) against the experiment number.
pub fn figure4(st: &StudyStats, case: usize) -> RgbImage {
    let series = st.cases[case]
        .targets
        .iter()
        .map(|t| {
            t.per_run_um
                .iter()
                .enumerate()
                .map(|(i, v)| ((i + 1) as f64, v - t.nominal_um))
                .collect()
        })
        .collect();
    Plot {
        width: 640,
        height: 400,
        series,
        y_grid: 100.0,
    }
    .render()
}

/// Figure 5: the RMS standard deviation (µm) against the case number (1, 2, 3).
pub fn figure5(st: &StudyStats) -> RgbImage {
    let series = vec![st
        .cases
        .iter()
        .enumerate()
        .map(|(i, c)| ((i + 1) as f64, c.rms_std_um))
        .collect()];
    Plot {
        width: 480,
        height: 360,
        series,
        y_grid: 50.0,
    }
    .render()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::stats::CaseStats;

    fn case(name: &str, k: u32, std_um: f64) -> CaseStats {
        CaseStats {
            name: name.into(),
            frames: 1,
            step_um: 0.0,
            k,
            targets: vec![TargetStats {
                name: "B".into(),
                nominal_um: 1000.0,
                nominal_px: 1000.0 / 774.0,
                n: 3,
                mean_um: 1000.0,
                measured_grid_px: 1000.0 / 774.0 * k as f64,
                pixel_ratio: 1.0 / k as f64,
                std_um,
                bias_um: 0.0,
                per_run_um: vec![1000.0 - std_um, 1000.0, 1000.0 + std_um],
            }],
            rms_std_um: std_um,
        }
    }

    #[test]
    fn tables_show_each_case_and_the_gain() {
        let st = StudyStats {
            scale_um_per_px: 774.0,
            cases: vec![case("case 1", 1, 280.0), case("case 2", 5, 100.0)],
        };
        let t = study_tables(&st);
        assert!(t.contains("Table 1") && t.contains("Table 2") && t.contains("Table 3"));
        let b_row = t.lines().find(|l| l.starts_with("B ")).unwrap();
        assert!(b_row.contains("1.29") && b_row.contains("6.46"), "{b_row}");
        let gain = t.lines().find(|l| l.starts_with("gain")).unwrap();
        assert!(gain.contains("2.80x"), "{gain}");
        let back: StudyStats = serde_json::from_str(&study_json(&st)).unwrap();
        assert_eq!(back.cases.len(), 2);
        assert_eq!(back.cases[1].targets[0].per_run_um.len(), 3);
        assert_eq!(figure5(&st).dimensions(), (480, 360));
        assert_eq!(figure4(&st, 1).dimensions(), (640, 400));
    }

    #[test]
    fn plot_draws_series_inside_the_frame() {
        let p = Plot {
            width: 200,
            height: 100,
            series: vec![vec![(0.0, 0.0), (1.0, 1.0)]],
            y_grid: 0.5,
        };
        let img = p.render();
        // The first series' colour at the corners of the data area.
        let c = Rgb(COLOURS[0]);
        assert_eq!(*img.get_pixel(30, 70), c);
        assert_eq!(*img.get_pixel(170, 30), c);
        assert_eq!(*img.get_pixel(100, 10), Rgb([255, 255, 255]));
    }
}
