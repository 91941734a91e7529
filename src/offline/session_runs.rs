//! A recorded session processed again, offline, as the daemon processed it: the runs of its
//! manifest's plan with each run's recorded processing options (or, with overrides, the
//! options a daemon replay with those overrides would use: `Plan::for_replay`), the board
//! and scale of its rig, every frame registered by what the job registered by (the image,
//! the commanded positions or the interferometer readings of `steps.csv`), each run's
//! frames through its own pipeline, and the study's summary over the runs. A multi-run
//! session gives one result per run, never one scan of all its frames.

use super::outputs::RunSettings;
use super::overrides::Overrides;
use super::push::{push_frames, FrameIn, PushError};
use crate::acquisition::plan::RunPlan;
use crate::acquisition::processor::Image16;
use crate::acquisition::study::{summarize, JobResult, RunResult};
use crate::acquisition::JobRegistration;
use crate::board::Board;
use crate::calibration_file::Applied;
use crate::folder::FrameFile;
use crate::pipeline::{Pipeline, ValidOptions};
use crate::session::{Session, StepRow};

/// Why a session cannot be processed at all (a run the pipeline refuses is not this: it is
/// recorded in the result with its error, as the daemon records it).
#[derive(Debug, thiserror::Error)]
pub enum SessionProcessError {
    #[error("{session}: {message}")]
    Setup { session: String, message: String },
    #[error(transparent)]
    Read(#[from] crate::folder::FolderError),
}

/// One run to process: its plan (the case cut to the frames held), options and frames.
#[derive(Debug, Clone)]
pub struct RunInput {
    pub plan: RunPlan,
    pub options: ValidOptions,
    pub frames: Vec<FrameIn>,
    /// Why the run cannot be processed (a frame without the interferometer reading its
    /// registration needs), as the daemon's run error says it.
    pub error: Option<String>,
}

/// A session's runs, ready to process; `limit` keeps the session's first N frames.
pub fn session_runs(
    s: &Session,
    ov: &Overrides,
    limit: Option<usize>,
) -> Result<Vec<RunInput>, SessionProcessError> {
    let setup = |message: String| SessionProcessError::Setup {
        session: s.dir.display().to_string(),
        message,
    };
    let held = limit.map_or(s.steps.len(), |n| n.min(s.steps.len()));
    if held == 0 {
        return Err(setup("the session holds no frame".into()));
    }
    let m = &s.manifest;
    let rig = ov.rig(&m.rig);
    let mut spec = m.job.with_defaults(&m.rig.job_defaults);
    spec = spec.overridden(&ov.processing());
    spec.process = true;
    let mut plan = m
        .plan
        .for_replay(held, &spec, &ov.processing(), &rig)
        .map_err(|e| setup(format!("processing options: {e}")))?;
    if ov.is_empty() {
        // Exactly what the daemon used, where the manifest records it.
        for (r, recorded) in plan.runs.iter_mut().zip(&m.plan.runs) {
            if let Some(p) = &recorded.processing {
                r.processing = Some(p.clone());
            }
        }
    }
    let registration = spec.registration.unwrap_or_default();
    let mut rows = s.steps[..held].iter().peekable();
    let mut runs = Vec::with_capacity(plan.runs.len());
    for r in plan.runs {
        let mut frames = Vec::new();
        let mut error = None;
        while let Some(row) = rows.next_if(|row| row.run == r.run) {
            match frame_in(s, row, registration) {
                Ok(f) => frames.push(f),
                Err(e) => {
                    error.get_or_insert(e);
                }
            }
        }
        if frames.len() != r.positions_um.len() && error.is_none() {
            error = Some(format!(
                "steps.csv has {} frames of run {}, its plan {}",
                frames.len(),
                r.run,
                r.positions_um.len()
            ));
        }
        let mut options = r
            .processing
            .clone()
            .expect("for_replay sets every run's options");
        if let Some(take) = ov.calibration_ink {
            options = options.with_calibration_ink(take);
        }
        runs.push(RunInput {
            plan: r,
            options,
            frames,
            error,
        });
    }
    Ok(runs)
}

/// A row's frame and the position it registers by: the commanded one, or with
/// `registration: interferometer` its reading (a frame without one fails its run, as it
/// fails a live job).
fn frame_in(s: &Session, row: &StepRow, reg: JobRegistration) -> Result<FrameIn, String> {
    let position_um = match (reg, row.interferometer_um) {
        (JobRegistration::Interferometer, Some(x)) => x,
        (JobRegistration::Interferometer, None) => {
            return Err(format!(
                "frame {}: no interferometer reading (registration: interferometer)",
                row.index
            ))
        }
        _ => row.commanded_registration_um(s.manifest.rig.axis_machine.as_ref()),
    };
    let (dir, rel) = s.frame_file(row.index).map_err(|e| e.to_string())?;
    Ok(FrameIn {
        file: FrameFile::Below { dir, rel },
        position_um,
        piezo_um: row.piezo_commanded_um,
    })
}

/// A processed session: the daemon's `result.json` document and the reconstructions,
/// named `run-NNN-<name>` as the daemon names them.
pub struct Processed {
    pub result: JobResult,
    pub images: Vec<(String, Image16)>,
    /// Each run's complete options as processed (`settings.json`).
    pub runs: Vec<RunSettings>,
}

/// Process every run of `s` (see [`session_runs`]); `board` overrides the rig's;
/// `calibration` converts every run's offsets;
/// `keep_images` converts the reconstructions to images; `decoders` PNG decoder threads per
/// run.
pub fn process_session(
    s: &Session,
    ov: &Overrides,
    board: Option<Board>,
    calibration: Option<&Applied>,
    limit: Option<usize>,
    keep_images: bool,
    decoders: usize,
) -> Result<Processed, SessionProcessError> {
    let runs = session_runs(s, ov, limit)?;
    if let Some(k) = ov.k {
        if runs
            .iter()
            .all(|r| r.options.combine == crate::pipeline::Combine::Mean)
        {
            return Err(SessionProcessError::Setup {
                session: s.dir.display().to_string(),
                message: format!(
                    "--k {k} changes nothing: its runs combine by `mean` (each frame \
                     measured, the estimates averaged; no reconstruction). Add \
                     --combine interp (or splat) to reconstruct at k = {k}"
                ),
            });
        }
    }
    let settings = runs
        .iter()
        .map(|r| RunSettings {
            run: r.plan.run,
            case: r.plan.case.name.clone(),
            repeat: r.plan.repeat,
            options: r.options.clone().into_inner(),
        })
        .collect();
    let board = board.or_else(|| s.manifest.rig.board.clone());
    let mut results = Vec::with_capacity(runs.len());
    let mut images = Vec::new();
    for input in runs {
        let (run, outcome) = process_run(input, board.clone(), calibration, keep_images, decoders)?;
        let (result, error) = match outcome {
            Ok(f) => {
                for im in f.images {
                    images.push((format!("run-{:03}-{}", run.run, im.name), im.image));
                }
                (Some(f.result), None)
            }
            Err(e) => (None, Some(e)),
        };
        results.push(RunResult {
            run: run.run,
            case: run.case.name.clone(),
            repeat: run.repeat,
            frames: run.case.frames,
            step_um: run.case.step_um,
            k: run.case.k,
            result,
            error,
        });
    }
    let names: Vec<&str> = board
        .iter()
        .flat_map(|b| b.targets.iter().map(|t| t.name.as_str()))
        .collect();
    let scale = ov.rig(&s.manifest.rig).scale_um_per_px;
    let study = (!results.is_empty()).then(|| summarize(&results, &names, scale));
    Ok(Processed {
        result: JobResult {
            runs: results,
            study,
            calibration: None,
            calibrated: None,
        },
        images,
        runs: settings,
    })
}

type RunOutcome = Result<crate::pipeline::run::Finished, String>;

/// One run through its pipeline. A frame the pipeline refuses, or a failing finish, is the
/// run's error (worded as the daemon's processor words it); a frame that cannot be read is
/// the session's.
fn process_run(
    input: RunInput,
    board: Option<Board>,
    calibration: Option<&Applied>,
    keep_images: bool,
    decoders: usize,
) -> Result<(RunPlan, RunOutcome), SessionProcessError> {
    if let Some(e) = input.error {
        return Ok((input.plan, Err(e)));
    }
    let mut pipeline = Pipeline::new(input.options, board);
    pipeline.keep_images(keep_images);
    if let Some(c) = calibration {
        c.apply(&mut pipeline);
    }
    let outcome = match push_frames(&mut pipeline, &input.frames, decoders) {
        Ok(()) => pipeline.finish().map_err(|e| e.to_string()),
        Err(PushError::Pipeline { nth, file, source }) => {
            let index = frame_index(&file).unwrap_or(nth as u32);
            Err(format!("frame {index}: {source}"))
        }
        Err(PushError::Read(e)) => return Err(e.into()),
        Err(PushError::Decoder) => {
            return Err(SessionProcessError::Setup {
                session: String::new(),
                message: "a frame decoder stopped".into(),
            })
        }
    };
    Ok((input.plan, outcome))
}

/// The job's frame index from a session frame's file name (`000012.png` -> 12).
fn frame_index(file: &FrameFile) -> Option<u32> {
    file.path().file_stem()?.to_str()?.parse().ok()
}

/// The calibration the daemon applied to the session's job, read where the daemon read it
/// (or from the data root the session sits in, if it moved); none if it applied none. A
/// record that cannot be read is an error naming it and the ways on.
pub fn recorded_calibration(s: &Session) -> anyhow::Result<Option<Applied>> {
    use std::path::PathBuf;
    let Some(note) = s.manifest.calibration.as_ref().filter(|n| n.applied) else {
        return Ok(None);
    };
    let id = note.id.as_deref().unwrap_or_default();
    let beside = crate::bounds::one_component("calibration id", id)
        .ok()
        .and_then(|id| {
            Some(
                s.dir
                    .parent()?
                    .join(crate::calibration_store::DIR)
                    .join(format!("{id}.json")),
            )
        });
    let places: Vec<PathBuf> = note
        .source
        .iter()
        .map(PathBuf::from)
        .chain(beside)
        .collect();
    let mut why = Vec::new();
    for p in &places {
        match Applied::load(p) {
            Ok(a) if a.calibration.id == id => {
                eprintln!(
                    "calibration {id} applied, as the daemon did ({})",
                    p.display()
                );
                return Ok(Some(a));
            }
            Ok(a) => why.push(format!(
                "{} holds calibration {}",
                p.display(),
                a.calibration.id
            )),
            Err(e) => why.push(crate::text::error_chain(e.chain())),
        }
    }
    anyhow::bail!(
        "{}: its job applied calibration {id:?}, which cannot be read here ({}): give it with \
         --calibration FILE, or --no-calibration for the global scale",
        s.dir.display(),
        if why.is_empty() {
            "no record file named".into()
        } else {
            why.join("; ")
        }
    )
}
