//! What a job will take, estimated from its plan at submit: the disk it writes (frames,
//! rows, and the reconstructions' 16-bit PNGs) and the memory its processing needs (the
//! pipeline's peak per run, the reconstructions kept until the job ends and encoded then,
//! the frames in flight between the engine, the disk and processing). Checked against the
//! daemon's budgets before anything moves, so a job that would fill the disk or exhaust the
//! machine's memory is refused with the figures, not killed half-way.

use crate::acquisition::plan::{estimated_bytes, Plan, PlanError};
use crate::acquisition::rig::RigInfo;

/// Frames held in memory at once besides processing's own: the engine's, two in the
/// recorder's queue, four in the processor's, one being written, one being decoded.
pub const FRAMES_IN_FLIGHT: u64 = 9;
/// PNG overhead of one image on top of its raw pixels (headers, zlib framing, filters).
const PNG_SLACK_BYTES: u64 = 64 * 1024;

/// The 16-bit images a plan's runs keep (bytes each run), in run order.
fn kept_images(plan: &Plan, rig: &RigInfo) -> Vec<u64> {
    plan.runs
        .iter()
        .map(|r| {
            r.processing.as_ref().map_or(0, |o| {
                o.kept_image_bytes(rig.frame_size, rig.board.as_ref())
            })
        })
        .collect()
}

/// The disk a job writes: its frames ([`estimated_bytes`]; a resumed job's from its first
/// missing one) and its reconstructions' PNGs (every run's).
pub fn disk_bytes(plan: &Plan, rig: &RigInfo) -> u64 {
    reconstruction_bytes(plan, rig).saturating_add(estimated_bytes(
        plan.frames_to_capture() as u64,
        rig.frame_size,
    ))
}

/// The disk the reconstructions' PNGs take (about their raw 16-bit size).
pub fn reconstruction_bytes(plan: &Plan, rig: &RigInfo) -> u64 {
    kept_images(plan, rig)
        .into_iter()
        .filter(|&b| b > 0)
        .map(|b| b + PNG_SLACK_BYTES)
        .sum()
}

/// The most memory a job's processing holds at once. Runs are processed one after the
/// other; each run's reconstructions are kept until the job ends, when each is copied and
/// encoded in turn: the copy, and the PNG buffer growing by doubling (up to twice the image
/// while it reallocates), three times the largest image on top of them all. With
/// `calibration_prior` (the calibration the job will apply learnt an ink prior), the
/// prior's working set in every run that takes it.
pub fn memory_bytes(plan: &Plan, rig: &RigInfo, calibration_prior: bool) -> u64 {
    let (w, h) = rig.frame_size;
    let in_flight = FRAMES_IN_FLIGHT * 3 * w as u64 * h as u64;
    let images = kept_images(plan, rig);
    let mut kept: u64 = 0;
    let mut peak: u64 = 0;
    for (r, img) in plan.runs.iter().zip(&images) {
        if let Some(o) = &r.processing {
            let frames = r.positions_um.len() as u32;
            let mut run = o.peak_memory_bytes(rig.frame_size, frames, rig.board.as_ref());
            if calibration_prior && o.calibration_ink && o.ink_prior.is_none() {
                run += o.ink_prior_bytes(rig.frame_size, rig.board.as_ref());
            }
            peak = peak.max(kept.saturating_add(run));
        }
        kept = kept.saturating_add(*img);
    }
    let largest = images.iter().copied().max().unwrap_or(0);
    let closing = kept.saturating_add(3 * largest);
    peak.max(closing).saturating_add(in_flight)
}

fn mb(bytes: u64) -> u64 {
    bytes.div_ceil(1 << 20)
}

