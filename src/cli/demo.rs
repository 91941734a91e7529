//! `rigctl demo`: the paper's study on the simulated rig, through the daemon's socket.
//!
//! Starts a simulated rig (the sim's `webcam` camera unless `--camera`) and a daemon
//! in-process on a temporary socket, runs the daemon's calibration job (40 x 500 µm; not
//! with `--no-calibrate`), then submits the study (20 repeats of case 1: one raw frame;
//! case 2: 10 frames at 100 µm, k = 5; case 3: 20 frames at 50 µm, k = 10; each repeat from
//! a different sub-pixel start), which applies the calibration; prints Tables 1-3, the
//! calibrated and global-scale figures beside the paper's, and writes the session, the
//! report and its figures (`rigctl report`'s). The frames (~1 GB) and reconstructions are
//! removed afterwards unless `--keep`: a demo user wants the tables, not the pixels.

use crate::acquisition::study::{calibration_table, tables, StudySummary};
use crate::acquisition::{JobSpec, PaperCase};
use crate::calibration_note::Calibrated;
use crate::cli::client::{follow, report_end, Client, Ended};
use crate::config::DaemonSettings;
use crate::daemon::protocol::Request;
use crate::daemon::server;
use crate::ownership::Ownership;
use crate::rig::{simulated, SimSettings};
use anyhow::Context;
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct DemoArgs {
    /// Socket of the demo's daemon (default: a temporary one). Refused when a daemon
    /// already serves there: the demo only ever submits to the daemon it starts.
    #[arg(long, value_name = "PATH")]
    pub socket: Option<PathBuf>,
    /// Where the session and the report are written.
    #[arg(long, value_name = "DIR", default_value = "rigd-demo")]
    pub data_root: PathBuf,
    /// Keep the whole session (its ~1 GB of frames and the reconstructions, replayable);
    /// without it only the report, result.json, manifest and steps.csv are kept.
    #[arg(long)]
    pub keep: bool,
    /// Repeats of each case (the paper: 20).
    #[arg(long, value_name = "N", default_value_t = 20)]
    pub repeats: u32,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
    /// The sim's camera profile: ideal (clean, matched), webcam (tilt, distortion, Bayer,
    /// MJPEG: docs/sim.md) or stress.
    #[arg(long, value_name = "PROFILE", default_value = "webcam",
          value_parser = ["ideal", "webcam", "stress"])]
    pub camera: String,
    /// Skip the calibration job: the study's offsets use the global scale only.
    #[arg(long)]
    pub no_calibrate: bool,
    /// Print the calibration's whole summary (the field model's parameters, every
    /// target's scale), not only its verdict.
    #[arg(long)]
    pub verbose: bool,
}

/// The demo's sim: the camera of `profile` on a fast frame clock.
pub fn sim_settings(profile: &str) -> anyhow::Result<SimSettings> {
    Ok(SimSettings::for_camera(profile)?)
}

/// The paper's study as a job: each repeat starts 1/repeats of a pixel further.
pub fn paper_study(repeats: u32, scale_um_per_px: f64) -> JobSpec {
    JobSpec {
        study: Some(PaperCase::ALL.to_vec()),
        repeats,
        repeat_shift_um: scale_um_per_px / repeats.max(1) as f64,
        settle_ms: 0,
        label: Some("paper study (demo)".into()),
        ..JobSpec::default()
    }
}

pub fn run(mut a: DemoArgs) -> anyhow::Result<()> {
    let t0 = Instant::now();
    a.data_root = std::path::absolute(&a.data_root)
        .with_context(|| format!("data root {}", a.data_root.display()))?;
    let own_socket = a.socket.is_none();
    let socket = a.socket.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("rigd-demo-{}.sock", std::process::id()))
    });
    // The demo's own socket is this process's alone: its lock file goes with it, whatever
    // the outcome (declared before the daemon, so dropped after it has stopped).
    let _lock_file = own_socket.then(|| RemovedOnDrop(crate::ownership::socket_lock_path(&socket)));
    let settings = DaemonSettings {
        socket: socket.clone(),
        group: None,
        data_root: a.data_root.clone(),
        ..DaemonSettings::default()
    };
    // Claimed before anything starts: when a daemon serves at --socket (or holds the data
    // root) the demo stops here, and never submits the study to a rig it did not start.
    let owner = Ownership::claim(&settings, &[], "rigctl demo")
        .context("rigctl demo starts its own daemon")?;
    let sim = sim_settings(&a.camera)?;
    let scale = sim.camera.scale_um_per_px;
    let mut daemon = server::Background::start_owned(owner, simulated(&sim)?)?;
    let mut c = Client::connect(&socket)?;
    c.request(&Request::Subscribe { job_id: None })?;
    let calibrated = match a.no_calibrate {
        true => None,
        false => Some(calibrate(&mut c, &a)?),
    };
    let (id, end) = run_study(&mut c, &a, scale)?;
    let fetched = c.request(&Request::Result { job_id: id });
    drop(c);
    daemon.stop()?;
    report_end(id, &end)?;
    let fetched = fetched?;
    let session = fetched["session"].as_str().unwrap_or_default().to_string();
    let study: StudySummary = serde_json::from_value(fetched["result"]["study"].clone())
        .context("the study's result has no summary")?;
    let failed: usize = study.cases.iter().map(|c| c.runs_failed).sum();
    let runtime_s = t0.elapsed().as_secs_f64();
    let report = serde_json::json!({
        "session": session,
        "session_dir": a.data_root.join(&session),
        "repeats": a.repeats,
        "runtime_s": runtime_s,
        "runs_failed": failed,
        "cases": study.cases,
        "stats": study.stats,
        "paper_rms_std_um": { "case1": 281.5, "case2": 96.6, "case3": 69.9 },
        "camera": a.camera,
        "calibrated": calibrated,
        "calibration": fetched["result"]["calibration"],
    });
    let dir = a.data_root.join(&session);
    let mut text = tables(&study);
    text.push_str(&calibration_table(&study));
    std::fs::write(dir.join("report.json"), serde_json::to_vec_pretty(&report)?)?;
    // report.txt and the figures (Figures 4 and 5, the per-step residuals), as `rigctl report`.
    let figures = crate::cli::report::write(&dir, &dir)?;
    if !a.keep {
        drop_bulk(&dir)?;
        if let Some(made) = &calibrated {
            drop_bulk(&a.data_root.join(&made.session))?;
        }
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!("{text}");
        println!(
            "The paper: 281.5 µm (case 1), 96.6 µm (case 2), 69.9 µm (case 3).\nReport: {} ({runtime_s:.1} s); {} figures beside it",
            dir.join("report.txt").display(),
            figures.len().saturating_sub(1) / 2
        );
        where_it_is(a.keep, &dir, failed);
    }
    Ok(())
}

