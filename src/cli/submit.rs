//! `rigctl submit`: queue a capture job and follow it with a progress bar.

use crate::acquisition::study::JobResult;
use crate::acquisition::{JobRegistration, JobSpec, PaperCase, Processing, StageKind};
use crate::cli::client::{report_end, Client, SocketArg};
use crate::cli::results::results_table;
use crate::daemon::protocol::Request;
use crate::pipeline::{Combine, Estimator};

#[derive(clap::Args, Debug)]
pub struct SubmitArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// Stage to step.
    #[arg(long, value_enum, default_value = "axis")]
    pub stage: StageKind,
    /// Distance between frames (µm; negative steps backwards). Needed with --steps N > 1.
    #[arg(long, value_name = "UM", allow_negative_numbers = true, value_parser = crate::cli::process::finite)]
    pub step_um: Option<f64>,
    /// Number of frames of one scan (give it with --step-um, or give --study instead).
    #[arg(long, value_name = "N", allow_negative_numbers = true)]
    pub steps: Option<u32>,
    /// Run these of the paper's cases instead of one scan (comma-separated: case1,case2,case3).
    #[arg(long, value_delimiter = ',', value_enum)]
    pub study: Vec<PaperCase>,
    /// Wait after each move before the frame is grabbed, ms (on top of the stage's own
    /// settle_ms).
    #[arg(long, value_name = "MS", default_value_t = 20)]
    pub settle_ms: u64,
    #[command(flatten)]
    pub processing: ProcessingArgs,
    #[command(flatten)]
    pub plan: Box<crate::cli::plan_args::PlanArgs>,
    /// How many times the scan (or each study case) is run; each repeat is processed on its
    /// own, and with 2 or more the result gives each target's spread.
    #[arg(
        long,
        value_name = "N",
        default_value_t = 1,
        allow_negative_numbers = true
    )]
    pub repeats: u32,
    /// Absolute start position (µm); default: the rig's.
    #[arg(long, value_name = "UM", allow_negative_numbers = true, value_parser = crate::cli::process::finite)]
    pub start_um: Option<f64>,
    /// Shift of each repeat's start (µm), for different sub-pixel phases.
    #[arg(
        long,
        value_name = "UM",
        default_value_t = 0.0,
        allow_negative_numbers = true,
        value_parser = crate::cli::process::finite
    )]
    pub repeat_shift_um: f64,
    /// Capture and record only.
    #[arg(long)]
    pub no_process: bool,
    /// A free-text label kept with the job and its session (shown by `list`).
    #[arg(long, value_name = "TEXT")]
    pub label: Option<String>,
    /// Return once queued instead of following the job.
    #[arg(long)]
    pub detach: bool,
}

/// The processing flags `submit` and `replay` share. Each left out is left to the daemon: for
/// a job the rig's `[pipeline]` default, else the protocol's; for a replay the recorded value.
#[derive(clap::Args, Debug)]
pub struct ProcessingArgs {
    #[arg(long, value_parser = crate::cli::process::parse_k, help = k_help())]
    pub k: Option<u32>,
    /// Default: the rig's ([pipeline] estimator), else fit.
    #[arg(long, value_enum)]
    pub estimator: Option<Estimator>,
    /// Default: the rig's ([pipeline] combine), else interp if k > 1, else mean.
    #[arg(long, value_enum)]
    pub combine: Option<Combine>,
    /// Where frame displacements come from: the image, the commanded positions or the
    /// interferometer's readings. Default: the rig's ([pipeline] registration), else image.
    #[arg(long, value_enum)]
    pub registration: Option<JobRegistration>,
    /// Also reconstruct the whole frame (default: the rig's [pipeline] whole_frame).
    #[arg(long)]
    pub whole_frame: bool,
}

fn k_help() -> String {
    let r = crate::pipeline::K_RANGE;
    format!(
        "Upsampling factor of the reconstruction, {}..={} (a study's cases keep their own)",
        r.start(),
        r.end()
    )
}

