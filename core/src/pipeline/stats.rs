//! Statistics of a study: repeated runs of the paper's cases, reduced to its Tables 1-3.
//!
//! Per case and target: the mean measured offset along the nominal direction, in pixels of
//! the grid it was measured on (camera pixels x k: the paper's Table 1 reads 5.54 px for
//! 1000 µm at k = 5), the pixel ratio = nominal camera px / measured grid px (Table 2),
//! and the standard deviation over runs in µm (Table 3) with its RMS over targets.

use super::ObjectResult;
use serde::{Deserialize, Serialize};

/// The runs of one case: each run is the list of objects one processing gave.
#[derive(Debug, Clone)]
pub struct CaseRuns {
    pub name: String,
    pub frames: usize,
    pub step_um: f64,
    pub k: u32,
    pub runs: Vec<Vec<ObjectResult>>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct TargetStats {
    pub name: String,
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub nominal_um: f64,
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub nominal_px: f64,
    /// Runs in which the target was measured.
    pub n: usize,
    /// Mean offset along the nominal direction.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub mean_um: f64,
    /// The same in pixels of the measurement grid (camera px x k), Table 1.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub measured_grid_px: f64,
    /// nominal camera px / measured grid px, Table 2.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub pixel_ratio: f64,
    /// Standard deviation over runs (n - 1), Table 3.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub std_um: f64,
    /// Mean minus nominal.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub bias_um: f64,
    /// Offsets per run (µm along the nominal direction), Figure 4.
    pub per_run_um: Vec<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct CaseStats {
    pub name: String,
    pub frames: usize,
    pub step_um: f64,
    pub k: u32,
    pub targets: Vec<TargetStats>,
    /// sqrt(mean(std²)) over targets, Table 3's RMS row.
    #[serde(deserialize_with = "nan_if_null")]
    #[cfg_attr(feature = "schemars", schemars(with = "Option<f64>"))]
    pub rms_std_um: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct StudyStats {
    pub scale_um_per_px: f64,
    pub cases: Vec<CaseStats>,
}

/// A figure that may be undefined: NaN in memory, `null` in JSON (serde_json writes a NaN
/// as null), read back as NaN. The standard deviation of one repeat is such a figure.
pub fn nan_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// Offset of `o` along `nominal`'s direction (its x or y for the paper's board).
pub fn along_nominal(o: &ObjectResult, nominal_um: [f64; 2]) -> f64 {
    let n = nominal_um[0].hypot(nominal_um[1]);
    if n == 0.0 {
        return o.offset_um[0];
    }
    (o.offset_um[0] * nominal_um[0] + o.offset_um[1] * nominal_um[1]) / n
}

fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    if v.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let m = v.iter().sum::<f64>() / n;
    let s = if v.len() > 1 {
        (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
    } else {
        f64::NAN
    };
    (m, s)
}

/// Reduce one case. `names` picks and orders the targets (board names); runs without a
/// target simply do not count for it.
pub fn case_stats(case: &CaseRuns, names: &[&str], scale_um_per_px: f64) -> CaseStats {
    let targets: Vec<TargetStats> = names
        .iter()
        .filter_map(|&name| {
            let mut nominal = None;
            let per_run: Vec<f64> = case
                .runs
                .iter()
                .filter_map(|run| run.iter().find(|o| o.name.as_deref() == Some(name)))
                .filter_map(|o| {
                    let nom = o.nominal_um?;
                    nominal = Some(nom);
                    Some(along_nominal(o, nom))
                })
                .collect();
            let nom = nominal?;
            let nominal_um = nom[0].hypot(nom[1]);
            let (mean_um, std_um) = mean_std(&per_run);
            let nominal_px = nominal_um / scale_um_per_px;
            let measured_grid_px = mean_um / scale_um_per_px * case.k as f64;
            Some(TargetStats {
                name: name.to_string(),
                nominal_um,
                nominal_px,
                n: per_run.len(),
                mean_um,
                measured_grid_px,
                pixel_ratio: nominal_px / measured_grid_px,
                std_um,
                bias_um: mean_um - nominal_um,
                per_run_um: per_run,
            })
        })
        .collect();
    let stds: Vec<f64> = targets
        .iter()
        .map(|t| t.std_um)
        .filter(|s| s.is_finite())
        .collect();
    let rms_std_um = (stds.iter().map(|s| s * s).sum::<f64>() / stds.len() as f64).sqrt();
    CaseStats {
        name: case.name.clone(),
        frames: case.frames,
        step_um: case.step_um,
        k: case.k,
        targets,
        rms_std_um,
    }
}

pub fn study_stats(cases: &[CaseRuns], names: &[&str], scale_um_per_px: f64) -> StudyStats {
    StudyStats {
        scale_um_per_px,
        cases: cases
            .iter()
            .map(|c| case_stats(c, names, scale_um_per_px))
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn obj(name: &str, dx_um: f64, nominal: [f64; 2]) -> ObjectResult {
        ObjectResult {
            name: Some(name.into()),
            centre_px: [0.0, 0.0],
            offset_px: [dx_um / 774.0, 0.0],
            offset_um: [dx_um, 0.0],
            sigma_um: None,
            nominal_um: Some(nominal),
            outer_radius_px: 20.0,
            inner_radius_px: 8.0,
            frames: 1,
            effective_pixel_um: 774.0,
            ..Default::default()
        }
    }

    #[test]
    fn tables_follow_the_papers_definitions() {
        let runs = vec![
            vec![obj("B", 900.0, [1000.0, 0.0])],
            vec![obj("B", 1100.0, [1000.0, 0.0])],
            vec![obj("B", 1000.0, [1000.0, 0.0])],
        ];
        let case = CaseRuns {
            name: "case 2".into(),
            frames: 10,
            step_um: 100.0,
            k: 5,
            runs,
        };
        let s = case_stats(&case, &["B", "missing"], 774.0);
        assert_eq!(s.targets.len(), 1);
        let t = &s.targets[0];
        assert_eq!(t.n, 3);
        assert!((t.mean_um - 1000.0).abs() < 1e-9);
        assert!((t.std_um - 100.0).abs() < 1e-9);
        // 1000 µm at 774 µm/px and k = 5: 6.46 grid px, ratio 1.29/6.46 = 0.2.
        assert!((t.measured_grid_px - 6.459948).abs() < 1e-5);
        assert!((t.pixel_ratio - 0.2).abs() < 1e-12);
        assert!((s.rms_std_um - 100.0).abs() < 1e-9);
    }

    #[test]
    fn vertical_targets_use_their_y_offset() {
        let mut o = obj("Bv", 0.0, [0.0, 1000.0]);
        o.offset_um = [30.0, 950.0];
        assert!((along_nominal(&o, [0.0, 1000.0]) - 950.0).abs() < 1e-12);
    }
}
