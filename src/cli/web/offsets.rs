//! The offsets chart: each target's measured offset minus its nominal per run, with the
//! offset's standard uncertainty u as error bars, from the session's `results.csv`. On the
//! component the nominal lies along (a target without nominal: its x offset as measured).

use crate::plot::{Chart, Series, Style};
use crate::results_csv::{self, Row};
use std::collections::BTreeMap;
use std::path::Path;

/// The chart's name among the session's charts.
pub const STEM: &str = "offsets";

pub fn chart(session: &Path) -> anyhow::Result<Chart> {
    let rows = results_csv::read(&session.join(results_csv::FILE)).map_err(anyhow::Error::msg)?;
    Ok(chart_of(&rows))
}

/// (y, u) of one row on its target's main component.
fn point(r: &Row) -> (f64, f64) {
    let along_y =
        matches!((r.nominal_dx_um, r.nominal_dy_um), (Some(x), Some(y)) if y.abs() > x.abs());
    let (d, n, u) = if along_y {
        (r.dy_um, r.nominal_dy_um, r.u_dy_um)
    } else {
        (r.dx_um, r.nominal_dx_um, r.u_dx_um)
    };
    (d - n.unwrap_or(0.0), u.unwrap_or(f64::NAN))
}

fn chart_of(rows: &[Row]) -> Chart {
    let mut by_target: BTreeMap<&str, Vec<&Row>> = BTreeMap::new();
    for r in rows {
        by_target.entry(&r.target).or_default().push(r);
    }
    let series = by_target
        .into_iter()
        .map(|(name, rows)| {
            let (points, y_u) = rows
                .iter()
                .map(|r| {
                    let (y, u) = point(r);
                    ((r.run as f64 + 1.0, y), u)
                })
                .unzip();
            Series {
                label: name.to_string(),
                points,
                style: Style::Points,
                y_u,
            }
        })
        .collect();
    Chart {
        title: "Offsets with their standard uncertainty (±u)".into(),
        x_label: "run".into(),
        y_label: "offset − nominal (µm)".into(),
        series,
        x_names: None,
        size: (640, 400),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(target: &str, run: u32, d: [f64; 2], nominal: [f64; 2], u: f64) -> Row {
        Row {
            run,
            case: "scan".into(),
            repeat: run,
            target: target.into(),
            dx_um: d[0],
            dy_um: d[1],
            u_dx_um: Some(u),
            u_dy_um: Some(2.0 * u),
            nominal_dx_um: Some(nominal[0]),
            nominal_dy_um: Some(nominal[1]),
            bias_dx_um: None,
            bias_dy_um: None,
            frames: 10,
            k: 5,
            estimator: "fit".into(),
            combine: "interp".into(),
            registration: "image".into(),
        }
    }

    #[test]
    fn each_target_is_a_series_of_its_bias_on_its_nominal_component() {
        let rows = [
            row("H", 0, [2001.5, 0.2], [2000.0, 0.0], 0.5),
            row("V", 0, [0.1, 2997.0], [0.0, 3000.0], 0.5),
            row("H", 1, [1999.0, 0.0], [2000.0, 0.0], 0.5),
        ];
        let c = chart_of(&rows);
        assert_eq!(c.series.len(), 2);
        assert_eq!(c.series[0].label, "H");
        assert_eq!(c.series[0].points, vec![(1.0, 1.5), (2.0, -1.0)]);
        assert_eq!(c.series[0].y_u, vec![0.5, 0.5]);
        // V lies along y: its y bias and its y u.
        assert_eq!(c.series[1].points, vec![(1.0, -3.0)]);
        assert_eq!(c.series[1].y_u, vec![1.0]);
        let svg = c.svg().unwrap();
        assert!(svg.contains("offset − nominal (µm)"));
    }
}