impl ProcessingArgs {
    pub fn processing(&self) -> Processing {
        Processing {
            k: self.k,
            estimator: self.estimator,
            combine: self.combine,
            registration: self.registration,
            whole_frame: self.whole_frame.then_some(true),
        }
    }
}

/// Which calibration converted the offsets (u includes its uncertainty), or why none did.
pub fn calibration_line(n: &crate::calibration_note::CalibrationNote) -> String {
    let id = n.id.as_deref().unwrap_or("?");
    let mut line = match (n.applied, &n.reason) {
        (true, _) => format!("calibration: {id} applied (u includes its field model's)"),
        (false, Some(why)) => {
            format!("calibration: none applied ({why}): offsets at the global scale")
        }
        (false, None) => "calibration: none applied: offsets at the global scale".into(),
    };
    for w in &n.warnings {
        line.push_str(&format!("\nwarning: {w}"));
    }
    line
}

impl SubmitArgs {
    pub fn spec(&self) -> JobSpec {
        let p = self.processing.processing();
        JobSpec {
            stage: self.stage,
            step_um: self.step_um,
            steps: self.steps,
            k: p.k,
            study: (!self.study.is_empty()).then(|| self.study.clone()),
            settle_ms: self.settle_ms,
            estimator: p.estimator,
            combine: p.combine,
            registration: p.registration,
            whole_frame: p.whole_frame,
            repeats: self.repeats,
            plan: self.plan.plan(),
            interval_s: self.plan.interval_s,
            start_um: self.start_um,
            repeat_shift_um: self.repeat_shift_um,
            process: !self.no_process,
            label: self.label.clone(),
            calibrate: None,
        }
    }
}

/// Submit `req` (a submit, a replay or a resume_session) and follow it unless `detach`.
pub fn submit_and_follow(socket: &SocketArg, req: Request, detach: bool) -> anyhow::Result<u64> {
    let mut c = socket.connect()?;
    if !detach {
        // Subscribe first so no event of the new job can be missed.
        c.request(&Request::Subscribe { job_id: None })?;
    }
    let r = c.request(&req)?;
    let id = r["job_id"].as_u64().unwrap_or_default();
    let total = r["total_frames"].as_u64().unwrap_or_default() as u32;
    // A resumed session's job: the plan's frames before its first are the original's.
    let before = r["resumed_from"]["first_index"].as_u64().unwrap_or(0) as u32;
    let ahead = r["queue_position"].as_u64().unwrap_or_default();
    // Ctrl-C is taken over before "queued" is printed: one that follows the line never
    // meets the default disposition, which would end rigctl in silence.
    let ctrl_c = (!detach).then(|| crate::cli::interrupt::watch(socket.path(), id));
    match before {
        0 => eprintln!("job {id} queued ({total} frames, {ahead} ahead)"),
        _ => eprintln!(
            "job {id} queued ({} frames: frames {before}..{} of the plan's {total}, {ahead} ahead)",
            total.saturating_sub(before),
            total.saturating_sub(1)
        ),
    }
    for w in r["warnings"].as_array().into_iter().flatten() {
        eprintln!("warning: {}", w.as_str().unwrap_or_default());
    }
    if detach {
        println!("{id}");
        return Ok(id);
    }
    if before > 0 {
        eprintln!(
            "resuming session {} from frame {before}",
            r["resumed_from"]["session"].as_str().unwrap_or("?")
        );
    }
    let pace = crate::cli::client::Pace::default().taken_before(before);
    let end = crate::cli::client::follow_from(&mut c, id, total, false, pace, before)?;
    drop(ctrl_c);
    report_end(id, &end)?;
    print_results(&mut c, id)?;
    Ok(id)
}

