//! A job spec checked against the rig and expanded into runs, before anything moves.

use crate::daemon::protocol::{
    CaseScan, ErrorCode, JobRegistration, JobSpec, Processing, ProtoError,
};
use crate::daemon::rig::RigInfo;
use crate::pipeline::{Combine, Estimator};
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

/// `spec` with every processing field it leaves out filled in: from the rig's `[pipeline]`
/// defaults where the config sets them, else the protocol's own. A study's cases keep their
/// own k, and without a configured `combine` each case combines by its k (interp above 1,
/// else mean), so a study's `k` and possibly `combine` stay unset.
pub fn resolve_defaults(spec: &JobSpec, d: &Processing) -> JobSpec {
    let mut s = spec.clone();
    s.estimator = s.estimator.or(d.estimator).or(Some(Estimator::default()));
    s.combine = s.combine.or(d.combine);
    if s.study.is_none() {
        let k = *s.k.get_or_insert(d.k.unwrap_or(1));
        s.combine.get_or_insert(if k > 1 {
            Combine::Interp
        } else {
            Combine::Mean
        });
    }
    s.registration = s
        .registration
        .or(d.registration)
        .or(Some(JobRegistration::Image));
    s.whole_frame = s.whole_frame.or(d.whole_frame).or(Some(false));
    s
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

/// What a job of `frames` frames of `frame_size` may write: frames are written as PNG, and
/// an 8-bit RGB frame's raw size bounds its PNG closely enough for noisy images (they
/// barely compress); 4 KiB a frame for its steps.csv row and file-system slack, 1 MiB for
/// the manifest, result and images.
pub fn estimated_bytes(frames: u64, frame_size: (u32, u32)) -> u64 {
    let (w, h) = frame_size;
    frames.saturating_mul(w as u64 * h as u64 * 3 + 4096) + (1 << 20)
}

fn mb(bytes: u64) -> u64 {
    bytes >> 20
}

fn disk_message(frames: u32, need: u64, committed: u64, root: &Path, free: u64) -> String {
    let root = root.display();
    if committed == 0 {
        format!(
            "{frames} frames need about {} MB but {root} has {} MB free",
            mb(need),
            mb(free)
        )
    } else {
        format!(
            "{frames} frames need about {} MB, {} MB are already committed to queued and \
             running jobs, and {root} has {} MB free",
            mb(need),
            mb(committed),
            mb(free)
        )
    }
}

/// Check `spec` against the rig and the disk and expand it into runs. `committed_bytes`:
/// what the jobs already queued or running are still expected to write (their
/// [`estimated_bytes`] for the frames they have left), which the free space must also hold.
pub fn plan(
    spec: &JobSpec,
    rig: &RigInfo,
    data_root: &Path,
    committed_bytes: u64,
) -> Result<Plan, ProtoError> {
    let cases = cases(spec)?;
    if spec.repeats == 0 {
        return Err(rejected("`repeats` must be at least 1"));
    }
    if spec.registration == Some(JobRegistration::Interferometer) && !rig.interferometer {
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
    let need = estimated_bytes(total, rig.frame_size);
    if let Some(free) = free_bytes(data_root) {
        if need.saturating_add(committed_bytes) > free {
            return Err(rejected(disk_message(
                total_frames,
                need,
                committed_bytes,
                data_root,
                free,
            )));
        }
    }
    Ok(Plan { runs, total_frames })
}

/// Free bytes for an unprivileged writer on the filesystem holding `path`.
pub fn free_bytes(path: &Path) -> Option<u64> {
    let st = nix::sys::statvfs::statvfs(path).ok()?;
    #[allow(clippy::unnecessary_cast)] // the field types differ between targets
    Some(st.blocks_available() as u64 * st.fragment_size() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::protocol::PaperCase;
    use crate::pipeline::Registration;

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
            job_defaults: Processing::default(),
            grab_timeout_ms: 5000,
        }
    }

    #[test]
    fn omitted_processing_takes_the_rigs_defaults_and_explicit_values_win() {
        let scan = JobSpec {
            steps: Some(3),
            step_um: Some(10.0),
            ..JobSpec::default()
        };
        // No configured defaults (rigd --sim): the protocol's own, k-dependent combine.
        let r = resolve_defaults(&scan, &Processing::default());
        assert_eq!(
            (r.k, r.estimator, r.combine, r.registration, r.whole_frame),
            (
                Some(1),
                Some(Estimator::Fit),
                Some(Combine::Mean),
                Some(JobRegistration::Image),
                Some(false)
            )
        );
        let k4 = resolve_defaults(
            &JobSpec {
                k: Some(4),
                ..scan.clone()
            },
            &Processing::default(),
        );
        assert_eq!(k4.combine, Some(Combine::Interp));
        let rig = Processing {
            k: Some(6),
            estimator: Some(Estimator::Paper),
            combine: None,
            // The config names the commanded positions "positions".
            registration: Some(Registration::Positions.into()),
            whole_frame: Some(true),
        };
        let r = resolve_defaults(&scan, &rig);
        assert_eq!(
            (r.k, r.estimator, r.combine, r.registration, r.whole_frame),
            (
                Some(6),
                Some(Estimator::Paper),
                Some(Combine::Interp),
                Some(JobRegistration::Commanded),
                Some(true)
            )
        );
        // ...and processing runs with them.
        let o = crate::daemon::protocol::process_options(&r, 6, 774.0, [-1.0, 0.0]);
        assert_eq!(
            (o.k, o.estimator, o.combine, o.registration, o.whole_frame),
            (
                6,
                Estimator::Paper,
                Combine::Interp,
                Registration::Positions,
                true
            )
        );
        let explicit = JobSpec {
            k: Some(1),
            estimator: Some(Estimator::Fit),
            combine: Some(Combine::Splat),
            registration: Some(JobRegistration::Interferometer),
            whole_frame: Some(false),
            ..scan.clone()
        };
        assert_eq!(resolve_defaults(&explicit, &rig), explicit);
        // A study's cases keep their own k (and combine by it when nothing is configured).
        let study = JobSpec {
            study: Some(PaperCase::ALL.to_vec()),
            ..JobSpec::default()
        };
        let s = resolve_defaults(&study, &rig);
        assert_eq!(
            (s.k, s.combine, s.estimator),
            (None, None, Some(Estimator::Paper))
        );
        assert!(plan(&s, &super::tests::rig(), Path::new("/tmp"), 0).is_ok());
    }

    #[test]
    fn the_disk_check_counts_what_queued_jobs_will_write() {
        let t = Path::new("/tmp");
        let free = free_bytes(t).expect("statvfs of /tmp");
        // Frames of about a tenth of the free space each: six of them fit, but not next to
        // six more already queued.
        let rig = RigInfo {
            frame_size: (1000, (free / 30_000).max(1) as u32),
            ..rig()
        };
        let six = JobSpec {
            steps: Some(6),
            step_um: Some(10.0),
            ..JobSpec::default()
        };
        let need = estimated_bytes(6, rig.frame_size);
        assert!(plan(&six, &rig, t, 0).is_ok());
        let e = plan(&six, &rig, t, need).unwrap_err();
        assert_eq!(e.code, ErrorCode::Rejected);
        let m = e.message;
        assert!(m.starts_with("6 frames need about "), "{m}");
        assert!(
            m.contains(&format!(
                ", {} MB are already committed to queued",
                need >> 20
            )),
            "{m}"
        );
        assert!(m.contains("/tmp has ") && m.ends_with(" MB free"), "{m}");
        // Nothing queued, too big alone: the single-job message.
        let e = plan(
            &JobSpec {
                steps: Some(12),
                ..six.clone()
            },
            &rig,
            t,
            0,
        )
        .unwrap_err();
        assert!(e.message.contains(" MB but /tmp has "), "{}", e.message);
        assert_eq!(estimated_bytes(2, (10, 10)), 2 * (300 + 4096) + (1 << 20));
    }

    #[test]
    fn the_paper_study_expands_to_sixty_runs_of_620_frames() {
        let spec = JobSpec {
            study: Some(PaperCase::ALL.to_vec()),
            repeats: 20,
            repeat_shift_um: 38.7,
            ..JobSpec::default()
        };
        let p = plan(&spec, &rig(), Path::new("/tmp"), 0).unwrap();
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
        assert!(plan(&zero, &r, t, 0)
            .unwrap_err()
            .message
            .contains("non-zero"));
        let far = JobSpec {
            step_um: Some(5000.0),
            ..base.clone()
        };
        assert!(plan(&far, &r, t, 0)
            .unwrap_err()
            .message
            .contains("soft limits"));
        let piezo = JobSpec {
            stage: crate::daemon::protocol::StageKind::Piezo,
            ..base.clone()
        };
        assert!(plan(&piezo, &r, t, 0)
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
        assert!(plan(&big, &huge, t, 0)
            .unwrap_err()
            .message
            .contains("MB free"));
        assert!(plan(&base, &r, t, 0).is_ok());
        let by_laser = JobSpec {
            registration: Some(JobRegistration::Interferometer),
            ..base.clone()
        };
        let e = plan(&by_laser, &r, t, 0).unwrap_err();
        assert!(e.message.contains("[xl80]"), "{}", e.message);
        let with_laser = RigInfo {
            interferometer: true,
            ..rig()
        };
        assert!(plan(&by_laser, &with_laser, t, 0).is_ok());
    }
}
