//! The calibration records' shared vocabulary: the note a job's events, result and manifest
//! carry of the calibration it used, what a calibration job made, the age past which a
//! record is stale, and the summary text `rigctl calibrate` and the daemon print.

use crate::calibration::Calibration;
use serde::{Deserialize, Serialize};

/// `[daemon] calibration_max_age_days` when the config leaves it out.
pub const DEFAULT_MAX_AGE_DAYS: f64 = 30.0;

/// The calibration a job used, as its manifest, result and `calibration` event name it.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, schemars::JsonSchema)]
pub struct CalibrationNote {
    /// Whether the job's offsets are converted with it (false: the global scale).
    pub applied: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// When it was made (RFC 3339).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub date: Option<String>,
    /// `commanded` or `interferometer`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<String>,
    /// The record's file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub age_days: Option<f64>,
    /// Why none is applied, when none is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Stale, or fitted on another scale, board or frame size.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// What a calibration job made: the record kept as the data root's current calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Calibrated {
    pub id: String,
    pub date: String,
    pub method: String,
    /// The record's file (`<data_root>/calibrations/<id>.json`).
    pub path: String,
    pub session: String,
    pub frames: usize,
    pub step_um: f64,
    pub targets: usize,
    pub residual_rms_um: f64,
    pub residual_max_um: f64,
    /// `rigctl calibrate`'s summary of it, as text.
    pub summary: String,
}

/// A few lines: the field's residuals and per target its local scale and uncertainty.
pub fn summary(cal: &Calibration) -> String {
    let f = &cal.field;
    let mut s = format!(
        "calibration {} ({:?}, {} frames, step {} µm, {} layout): field model residual RMS {:.2} µm, max {:.2} µm\n",
        cal.id, cal.method, cal.scan.frames, cal.scan.step_um, f.layout, f.residual_rms_um, f.residual_max_um
    );
    for p in &f.parameters {
        s += &format!("  {:<15} {:>14.6e} ± {:.2e}\n", p.name, p.value, p.u);
    }
    s += "  target  centre_px           µm/px (own)   µm/px (model)  u_rel   line RMS µm\n";
    for t in &cal.targets {
        s += &format!(
            "  {:<7} ({:>7.1}, {:>6.1})  {:>9.3} ±{:.3} {:>9.3}  {:.1e}  {:.2}\n",
            t.name.as_deref().unwrap_or("-"),
            t.centre_px[0],
            t.centre_px[1],
            t.scale_um_per_px,
            t.scale_u_um_per_px,
            t.model_scale_um_per_px,
            t.model_scale_rel_u,
            t.residual_rms_um
        );
    }
    s += &model_check_line(cal);
    s += &ink_line(cal);
    s += &ink_margin_line(cal);
    s += &lateral_line(cal);
    s
}

/// The field model against targets it was not fitted to, and the u every conversion carries
/// for what it cannot know.
fn model_check_line(cal: &Calibration) -> String {
    let c = cal.model_check();
    let pct = |x: f64| format!("{:.3} %", 100.0 * x);
    let rates = format!(
        "{} / {} (along / across) against the noise's {} / {}",
        pct(c.rms_rel[0]),
        pct(c.rms_rel[1]),
        pct(c.noise_rel[0]),
        pct(c.noise_rel[1])
    );
    let verdict = if c.holds {
        format!("holds: the targets' rates match it to {rates}")
    } else if c.failed.iter().any(|f| f == "leave-one-out") {
        format!("DOES NOT describe this rig: the targets' rates miss it by {rates}")
    } else {
        format!(
            "the targets' rates match it to {rates}, but their places miss it beyond their noise (a print off its design, or a field the model does not describe)"
        )
    };
    let mut s = format!(
        "  field model checked ({}, {} targets): {verdict}; every offset carries a model u of {} of its length\n",
        c.method, c.targets, pct(c.model_rel_u)
    );
    match (cal.field.layout.as_str(), cal.field.zoom_per_um) {
        ("free", _) => s += &format!(
            "  no board: the scan cannot tell a rail out of the board's plane from a tilt; offsets carry up to {} more at the frame's edge along the stage (calibrate with --board to fit it)\n",
            pct(crate::calibration::validation::gauge_rel_u(
                &cal.field.model,
                cal.field.stage_dir_rad,
                [cal.field.model.centre_px[0] * 2.0, cal.field.model.centre_px[1]],
            ))
        ),
        (_, Some(z)) => {
            let u = (cal.field.parameters.iter())
                .find(|p| p.name == "rail_zoom_per_um")
                .map_or(0.0, |p| p.u);
            s += &if z.abs() > 2.0 * u {
                format!(
                    "  the rail zooms the image by {:.2e} ± {:.1e} per mm of travel ({:+.3} % over the scan): it is out of the board's plane, and the fit allows for it\n",
                    z * 1000.0,
                    u * 1000.0,
                    -100.0 * z * cal.scan.travel_um
                )
            } else {
                format!(
                    "  no zoom over the travel ({:.1e} ± {:.1e} per mm): the rail is parallel to the board\n",
                    z * 1000.0,
                    u * 1000.0
                )
            };
        }
        _ => {}
    }
    s
}