/// The paper's study submitted to the demo's daemon and followed to its end.
fn run_study(c: &mut Client, a: &DemoArgs, scale: f64) -> anyhow::Result<(u64, Ended)> {
    let r = c.request(&Request::Submit {
        job: paper_study(a.repeats, scale),
    })?;
    let id = r["job_id"].as_u64().unwrap_or_default();
    let total = r["total_frames"].as_u64().unwrap_or_default() as u32;
    if !a.json {
        eprintln!(
            "rigctl demo: the paper's study on the simulated rig: {} repeats x 3 cases = {total} frames",
            a.repeats
        );
    }
    Ok((id, follow(c, id, total, a.json)?))
}

/// Where the session is, what was kept of it, and the runs that failed.
fn where_it_is(keep: bool, dir: &std::path::Path, failed: usize) {
    {
        match keep {
            true => println!(
                "Session kept whole (frames and reconstructions): {}",
                dir.display()
            ),
            false => println!(
                "Frames and reconstructions removed (--keep keeps them); report, result.json, \
                 manifest and steps.csv are in {}",
                dir.display()
            ),
        }
        if failed > 0 {
            println!("{failed} runs could not be processed (see result.json)");
        }
    }
}

/// The daemon's calibration job on the demo's rig, followed to its end; its record.
fn calibrate(c: &mut Client, a: &DemoArgs) -> anyhow::Result<Calibrated> {
    let job = JobSpec {
        calibrate: Some(Box::default()),
        settle_ms: 0,
        label: Some("calibration (demo)".into()),
        ..JobSpec::default()
    };
    let r = c.request(&Request::Submit { job })?;
    let id = r["job_id"].as_u64().unwrap_or_default();
    let total = r["total_frames"].as_u64().unwrap_or_default() as u32;
    if !a.json {
        eprintln!(
            "rigctl demo: calibrating the {} camera first: {total} frames of 500 µm",
            a.camera
        );
    }
    let end = follow(c, id, total, a.json)?;
    report_end(id, &end)?;
    let fetched = c.request(&Request::Result { job_id: id })?;
    let made: Calibrated = serde_json::from_value(fetched["result"]["calibrated"].clone())
        .context("the calibration job's result names no calibration")?;
    if !a.json {
        match a.verbose {
            true => println!("{}", made.summary),
            false => println!("{}", verdict(&made)),
        }
    }
    Ok(made)
}

/// The calibration in two lines: its residual against the scan, and where the record is.
fn verdict(c: &Calibrated) -> String {
    format!(
        "calibration {}: {} targets, {} frames at {} µm; the field model fits the scan to {:.1} µm \
         RMS ({:.1} µm at most)\n  record: {} (`--verbose` prints its parameters)\n",
        c.id, c.targets, c.frames, c.step_um, c.residual_rms_um, c.residual_max_um, c.path
    )
}

/// The session's bulk: its frames and reconstructions (about 1 GB for the paper's study).
/// The rest (manifest, steps.csv, result.json, the report) stays.
fn drop_bulk(dir: &std::path::Path) -> anyhow::Result<()> {
    for sub in ["frames", "images"] {
        let p = dir.join(sub);
        if p.is_dir() {
            std::fs::remove_dir_all(&p).with_context(|| format!("removing {}", p.display()))?;
        }
    }
    Ok(())
}

/// A file removed when this is dropped.
struct RemovedOnDrop(std::path::PathBuf);

impl Drop for RemovedOnDrop {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}
