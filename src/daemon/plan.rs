//! A job spec checked against the rig and expanded into runs, before anything moves.

use crate::daemon::protocol::{CaseScan, ErrorCode, JobRegistration, JobSpec, ProtoError};
use crate::daemon::rig::RigInfo;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Most frames one job may ask for.
pub const MAX_FRAMES: u32 = 100_000;

/// One scan of one case in one repeat.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunPlan {
    pub run: u32,
    pub case: CaseScan,
    pub repeat: u32,
    /// Commanded position of every frame.
    pub positions_um: Vec<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    pub runs: Vec<RunPlan>,
    pub total_frames: u32,
}

fn rejected(msg: impl Into<String>) -> ProtoError {
    ProtoError::new(ErrorCode::Rejected, msg)
}

/// The scans a job asks for, checked for shape.
fn cases(spec: &JobSpec) -> Result<Vec<CaseScan>, ProtoError> {
    match &spec.study {
        Some(study) => {
            if spec.step_um.is_some() || spec.steps.is_some() || spec.k.is_some() {
                return Err(rejected(
                    "give either `study` or `step_um`/`steps`/`k`, not both",
                ));
            }
            if study.is_empty() {
                return Err(rejected("`study` names no case"));
            }
            Ok(study.iter().map(|c| c.scan()).collect())
        }
        None => {
            let steps = spec
                .steps
                .ok_or_else(|| rejected("`steps` is missing (or give a `study`)"))?;
            let step_um = spec.step_um.unwrap_or(0.0);
            if steps > 1 && spec.step_um.is_none() {
                return Err(rejected("`step_um` is missing"));
            }
            Ok(vec![CaseScan {
                name: "scan".into(),
                frames: steps,
                step_um,
                k: spec.k.unwrap_or(1),
            }])
        }
    }
}

/// Check `spec` against the rig and the disk and expand it into runs.
pub fn plan(spec: &JobSpec, rig: &RigInfo, data_root: &Path) -> Result<Plan, ProtoError> {
    let cases = cases(spec)?;
    if spec.repeats == 0 {
        return Err(rejected("`repeats` must be at least 1"));
    }
    if spec.registration == JobRegistration::Interferometer && !rig.interferometer {
        return Err(rejected(
            "`registration`: \"interferometer\" needs an interferometer, and this rig has none \
             (no [xl80] section in its configuration)",
        ));
    }
    let limits = rig
        .limits_um(spec.stage)
        .ok_or_else(|| rejected(format!("this rig has no {:?} stage", spec.stage)))?;
    for (name, v) in [
        ("start_um", spec.start_um.unwrap_or(0.0)),
        ("repeat_shift_um", spec.repeat_shift_um),
    ] {
        if !v.is_finite() {
            return Err(rejected(format!("`{name}` must be a finite number")));
        }
    }
    let start = spec.start_um.unwrap_or(match spec.stage {
        crate::daemon::protocol::StageKind::Axis => rig.default_start_um,
        crate::daemon::protocol::StageKind::Piezo => limits[0],
    });
    let mut runs = Vec::new();
    let mut total: u64 = 0;
    for repeat in 0..spec.repeats {
        for c in &cases {
            if c.frames == 0 {
                return Err(rejected(format!("{}: `steps` must be at least 1", c.name)));
            }
            if c.k == 0 || c.k > 64 {
                return Err(rejected(format!(
                    "{}: `k` must be 1..=64, got {}",
                    c.name, c.k
                )));
            }
            if !c.step_um.is_finite() || (c.frames > 1 && c.step_um == 0.0) {
                return Err(rejected(format!(
                    "{}: `step_um` must be a non-zero finite number for {} frames, got {}",
                    c.name, c.frames, c.step_um
                )));
            }
            total += c.frames as u64;
            if total > MAX_FRAMES as u64 {
                return Err(rejected(format!(
                    "the job asks for more than {MAX_FRAMES} frames"
                )));
            }
            let first = start + repeat as f64 * spec.repeat_shift_um;
            let positions_um: Vec<f64> = (0..c.frames)
                .map(|i| first + i as f64 * c.step_um)
                .collect();
            for &p in [positions_um[0], positions_um[positions_um.len() - 1]].iter() {
                if p < limits[0] || p > limits[1] {
                    return Err(rejected(format!(
                        "{} repeat {repeat}: position {p} µm leaves the {:?} soft limits [{}, {}] µm",
                        c.name, spec.stage, limits[0], limits[1]
                    )));
                }
            }
            runs.push(RunPlan {
                run: runs.len() as u32,
                case: c.clone(),
                repeat,
                positions_um,
            });
        }
    }
    let total_frames = total as u32;
    // Frames are written as PNG; an 8-bit RGB frame's raw size bounds its PNG closely
    // enough for noisy images (they barely compress).
    let (w, h) = rig.frame_size;
    let need = total * (w as u64 * h as u64 * 3 + 4096) + (1 << 20);
    if let Some(free) = free_bytes(data_root) {
        if need > free {
            return Err(rejected(format!(
                "{total_frames} frames need about {} MB but {} has {} MB free",
                need >> 20,
                data_root.display(),
                free >> 20
            )));
        }
    }
    Ok(Plan { runs, total_frames })
}

