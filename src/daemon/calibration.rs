//! The daemon's calibrations (docs/calibration.md, "In the daemon"): what a job applies —
//! the data root's current record (`calibration_store`), checked against the job's rig for
//! its age, frame size, scale and board, every mismatch a warning in the job's events, its
//! result, its manifest and the log — and what a calibration job makes of its session.

use crate::acquisition::calibration_job::CalibrationScan;
use crate::calibration::Calibration;
use crate::calibration_file::Applied;
use crate::calibration_note::{Calibrated, CalibrationNote};
use crate::offline::calibrate::{fit_folder, FolderFit};
use crate::rig::RigInfo;
use std::path::Path;
use std::time::SystemTime;

/// The calibration a job applies, and what it says of it.
#[derive(Debug, Clone, Default)]
pub struct JobCalibration {
    pub applied: Option<Applied>,
    pub note: CalibrationNote,
}

impl JobCalibration {
    fn none(reason: impl Into<String>) -> JobCalibration {
        JobCalibration {
            applied: None,
            note: CalibrationNote {
                reason: Some(reason.into()),
                ..CalibrationNote::default()
            },
        }
    }
}

/// The calibration a job on `rig` applies: none for a calibration scan, else the data
/// root's current one, checked. An error (naming the file) when the current one cannot be
/// read: the job does not run on a calibration it cannot read.
pub fn for_job(
    data_root: &Path,
    max_age_days: f64,
    rig: &RigInfo,
    calibrating: bool,
) -> Result<JobCalibration, String> {
    if calibrating {
        return Ok(JobCalibration::none("a calibration scan"));
    }
    match crate::calibration_store::current(data_root) {
        Ok(Some(a)) => Ok(checked(a, rig, max_age_days, SystemTime::now())),
        Ok(None) => Ok(JobCalibration::none(format!(
            "no current calibration in {} (rigctl calibrate makes one)",
            crate::calibration_store::dir(data_root).display()
        ))),
        Err(e) => Err(format!(
            "the current calibration cannot be used: {} (calibrate again, or remove {})",
            crate::text::error_chain(e.chain()),
            crate::calibration_store::dir(data_root)
                .join(crate::calibration_store::CURRENT)
                .display()
        )),
    }
}

/// `a` checked against `rig` at `now`: too old, or fitted on another scale or board, it is
/// applied with warnings; fitted on another frame size it cannot be, and is not.
fn checked(a: Applied, rig: &RigInfo, max_age_days: f64, now: SystemTime) -> JobCalibration {
    let cal = &a.calibration;
    let age_days = age_days(&cal.date, now);
    let mut warnings = Vec::new();
    if let Some(age) = age_days.filter(|&d| d > max_age_days) {
        warnings.push(format!(
            "calibration {} is {age:.1} days old, over the {max_age_days} days allowed \
             ([daemon] calibration_max_age_days): calibrate again (rigctl calibrate)",
            cal.id
        ));
    }
    if age_days.is_none() {
        warnings.push(format!(
            "calibration {}: its date {:?} is not RFC 3339, its age is unknown",
            cal.id, cal.date
        ));
    }
    let board = rig.board.as_ref().map(|b| b.name.as_str());
    let (applied, reason) = match cal.check(rig.frame_size, rig.scale_um_per_px, board) {
        Ok(w) => {
            warnings.extend(w);
            (true, None)
        }
        Err(e) => {
            let why = format!("{e}: not applied, offsets use the global scale");
            warnings.push(why.clone());
            (false, Some(why))
        }
    };
    let note = CalibrationNote {
        applied,
        id: Some(cal.id.clone()),
        date: Some(cal.date.clone()),
        method: Some(crate::text::wire_name(&cal.method)),
        source: Some(a.source.clone()),
        age_days,
        reason,
        warnings,
    };
    JobCalibration {
        applied: applied.then_some(a),
        note,
    }
}

/// Days from an RFC 3339 `date` to `now` (None: not a date).
fn age_days(date: &str, now: SystemTime) -> Option<f64> {
    use time::format_description::well_known::Rfc3339;
    let then = time::OffsetDateTime::parse(date, &Rfc3339).ok()?;
    let now = time::OffsetDateTime::from(now);
    Some((now - then).as_seconds_f64() / 86_400.0)
}

/// The rig in a line, for the record: mode, camera, board, scale, frame size.
pub fn rig_description(rig: &RigInfo) -> String {
    let c = &rig.config;
    let camera = c["camera_profile"]
        .as_str()
        .map(|p| format!("sim camera profile {p}"))
        .or_else(|| {
            c["camera"]["device"]
                .as_str()
                .map(|d| format!("camera {d}"))
        })
        .or_else(|| {
            c["camera"]["driver"]
                .as_str()
                .map(|d| format!("camera {d}"))
        })
        .unwrap_or_else(|| "camera (unnamed model)".into());
    format!(
        "{} rig: {camera}, board {}, {} µm/px, {}x{} frames",
        crate::text::wire_name(&rig.mode),
        rig.board.as_ref().map_or("none", |b| b.name.as_str()),
        rig.scale_um_per_px,
        rig.frame_size.0,
        rig.frame_size.1
    )
}

/// Fit the calibration of a calibration job's session `dir` (named `session`), taken on
/// `rig`, and keep it as the data root's current one.
pub fn fit_session(
    data_root: &Path,
    dir: &Path,
    session: &str,
    rig: &RigInfo,
    scan: &CalibrationScan,
) -> anyhow::Result<Calibrated> {
    let fit = FolderFit {
        scale_um_per_px: rig.scale_um_per_px,
        board: rig.board.clone(),
        reference: scan.registration.into(),
        axis_dir: rig.axis_dir,
        reference_rel_u: scan.reference_rel_u,
        rig: Some(rig_description(rig)),
        response: rig.response,
    };
    let mut cal = fit_folder(dir, &fit)?;
    cal.scan.session = Some(session.to_string());
    if let Some(m) = cal.ink_margin.as_ref().filter(|m| m.halos()) {
        tracing::warn!(
            margin_s = m.margin_s,
            "{}",
            crate::calibration_note::HALO_ADVICE
        );
    }
    let path = crate::calibration_store::save_current(data_root, &cal)?;
    Ok(made(&cal, &path, session))
}

fn made(cal: &Calibration, path: &Path, session: &str) -> Calibrated {
    Calibrated {
        id: cal.id.clone(),
        date: cal.date.clone(),
        method: crate::text::wire_name(&cal.method),
        path: path.display().to_string(),
        session: session.to_string(),
        frames: cal.scan.frames,
        step_um: cal.scan.step_um,
        targets: cal.targets.len(),
        residual_rms_um: cal.field.residual_rms_um,
        residual_max_um: cal.field.residual_max_um,
        summary: crate::calibration_note::summary(cal),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn age_is_counted_from_the_records_date() {
        let now = SystemTime::UNIX_EPOCH + Duration::from_secs(40 * 86_400);
        let d = age_days("1970-01-01T00:00:00Z", now).unwrap();
        assert!((d - 40.0).abs() < 1e-9, "{d}");
        assert!(age_days("yesterday", now).is_none());
    }
}
