//! Reports: one processing result as text, and a study as the paper's Tables 1-3 (text and
//! JSON). Its Figures 4 and 5 are `figures`' charts.

use crate::pipeline::stats::{StudyStats, TargetStats};
use crate::pipeline::ProcessResult;
use crate::text::wire_name;
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
    crate::text::fixed(Some(x), digits)
}

fn short(name: &str) -> String {
    name.chars().take(12).collect()
}

/// The study as JSON (the stats, per-run offsets included).
pub fn study_json(st: &StudyStats) -> String {
    serde_json::to_string_pretty(st).expect("stats serialise")
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
    }
}
