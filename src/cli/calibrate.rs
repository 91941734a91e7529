//! `rigctl calibrate`: fit a calibration (each target's local scale, the field model) from
//! a scan of known displacements (docs/calibration.md). With a DIR, offline from a folder
//! scan; without one, the daemon's calibration job on its rig (the scan, the same fit, the
//! record kept in its data root as the current calibration).

use crate::acquisition::calibration_job::{CalibrationScan, ScanReference};
use crate::acquisition::JobRegistration;
use crate::board::Board;
use crate::calibration::Reference;
use crate::cli::client::{follow, report_end, SocketArg};
use crate::daemon::protocol::Request;
use crate::offline::calibrate::{fit_folder, FolderFit};
use anyhow::Context;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct CalibrateArgs {
    /// A folder of frames/*.png and steps.csv: a scan of known displacements (e.g. 40
    /// steps of 500 µm). Left out: the daemon scans its rig (a calibration job).
    pub dir: Option<PathBuf>,
    /// The global scale the runs it will convert are processed with, µm per px (with DIR;
    /// the daemon uses its rig's).
    #[arg(long, value_name = "UM")]
    pub scale_um_per_px: Option<f64>,
    /// Where to write the calibration record (JSON; with DIR: the daemon keeps its own in
    /// <data root>/calibrations/).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Board file: its layout fixes the field's shape and names the targets (with DIR).
    #[arg(long)]
    pub board: Option<PathBuf>,
    /// The length reference: steps.csv's position_um (commanded) or interferometer_um.
    #[arg(long, value_enum, default_value = "commanded")]
    pub registration: JobRegistration,
    /// Image displacement per unit of axis travel, "x,y" (a starting guess; with DIR).
    #[arg(long, value_parser = super::process::parse_dir, allow_hyphen_values = true,
          value_name = "X,Y", default_value = "-1,0")]
    pub axis_dir: [f64; 2],
    /// Relative standard uncertainty of the reference's scale [commanded 1e-4,
    /// interferometer 1e-6].
    #[arg(long, value_name = "REL")]
    pub reference_rel_u: Option<f64>,
    /// The camera's output curve (DIR): the scan is measured in linear light.
    #[arg(long, value_enum, default_value = "linear")]
    pub response: crate::pipeline::Response,
    /// The daemon's scan (without DIR): frames.
    #[arg(long, value_name = "N", default_value_t = crate::acquisition::calibration_job::DEFAULT_STEPS)]
    pub steps: u32,
    /// The daemon's scan (without DIR): distance between frames, µm.
    #[arg(long, value_name = "UM", allow_negative_numbers = true,
          default_value_t = crate::acquisition::calibration_job::DEFAULT_STEP_UM)]
    pub step_um: f64,
    /// The daemon's scan (without DIR): absolute start, µm (default: the rig's).
    #[arg(long, value_name = "UM", allow_negative_numbers = true)]
    pub start_um: Option<f64>,
    #[command(flatten)]
    pub socket: SocketArg,
    /// Print the calibration record (with DIR) or the job's result (without) on stdout.
    #[arg(long)]
    pub json: bool,
}

fn reference(r: JobRegistration) -> anyhow::Result<Reference> {
    match r {
        JobRegistration::Interferometer => Ok(Reference::Interferometer),
        JobRegistration::Commanded => Ok(Reference::Commanded),
        JobRegistration::Image => anyhow::bail!(
            "--registration image: a calibration needs known displacements (commanded or interferometer)"
        ),
    }
}

pub fn run(args: CalibrateArgs) -> anyhow::Result<()> {
    let reference = reference(args.registration)?;
    match args.dir.clone() {
        Some(dir) => offline(&args, dir, reference),
        None => on_the_rig(&args, reference),
    }
}

/// `rigctl calibrate DIR`: the folder's scan fitted here, the record written to --out.
fn offline(args: &CalibrateArgs, dir: PathBuf, reference: Reference) -> anyhow::Result<()> {
    let (Some(scale_um_per_px), Some(out)) = (args.scale_um_per_px, args.out.as_ref()) else {
        anyhow::bail!("rigctl calibrate DIR needs --scale-um-per-px UM and --out FILE");
    };
    let fit = FolderFit {
        scale_um_per_px,
        board: args.board.as_deref().map(Board::load).transpose()?,
        reference,
        axis_dir: args.axis_dir,
        reference_rel_u: args.reference_rel_u,
        rig: None,
        response: args.response,
    };
    let cal = fit_folder(&dir, &fit)?;
    crate::calibration_file::save(out, &cal)?;
    if args.json {
        println!("{}", serde_json::to_string(&cal)?);
    } else {
        print!("{}", crate::calibration_note::summary(&cal));
        println!("written to {}", out.display());
    }
    Ok(())
}

/// `rigctl calibrate` without DIR: the daemon's calibration job, followed; its summary.
fn on_the_rig(args: &CalibrateArgs, reference: Reference) -> anyhow::Result<()> {
    if args.scale_um_per_px.is_some() || args.out.is_some() || args.board.is_some() {
        anyhow::bail!(
            "--scale-um-per-px, --out and --board go with DIR: the daemon calibrates with its \
             rig's scale and board and keeps the record in its data root"
        );
    }
    let job = crate::acquisition::JobSpec {
        calibrate: Some(Box::new(CalibrationScan {
            steps: args.steps,
            step_um: args.step_um,
            registration: match reference {
                Reference::Commanded => ScanReference::Commanded,
                Reference::Interferometer => ScanReference::Interferometer,
            },
            reference_rel_u: args.reference_rel_u,
        })),
        start_um: args.start_um,
        settle_ms: 0,
        label: Some("calibration".into()),
        ..Default::default()
    };
    let mut c = args.socket.connect()?;
    c.request(&Request::Subscribe { job_id: None })?;
    let r = c.request(&Request::Submit { job })?;
    let id = r["job_id"].as_u64().unwrap_or_default();
    let total = r["total_frames"].as_u64().unwrap_or_default() as u32;
    eprintln!(
        "calibration job {id}: {total} frames of {} µm",
        args.step_um
    );
    let end = follow(&mut c, id, total, args.json)?;
    report_end(id, &end)?;
    let fetched = c.request(&Request::Result { job_id: id })?;
    let made = &fetched["result"]["calibrated"];
    if args.json {
        println!("{}", serde_json::to_string(&fetched["result"])?);
        return Ok(());
    }
    let made: crate::calibration_note::Calibrated = serde_json::from_value(made.clone())
        .context("the calibration job's result names no calibration")?;
    print!("{}", made.summary);
    println!(
        "written to {} (the daemon's current calibration)",
        made.path
    );
    Ok(())
}
