//! The job's frames into the live view: a step sink in front of the recorder that hands
//! each record to the live view's slot (a pointer swapped under a lock; the pixels are
//! shared, not copied) when someone watches, then passes it on. Nothing here waits for
//! the live view's work.

use super::wire::StagePositions;
use super::{FrameImage, LiveFrame, LiveView};
use crate::acquisition::record::StepRecord;
use crate::acquisition::sink::{SinkError, StepSink};
use crate::acquisition::StageKind;
use crate::hw::{Frame, HwError};
use std::sync::Arc;

pub struct Tap<S: StepSink> {
    shared: Arc<Shared>,
    job_id: u64,
    stage: StageKind,
    pub inner: S,
}

/// What the tap needs of the daemon: its live view.
type Shared = crate::daemon::Shared;

impl<S: StepSink> Tap<S> {
    pub fn new(shared: Arc<Shared>, job_id: u64, stage: StageKind, inner: S) -> Tap<S> {
        Tap {
            shared,
            job_id,
            stage,
            inner,
        }
    }

    fn live(&self) -> &LiveView {
        &self.shared.live
    }
}

impl<S: StepSink> StepSink for Tap<S> {
    fn step(&mut self, rec: Arc<StepRecord>) -> Result<(), SinkError> {
        if self.live().watched() {
            let mut stage_um = StagePositions::default();
            match self.stage {
                StageKind::Axis => stage_um.axis_um = Some(rec.axis_um),
                StageKind::Piezo => stage_um.piezo_um = Some(rec.axis_um),
            }
            self.live().offer(LiveFrame {
                job_id: Some(self.job_id),
                image: FrameImage::Step(rec.clone()),
                stage_um,
            });
        }
        self.inner.step(rec)
    }
    fn end_run(&mut self, run: u32) -> Result<(), SinkError> {
        self.inner.end_run(run)
    }
    fn finish(&mut self) -> Result<(), SinkError> {
        self.inner.finish()
    }
    /// A paused job's camera serves the live view as the idle worker does, at the rate
    /// its watchers ask.
    fn wants_paused_frame(&self) -> bool {
        self.live().grab_due()
    }
    fn paused_frame(&mut self, frame: Result<Frame, HwError>, at_um: Option<f64>) {
        let mut stage_um = StagePositions::default();
        match self.stage {
            StageKind::Axis => stage_um.axis_um = at_um,
            StageKind::Piezo => stage_um.piezo_um = at_um,
        }
        let frame = frame.map(|f| LiveFrame {
            job_id: Some(self.job_id),
            image: FrameImage::Own(f),
            stage_um,
        });
        self.live().grabbed(frame);
    }
}