/// A finished job's measurements as a table, and its session's absolute path.
pub fn print_results(c: &mut Client, id: u64) -> anyhow::Result<()> {
    let r = c.request(&Request::Result { job_id: id })?;
    let hello = c.request(&Request::Hello {})?;
    let data_root = std::path::PathBuf::from(hello["data_root"].as_str().unwrap_or_default());
    let session = r["session"].as_str().unwrap_or_default();
    let result: Option<JobResult> = match r["result"].is_null() {
        true => None,
        false => Some(serde_json::from_value(r["result"].clone())?),
    };
    match result.as_ref().map(results_table) {
        Some(t) if !t.is_empty() => print!("{}", t.render()),
        _ => println!("(no measurements: the job was not processed)"),
    }
    if let Some(note) = result.as_ref().and_then(|r| r.calibration.as_ref()) {
        println!("{}", calibration_line(note));
    }
    println!("session: {}", data_root.join(session).display());
    Ok(())
}

impl SubmitArgs {
    /// What the command line lacks for a job, named by its flags (before the daemon would
    /// name the job's fields).
    pub fn check(&self) -> anyhow::Result<()> {
        if !self.study.is_empty() || self.plan.plan().is_some() {
            return Ok(());
        }
        match (self.steps, self.step_um) {
            (None, _) => anyhow::bail!(
                "say what to capture: --steps N --step-um UM (one scan of N frames), \
                 --study case1,case2,case3 (the paper's cases), or a plan (--line, \
                 --grid-inner/--grid-outer, --plan FILE.json)"
            ),
            (Some(n), None) if n > 1 => {
                anyhow::bail!("--steps {n} needs --step-um UM (the distance between frames)")
            }
            _ => Ok(()),
        }
    }
}

pub fn run(a: SubmitArgs) -> anyhow::Result<()> {
    a.check()?;
    let req = Request::Submit { job: a.spec() };
    submit_and_follow(&a.socket, req, a.detach).map(|_| ())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        submit: SubmitArgs,
    }

    fn parse(args: &[&str]) -> Result<SubmitArgs, clap::Error> {
        let argv = ["rigctl"].iter().chain(args).copied();
        Cli::try_parse_from(argv).map(|c| c.submit)
    }

    #[test]
    fn negative_numbers_need_no_equals_sign() {
        let a = parse(&["--step-um", "-50", "--steps", "3", "--start-um", "-200"]).unwrap();
        assert_eq!((a.step_um, a.start_um), (Some(-50.0), Some(-200.0)));
        let a = parse(&[
            "--steps",
            "2",
            "--step-um",
            "5",
            "--repeat-shift-um",
            "-1.5",
        ])
        .unwrap();
        assert_eq!(a.repeat_shift_um, -1.5);
    }

    #[test]
    fn a_bare_submit_names_the_flags_it_needs() {
        let e = parse(&[]).unwrap().check().unwrap_err().to_string();
        assert!(
            e.contains("--steps N --step-um UM") && e.contains("--study"),
            "{e}"
        );
        assert!(!e.contains("`step_um`"), "{e}");
        assert!(!e.contains("  "), "{e}");
        let e = parse(&["--steps", "4"]).unwrap().check().unwrap_err();
        assert_eq!(
            e.to_string(),
            "--steps 4 needs --step-um UM (the distance between frames)"
        );
        parse(&["--steps", "1"]).unwrap().check().unwrap();
        parse(&["--study", "case1"]).unwrap().check().unwrap();
    }

    fn spec(args: &[&str]) -> JobSpec {
        let argv = ["rigctl"].iter().chain(args).copied();
        Cli::try_parse_from(argv).unwrap().submit.spec()
    }

    #[test]
    fn processing_left_out_is_left_to_the_rig_and_given_flags_are_sent() {
        let s = spec(&["--steps", "3", "--step-um", "50"]);
        assert_eq!(
            (s.k, s.estimator, s.combine, s.registration, s.whole_frame),
            (None, None, None, None, None)
        );
        let s = spec(&[
            "--steps",
            "3",
            "--step-um",
            "50",
            "--estimator",
            "paper",
            "--registration",
            "interferometer",
            "--whole-frame",
        ]);
        assert_eq!(
            (s.estimator, s.registration, s.whole_frame),
            (
                Some(Estimator::Paper),
                Some(JobRegistration::Interferometer),
                Some(true)
            )
        );
    }
}