/// Free bytes for an unprivileged writer on the filesystem holding `path`.
pub fn free_bytes(path: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(path.as_os_str().as_bytes()).ok()?;
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `c` is a valid NUL-terminated path and `st` a valid out-pointer.
    let rc = unsafe { libc::statvfs(c.as_ptr(), &mut st) };
    (rc == 0).then(|| st.f_bavail as u64 * st.f_frsize as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::protocol::PaperCase;

    fn rig() -> RigInfo {
        RigInfo {
            mode: "sim".into(),
            axis_limits_um: [0.0, 10_000.0],
            piezo_limits_um: None,
            default_start_um: 1000.0,
            scale_um_per_px: 774.0,
            axis_dir: [-1.0, 0.0],
            frame_size: (64, 48),
            interferometer: false,
            board: None,
            config: serde_json::Value::Null,
        }
    }

    #[test]
    fn the_paper_study_expands_to_sixty_runs_of_620_frames() {
        let spec = JobSpec {
            study: Some(PaperCase::ALL.to_vec()),
            repeats: 20,
            repeat_shift_um: 38.7,
            ..JobSpec::default()
        };
        let p = plan(&spec, &rig(), Path::new("/tmp")).unwrap();
        assert_eq!((p.runs.len(), p.total_frames), (60, 620));
        assert_eq!(p.runs[5].positions_um[0], 1000.0 + 38.7);
        assert_eq!(p.runs[2].positions_um[19], 1000.0 + 19.0 * 50.0);
    }

    #[test]
    fn zero_steps_limits_disk_and_missing_stages_are_rejected() {
        let base = JobSpec {
            steps: Some(3),
            step_um: Some(10.0),
            ..JobSpec::default()
        };
        let r = rig();
        let t = Path::new("/tmp");
        let zero = JobSpec {
            step_um: Some(0.0),
            ..base.clone()
        };
        assert!(plan(&zero, &r, t).unwrap_err().message.contains("non-zero"));
        let far = JobSpec {
            step_um: Some(5000.0),
            ..base.clone()
        };
        assert!(plan(&far, &r, t)
            .unwrap_err()
            .message
            .contains("soft limits"));
        let piezo = JobSpec {
            stage: crate::daemon::protocol::StageKind::Piezo,
            ..base.clone()
        };
        assert!(plan(&piezo, &r, t)
            .unwrap_err()
            .message
            .contains("no Piezo"));
        let huge = RigInfo {
            frame_size: (100_000, 100_000),
            ..rig()
        };
        let big = JobSpec {
            steps: Some(50),
            step_um: Some(1.0),
            ..base.clone()
        };
        assert!(plan(&big, &huge, t)
            .unwrap_err()
            .message
            .contains("MB free"));
        assert!(plan(&base, &r, t).is_ok());
        let by_laser = JobSpec {
            registration: JobRegistration::Interferometer,
            ..base.clone()
        };
        let e = plan(&by_laser, &r, t).unwrap_err();
        assert!(e.message.contains("[xl80]"), "{}", e.message);
        let with_laser = RigInfo {
            interferometer: true,
            ..rig()
        };
        assert!(plan(&by_laser, &with_laser, t).is_ok());
    }
}
