//! `rigctl calibrate`: fit a calibration (each target's local scale, the field model) from
//! a scan of known displacements (docs/calibration.md). With a DIR, offline from a folder
//! scan; without one, the daemon's calibration job on its rig (the scan, the same fit, the
//! record kept in its data root as the current calibration).

use crate::acquisition::calibration_job::{CalibrationScan, ScanReference};
use crate::acquisition::JobRegistration;
use crate::board::Board;
use crate::calibration::{Calibration, Reference};
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
        print!("{}", summary(&cal));
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
    let made: crate::daemon::calibration::Calibrated = serde_json::from_value(made.clone())
        .context("the calibration job's result names no calibration")?;
    print!("{}", made.summary);
    println!(
        "written to {} (the daemon's current calibration)",
        made.path
    );
    Ok(())
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
    s += &ink_line(cal);
    s += &ink_margin_line(cal);
    s += &lateral_line(cal);
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
