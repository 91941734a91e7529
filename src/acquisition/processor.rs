//! The processing sink: one pipeline per run, fed as frames arrive, each run's result when
//! its last frame is in. Runs behind the capture (on its own thread, see `sink::Threaded`).

use crate::acquisition::plan::RunPlan;
use crate::acquisition::record::{ms, StepRecord};
use crate::acquisition::sink::{SinkError, StepSink};
use crate::acquisition::study::RunResult;
use crate::board::Board;
use crate::pipeline::run::Finished;
use crate::pipeline::Pipeline;
use std::sync::Arc;
use std::time::Instant;

/// A reconstruction as the pipeline makes it: 16-bit grey.
pub type Image16 = image::ImageBuffer<image::Luma<u16>, Vec<u16>>;

/// What processing tells the world as it goes.
#[derive(Debug, Clone)]
pub enum ProcessorEvent {
    /// A frame was processed.
    Frame {
        index: u32,
        process_ms: f64,
        targets_found: usize,
    },
    /// A run has its measurement (or the reason it has none).
    Run(Box<RunResult>),
}

pub type Emit = Box<dyn Fn(ProcessorEvent) + Send>;

/// A frame an earlier session took of this plan (a resumed job's original): processed with
/// this job's frames of its run, as if this job had taken it.
#[derive(Debug, Clone, PartialEq)]
pub struct PriorFrame {
    pub index: u32,
    pub run: u32,
    /// The position it registers by (`StepRecord::registration_um`); `None`: the job
    /// registers by the interferometer and the frame has no reading.
    pub registration_um: Option<f64>,
    pub piezo_commanded_um: Option<f64>,
}

/// Reads a prior frame's image by its plan index (from the session that holds it).
pub type LoadFrame = Box<dyn Fn(u32) -> Result<image::RgbImage, String> + Send>;

/// The frames before a resumed plan's first one, in plan order, and how to read them.
pub struct Prior {
    pub frames: Vec<PriorFrame>,
    pub load: LoadFrame,
}

pub struct Processor {
    runs: Vec<RunPlan>,
    board: Option<Board>,
    emit: Emit,
    /// The run being fed, and its pipeline or why it has none.
    current: Option<(u32, Result<Pipeline, String>)>,
    pub results: Vec<RunResult>,
    /// Reconstructions, named `run-NNN-<name>`.
    pub images: Vec<(String, Image16)>,
    /// A resumed job's earlier frames: a run's are pushed before this job's frames of it.
    prior: Option<Prior>,
    /// The calibration every run's pipeline converts its offsets with.
    calibration: Option<crate::calibration_file::Applied>,
}

impl Processor {
    pub fn new(runs: Vec<RunPlan>, board: Option<Board>, emit: Emit) -> Processor {
        Processor {
            runs,
            board,
            emit,
            current: None,
            results: Vec::new(),
            images: Vec::new(),
            prior: None,
            calibration: None,
        }
    }

    /// Convert every run's offsets with `calibration` (none: the global scale).
    pub fn with_calibration(
        mut self,
        calibration: Option<crate::calibration_file::Applied>,
    ) -> Processor {
        self.calibration = calibration;
        self
    }

    /// Process the frames of `prior` too: a run's before this job's frames of it; the runs
    /// it holds whole at `finish`.
    pub fn with_prior(mut self, prior: Prior) -> Processor {
        self.prior = Some(prior);
        self
    }

    /// A new pipeline for `run`, fed the prior frames of it first.
    fn start_run(&self, run: u32) -> Result<Pipeline, String> {
        let mut p = self.pipeline_for(run)?;
        let Some(prior) = self.prior.as_ref() else {
            return Ok(p);
        };
        for f in prior.frames.iter().filter(|f| f.run == run) {
            let image = (prior.load)(f.index)?;
            let at = f.registration_um.ok_or_else(|| {
                format!("frame {}: no interferometer reading at its time", f.index)
            })?;
            p.push_at(&image, at, f.piezo_commanded_um)
                .map_err(|e| format!("frame {}: {e}", f.index))?;
        }
        Ok(p)
    }

    /// The runs the prior frames hold whole (every planned frame of them), in run order.
    fn prior_runs(&self) -> Vec<u32> {
        let Some(prior) = self.prior.as_ref() else {
            return Vec::new();
        };
        self.runs
            .iter()
            .filter(|r| {
                let n = prior.frames.iter().filter(|f| f.run == r.run).count();
                n > 0 && n == r.positions_um.len()
            })
            .map(|r| r.run)
            .collect()
    }

    fn pipeline_for(&self, run: u32) -> Result<Pipeline, String> {
        let plan = self
            .runs
            .get(run as usize)
            .ok_or_else(|| format!("run {run} is not in the plan"))?;
        let opts = plan
            .processing
            .clone()
            .ok_or_else(|| format!("run {run} has no processing options"))?;
        let mut p = Pipeline::new(opts, self.board.clone());
        if let Some(c) = &self.calibration {
            c.apply(&mut p);
        }
        Ok(p)
    }

    fn record(&mut self, run: u32, outcome: Result<Finished, String>) {
        let Some(plan) = self.runs.get(run as usize) else {
            return;
        };
        let (result, error) = match outcome {
            Ok(f) => {
                for im in f.images {
                    self.images
                        .push((format!("run-{run:03}-{}", im.name), im.image));
                }
                (Some(f.result), None)
            }
            Err(e) => (None, Some(e)),
        };
        let r = RunResult {
            run,
            case: plan.case.name.clone(),
            repeat: plan.repeat,
            frames: plan.case.frames,
            step_um: plan.case.step_um,
            k: plan.case.k,
            result,
            error,
        };
        (self.emit)(ProcessorEvent::Run(Box::new(r.clone())));
        self.results.push(r);
    }
}

impl StepSink for Processor {
    fn step(&mut self, rec: Arc<StepRecord>) -> Result<(), SinkError> {
        if self.current.as_ref().map(|c| c.0) != Some(rec.run) {
            self.current = Some((rec.run, self.start_run(rec.run)));
        }
        let Some((_, Ok(p))) = self.current.as_mut() else {
            return Ok(());
        };
        let t = Instant::now();
        // The piezo registers by its commanded position (closed loop, nanometres; the
        // interferometer reads the axis only).
        match p.push_at(
            &rec.frame.image,
            rec.registration_um,
            rec.piezo_commanded_um,
        ) {
            Ok(r) => (self.emit)(ProcessorEvent::Frame {
                index: rec.index,
                process_ms: ms(t.elapsed()),
                targets_found: r.targets_found,
            }),
            Err(e) => {
                let e = format!("frame {}: {e}", rec.index);
                self.current = Some((rec.run, Err(e)));
            }
        }
        Ok(())
    }

    fn end_run(&mut self, run: u32) -> Result<(), SinkError> {
        let outcome = match self.current.take() {
            Some((r, Ok(p))) if r == run => p.finish().map_err(|e| e.to_string()),
            Some((r, Err(e))) if r == run => Err(e),
            _ => Err("no frame reached processing".into()),
        };
        self.record(run, outcome);
        Ok(())
    }

    /// A resumed job's runs taken whole by the earlier session are processed from its
    /// frames now, behind the capture (the rig never waits for them); results in run order.
    fn finish(&mut self) -> Result<(), SinkError> {
        for run in self.prior_runs() {
            let outcome = self
                .start_run(run)
                .and_then(|p| p.finish().map_err(|e| e.to_string()));
            self.record(run, outcome);
        }
        self.results.sort_by_key(|r| r.run);
        Ok(())
    }
}