/// Refuse a plan whose processing needs more than `budget_mb` MB, naming the estimate, what
/// drives it and the budget. A capture-only job is not refused: it holds only the frames in
/// flight.
pub fn check_memory(
    plan: &Plan,
    rig: &RigInfo,
    budget_mb: u64,
    calibration_prior: bool,
) -> Result<u64, PlanError> {
    let need = memory_bytes(plan, rig, calibration_prior);
    let processes = plan.runs.iter().any(|r| r.processing.is_some());
    if !processes || need <= budget_mb.saturating_mul(1 << 20) {
        return Ok(need);
    }
    let (w, h) = rig.frame_size;
    let heaviest = plan
        .runs
        .iter()
        .filter_map(|r| r.processing.as_ref().map(|o| (r, o)))
        .max_by_key(|(r, o)| {
            o.peak_memory_bytes(
                rig.frame_size,
                r.positions_um.len() as u32,
                rig.board.as_ref(),
            )
        });
    let what = match heaviest {
        Some((r, o)) => format!(
            " (its heaviest run: {} repeat {}, {} frames of {w}x{h} at k = {}{})",
            r.case.name,
            r.repeat,
            r.positions_um.len(),
            o.k,
            match o.whole_frame {
                true => " with the whole frame reconstructed",
                false => "",
            }
        ),
        None => String::new(),
    };
    Err(PlanError(format!(
        "processing this job needs about {} MB of memory{what}, over the daemon's budget of \
         {budget_mb} MB ([daemon] max_job_memory_mb): lower k, leave out whole_frame or split \
         the job",
        mb(need)
    )))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquisition::job::JobSpec;
    use crate::acquisition::plan::plan;
    use crate::acquisition::rig::{RigInfo, RigMode};
    use std::path::Path;

    fn rig(frame_size: (u32, u32)) -> RigInfo {
        RigInfo {
            mode: RigMode::Sim,
            axis_limits_um: [0.0, 100_000.0],
            piezo_limits_um: None,
            axis_max_step_um: None,
            piezo_max_step_um: None,
            axis_settle_ms: None,
            piezo_settle_ms: None,
            default_start_um: 1000.0,
            scale_um_per_px: 774.0,
            axis_dir: [-1.0, 0.0],
            piezo_dir: None,
            frame_size,
            response: Default::default(),
            ink_prior: None,
            interferometer: false,
            axis_machine: None,
            board: Some(crate::board::Board::paper()),
            config: serde_json::Value::Null,
            job_defaults: Default::default(),
            grab_timeout_ms: 5000,
        }
    }

    fn job(k: u32, frames: u32, whole_frame: bool) -> JobSpec {
        JobSpec {
            steps: Some(frames),
            step_um: Some(10.0),
            k: Some(k),
            whole_frame: Some(whole_frame),
            ..JobSpec::default()
        }
        .with_defaults(&Default::default())
    }

    #[test]
    fn a_whole_frame_at_k32_is_counted_on_disk_and_refused_in_memory() {
        let r = rig((1280, 720));
        // Planned without the whole frame (this disk may not hold its 1.9 GB), then given
        // the whole frame's options as a submit would.
        let p = plan(&job(32, 2, false), &r, Path::new("/tmp"), 0).unwrap();
        let whole = 2 * 32 * 32 * 1280 * 720_u64; // 1.89 GB of 16-bit pixels
        let plan_whole = Plan {
            runs: vec![crate::acquisition::plan::RunPlan {
                processing: Some(
                    crate::acquisition::plan::run_options(&job(32, 2, true), 32, &r).unwrap(),
                ),
                ..p.runs[0].clone()
            }],
            ..p
        };
        let disk = reconstruction_bytes(&plan_whole, &r);
        assert!(
            disk > whole && disk < whole + whole / 20,
            "{disk} vs {whole}"
        );
        // In memory: the 4 k² w h f32 reconstruction and its 16-bit copy while the run
        // ends, then the copy kept, copied again and encoded when the job ends: four 16-bit
        // images, 7.55 GB. A run of this job peaks at 7.5 GB (measured).
        let mem = memory_bytes(&plan_whole, &r, false);
        assert!((7_200_000_000..8_000_000_000).contains(&mem), "{mem}");
        let e = check_memory(&plan_whole, &r, 2048, false).unwrap_err().0;
        assert!(
            e.starts_with("processing this job needs about ")
                && e.contains("at k = 32 with the whole frame reconstructed")
                && e.contains("budget of 2048 MB ([daemon] max_job_memory_mb)"),
            "{e}"
        );
    }

    #[test]
    fn ordinary_jobs_fit_the_default_budget() {
        let r = rig((1280, 720));
        for (k, frames, whole) in [(10, 20, false), (1, 100, false), (8, 10, true)] {
            let p = plan(&job(k, frames, whole), &r, Path::new("/tmp"), 0).unwrap();
            let mem = check_memory(&p, &r, 2048, false).unwrap();
            // Never less than the frames in flight (25 MB at 1280x720).
            assert!(mem >= FRAMES_IN_FLIGHT * 3 * 1280 * 720, "k={k}: {mem}");
        }
        // k = 10 whole frame: 2 k² w h = 184.3 MB of 16-bit image, and the paper board's
        // 12 targets' windows of 590² fine pixels, 8.4 MB: 192.7 MB of PNG.
        let p = plan(&job(10, 4, true), &r, Path::new("/tmp"), 0).unwrap();
        let png = reconstruction_bytes(&p, &r);
        let want = 2 * 100 * (1280 * 720 + 12 * 59 * 59);
        assert!(png >= want && png < want + want / 100, "{png} vs {want}");
        assert_eq!(disk_bytes(&p, &r), png + estimated_bytes(4, (1280, 720)));
        // Capture only: nothing kept, nothing processed.
        let raw = JobSpec {
            process: false,
            ..job(32, 4, true)
        };
        let p = plan(&raw, &r, Path::new("/tmp"), 0).unwrap();
        assert_eq!(reconstruction_bytes(&p, &r), 0);
        assert_eq!(
            memory_bytes(&p, &r, false),
            FRAMES_IN_FLIGHT * 3 * 1280 * 720
        );
    }

    /// The ink prior a calibration learnt is taken when the job runs: its working set is in
    /// the estimate when the current calibration has one, once, and not when the rig's
    /// own `ink_prior` (already counted) wins.
    #[test]
    fn a_calibrations_learnt_prior_is_counted_once() {
        let r = rig((1280, 720));
        let p = plan(&job(10, 20, false), &r, Path::new("/tmp"), 0).unwrap();
        let o = p.runs[0].processing.as_ref().unwrap();
        let prior = o.ink_prior_bytes(r.frame_size, r.board.as_ref());
        assert!(
            prior >= crate::pipeline::estimate::PRIOR_PEAK_BYTES,
            "{prior}"
        );
        // (Less than the whole prior where the job's end, its images kept, held more than
        // its run did: 280 of 296 MB on 2 threads, by 16 MB on any.)
        let (without, with) = (memory_bytes(&p, &r, false), memory_bytes(&p, &r, true));
        assert!(
            with - without > prior * 3 / 4 && with - without <= prior,
            "{with} {without}"
        );
        let given = RigInfo {
            ink_prior: Some(crate::pipeline::InkPrior {
                density_rms: 0.04,
                corr_um: 3000.0,
            }),
            ..r
        };
        let p = plan(&job(10, 20, false), &given, Path::new("/tmp"), 0).unwrap();
        let own = memory_bytes(&p, &given, false);
        assert_eq!(memory_bytes(&p, &given, true), own);
        // The same working set, inside the run's model (with its 2 % slack).
        assert!(own >= with && own < with + with / 40, "{own} {with}");
    }
}
