//! The interferometer as a step sink adapter: reads the position log at each frame's
//! exposure time, fills in the record's reading and the samples it was interpolated from,
//! and hands it on.
//!
//! It runs on the engine's thread, right after the grab. Reading it later, from a sink
//! thread, was tried: the log's clock offset is estimated from how fresh each burst of the
//! file is when it is read, and a reader that is busy elsewhere sees bursts late, so the
//! estimate loosens by tens of milliseconds and readings land in the previous move
//! (tests/suite/daemon_xl80.rs, an RTX log flushed ten times a second).

use crate::acquisition::job::JobRegistration;
use crate::acquisition::record::StepRecord;
use crate::acquisition::sink::{SinkError, StepSink};
use crate::hw::PositionLog;
use std::sync::Arc;

pub struct ReadLog<S: StepSink> {
    /// None: the rig has no interferometer, records pass through.
    pub log: Option<Box<dyn PositionLog>>,
    registration: JobRegistration,
    pub inner: S,
}

impl<S: StepSink> ReadLog<S> {
    /// Read `log` for every record before `inner` sees it. With `registration:
    /// interferometer`, each frame registers by its reading, and a frame without one fails
    /// the job (after it is handed on: what was captured is kept).
    pub fn new(
        log: Option<Box<dyn PositionLog>>,
        registration: JobRegistration,
        inner: S,
    ) -> ReadLog<S> {
        ReadLog {
            log,
            registration,
            inner,
        }
    }
}

impl<S: StepSink> StepSink for ReadLog<S> {
    fn step(&mut self, rec: Arc<StepRecord>) -> Result<(), SinkError> {
        let Some(log) = self.log.as_mut() else {
            return self.inner.step(rec);
        };
        // The engine keeps no copy: this is the only owner, and the frame is not copied.
        let mut rec = Arc::try_unwrap(rec).unwrap_or_else(|shared| (*shared).clone());
        rec.interferometer_um = log.position_at(rec.frame.timestamp);
        rec.samples = log.take_samples();
        rec.log_source = Some(log.source());
        let by_laser = self.registration == JobRegistration::Interferometer;
        if let (true, Some(x)) = (by_laser, rec.interferometer_um) {
            rec.registration_um = x;
        }
        let (index, missing) = (rec.index, rec.interferometer_um.is_none());
        self.inner.step(Arc::new(rec))?;
        match by_laser && missing {
            true => Err(SinkError::NoInterferometerReading { index }),
            false => Ok(()),
        }
    }
    fn end_run(&mut self, run: u32) -> Result<(), SinkError> {
        self.inner.end_run(run)
    }
    fn finish(&mut self) -> Result<(), SinkError> {
        self.inner.finish()
    }
    fn wants_paused_frame(&self) -> bool {
        self.inner.wants_paused_frame()
    }
    fn paused_frame(
        &mut self,
        frame: Result<crate::hw::Frame, crate::hw::HwError>,
        stage_um: Option<f64>,
    ) {
        self.inner.paused_frame(frame, stage_um)
    }
}
