//! A calibration record on disk: JSON (`rigctl calibrate --out FILE`), read back by
//! `rigctl process --calibration FILE`, `rigctl reprocess --calibration FILE`.

use crate::bounds;
use crate::calibration::{Calibration, CALIBRATION_VERSION};
use anyhow::Context;
use std::path::Path;
use std::sync::Arc;

/// Read and check a calibration file: errors name the file. A regular file only (no
/// symlink, FIFO or device at its name), at most [`bounds::MAX_DOCUMENT_BYTES`].
pub fn load(path: &Path) -> anyhow::Result<Arc<Calibration>> {
    let bytes = crate::nofollow::read_regular_max(path, bounds::MAX_DOCUMENT_BYTES)
        .with_context(|| format!("{}: cannot read the calibration", path.display()))?;
    parse(&bytes, path)
}

/// Targets a record may hold (a board has tens).
pub const MAX_TARGETS: usize = 4096;
/// Entries in any other list of a record (a target's residuals, rejections, ink bumps).
pub const MAX_ENTRIES: usize = 1 << 20;
/// Characters in a record's text fields (id, date, rig).
const MAX_TEXT_CHARS: usize = 256;

/// Check and decode a calibration record read from `path` (errors name it and the field).
pub fn parse(bytes: &[u8], path: &Path) -> anyhow::Result<Arc<Calibration>> {
    let v: serde_json::Value = serde_json::from_slice(bytes)
        .with_context(|| format!("{}: not a calibration record (JSON)", path.display()))?;
    let version = v.get("version").and_then(|x| x.as_u64());
    if version != Some(CALIBRATION_VERSION as u64) {
        anyhow::bail!(
            "{}: calibration record version {}: this rigd reads version {CALIBRATION_VERSION}",
            path.display(),
            version.map_or("missing".into(), |v| v.to_string())
        );
    }
    let cal: Calibration = serde_json::from_value(v).map_err(|e| {
        let e = bounds::cut(&e.to_string(), 300);
        anyhow::anyhow!("{}: not a calibration record: {e}", path.display())
    })?;
    check(&cal).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    Ok(Arc::new(cal))
}

/// A record's names, sizes and numbers in range: what a run applies must give finite
/// offsets. The error names the field.
pub fn check(cal: &Calibration) -> Result<(), String> {
    bounds::one_component("id", &cal.id)?;
    for (what, text) in [("date", Some(&cal.date)), ("rig", cal.rig.as_ref())] {
        if text.is_some_and(|t| t.chars().count() > MAX_TEXT_CHARS) {
            return Err(format!("{what} is over {MAX_TEXT_CHARS} characters"));
        }
    }
    let [w, h] = cal.fingerprint.frame_size;
    bounds::frame_size(w, h).map_err(|e| format!("fingerprint.frame_size {e}"))?;
    let scale = cal.fingerprint.scale_um_per_px;
    bounds::in_range("fingerprint.scale_um_per_px", scale, 1e-6, 1e6)?;
    if cal.targets.len() > MAX_TARGETS {
        return Err(format!(
            "{} targets, over the {MAX_TARGETS} a record may hold",
            cal.targets.len()
        ));
    }
    let lists = [
        ("rejected", cal.rejected.len()),
        ("ink_fields", cal.ink_fields.len()),
        ("field.covariance", cal.field.covariance.len()),
        ("field.parameters", cal.field.parameters.len()),
    ];
    let residuals = cal
        .targets
        .iter()
        .map(|t| ("targets[].residuals_um", t.residuals_um.len()));
    let bumps = cal
        .ink_fields
        .iter()
        .map(|f| ("ink_fields[].bumps_um", f.bumps_um.len()));
    for (what, n) in lists.into_iter().chain(residuals).chain(bumps) {
        if n > MAX_ENTRIES {
            return Err(format!(
                "{what}: {n} entries, over the {MAX_ENTRIES} allowed"
            ));
        }
    }
    check_model(&cal.field.model)?;
    check_model_error(cal)
}

/// The numbers every conversion's model u is made of (`Calibration::model_rel_u`).
fn check_model_error(cal: &Calibration) -> Result<(), String> {
    use bounds::in_range;
    let f = &cal.field;
    in_range("field.stage_dir_rad", f.stage_dir_rad, -1e3, 1e3)?;
    if let Some(z) = f.zoom_per_um {
        in_range("field.zoom_per_um", z, -1e-2, 1e-2)?;
    }
    if let Some(c) = &f.check {
        in_range("field.check.model_rel_u", c.model_rel_u, 0.0, 1.0)?;
    }
    in_range("scan.travel_um", cal.scan.travel_um, 0.0, 1e9)?;
    for t in &cal.targets {
        in_range("targets[].residual_rms_um", t.residual_rms_um, 0.0, 1e9)?;
        in_range(
            "targets[].model_residual_rms_um",
            t.model_residual_rms_um,
            0.0,
            1e9,
        )?;
    }
    Ok(())
}

/// The field model's numbers: those a run converts every offset with.
fn check_model(m: &crate::calibration::FieldModel) -> Result<(), String> {
    use bounds::in_range;
    let side = bounds::MAX_FRAME_SIDE_PX as f64;
    in_range(
        "field.model.centre_px[0]",
        m.centre_px[0],
        -side,
        2.0 * side,
    )?;
    in_range(
        "field.model.centre_px[1]",
        m.centre_px[1],
        -side,
        2.0 * side,
    )?;
    in_range(
        "field.model.norm_radius_px",
        m.norm_radius_px,
        1.0,
        2.0 * side,
    )?;
    let a = m.a_px_per_um;
    for (i, v) in a.as_flattened().iter().enumerate() {
        in_range(
            &format!("field.model.a_px_per_um[{}][{}]", i / 2, i % 2),
            *v,
            -1e6,
            1e6,
        )?;
    }
    let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    if det.abs() < 1e-12 {
        return Err(format!(
            "field.model.a_px_per_um is singular (determinant {det}): no µm per px from it"
        ));
    }
    in_range("field.model.g_per_um[0]", m.g_per_um[0], -1e-2, 1e-2)?;
    in_range("field.model.g_per_um[1]", m.g_per_um[1], -1e-2, 1e-2)?;
    in_range("field.model.k1", m.k1, -10.0, 10.0)?;
    in_range("field.model.k2", m.k2, -10.0, 10.0)?;
    Ok(())
}

/// Write a calibration as pretty JSON, atomically.
pub fn save(path: &Path, cal: &Calibration) -> anyhow::Result<()> {
    let mut text = serde_json::to_string_pretty(cal)?;
    text.push('\n');
    crate::atomic_file::write(path, text.as_bytes())
        .with_context(|| format!("{}: cannot write the calibration", path.display()))
}

/// A calibration as a run applies it: the record and the file it came from.
#[derive(Debug, Clone)]
pub struct Applied {
    pub calibration: Arc<Calibration>,
    pub source: String,
}

impl Applied {
    /// Read `path` ([`load`]).
    pub fn load(path: &Path) -> anyhow::Result<Applied> {
        Ok(Applied {
            calibration: load(path)?,
            source: path.display().to_string(),
        })
    }

    /// Hand it to a run's pipeline.
    pub fn apply(&self, pipeline: &mut crate::pipeline::Pipeline) {
        pipeline.set_calibration(Some(self.calibration.clone()), Some(self.source.clone()));
    }
}