/// How close to the edges the ink was read, and the bands against the interior it was
/// chosen from.
fn ink_margin_line(cal: &Calibration) -> String {
    let Some(m) = &cal.ink_margin else {
        return String::new();
    };
    let bands: Vec<String> = (m.bands.iter())
        .map(|b| {
            format!(
                "{:.2}–{:.2}: {:+.2} ± {:.2} %",
                b.from_s,
                b.to_s,
                100.0 * b.density_diff,
                100.0 * b.u_density_diff
            )
        })
        .collect();
    let mut s = format!(
        "  ink read from {:.2} blur widths inside the edges (bands against the interior, in blur widths: {})\n",
        m.margin_s,
        bands.join("; ")
    );
    if m.halos() {
        s += &format!("  {HALO_ADVICE}\n");
    }
    s
}

/// What a calibration whose bands show halos tells the user (`InkMargin::halos`).
pub const HALO_ADVICE: &str = "the frames show halos just inside the edges (most often the camera \
    sharpening its frames): set `[camera] sharpness = 0` (docs/camera.md) and calibrate again to \
    read the ink nearer the edges";

/// The lens's lateral colour as the scan measured it: each registered channel's
/// magnification against green and what it comes to at the frame's corner.
fn lateral_line(cal: &Calibration) -> String {
    let Some(l) = &cal.lateral_colour else {
        return "  lateral colour: not measured (jobs mix the channels as they are)\n".into();
    };
    let corner = l.model.centre_px[0].hypot(l.model.centre_px[1]);
    let channels: Vec<String> = [(0, "red"), (2, "blue")]
        .into_iter()
        .filter(|&(c, _)| l.shifts[c] > 0)
        .map(|(c, name)| {
            format!(
                "{name} {:+.2e} ± {:.1e} ({:+.3} px at the corner, {:.3} px RMS residual, {} shifts)",
                l.model.magnification[c],
                l.magnification_u[c],
                l.model.magnification[c] * corner,
                l.residual_rms_px[c],
                l.shifts[c]
            )
        })
        .collect();
    format!(
        "  lateral colour against green: {}; jobs register these channels onto green\n",
        channels.join(", ")
    )
}

/// What the scan learnt of the print's ink, and whether jobs take it as the fit's prior.
fn ink_line(cal: &Calibration) -> String {
    let Some(i) = &cal.ink else {
        return "  print's ink: not resolved by the scan (jobs take the print as evenly inked)\n"
            .into();
    };
    let maps = &cal.ink_fields;
    let taken = match (i.prior(), maps.is_empty()) {
        (Some(_), true) => "jobs take it as the fit's prior".to_string(),
        (Some(_), false) => {
            let left = maps.iter().map(|f| f.residual_rms).sum::<f64>() / maps.len() as f64;
            format!(
                "jobs take it as the fit's prior, centred on {} targets' maps ({:.2} % left unknown at the edges)",
                maps.len(),
                100.0 * left
            )
        }
        (None, _) => "even enough: jobs take the print as evenly inked".to_string(),
    };
    format!(
        "  print's ink: density RMS {:.2} % ± {:.2} %, correlation {:.0} ± {:.0} µm ({} shapes, blur {:.2} px): {taken}\n",
        100.0 * i.density_rms,
        100.0 * i.u_density_rms,
        i.corr_um,
        i.u_corr_um,
        i.shapes,
        i.blur_px
    )
}
