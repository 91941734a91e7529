//! The job's session as a step sink: each record's interferometer samples, frame and
//! `steps.csv` row go to disk, then the `step` event is published (a client never hears of
//! a frame that is not on disk), then the record goes on to processing.

use crate::acquisition::processor::Processor;
use crate::acquisition::record::StepRecord;
use crate::acquisition::sink::{SinkError, StepSink, Threaded};
use crate::session::{unix_s, SessionError, SessionWriter, StepRow};
use std::sync::Arc;

/// Called once a step is on disk.
pub type OnRecorded = Box<dyn Fn(&StepRecord) + Send>;

pub struct Recorder {
    pub session: SessionWriter,
    on_recorded: OnRecorded,
    /// Processing, on its own thread (none when the job does not process).
    pub processor: Option<Threaded<Processor>>,
}

impl Recorder {
    pub fn new(
        session: SessionWriter,
        on_recorded: OnRecorded,
        processor: Option<Threaded<Processor>>,
    ) -> Recorder {
        Recorder {
            session,
            on_recorded,
            processor,
        }
    }

    fn write(&mut self, rec: &StepRecord) -> Result<(), SessionError> {
        // The samples first: a reported frame's reading can be recomputed from the disk.
        self.session.append_interferometer(&rec.samples)?;
        if let Some(src) = &rec.log_source {
            // Its clock estimate moves: the manifest's next write records the last one.
            self.session.note_interferometer(src.clone());
        }
        self.session.record(row(rec), &rec.frame.image)
    }
}

fn row(rec: &StepRecord) -> StepRow {
    StepRow {
        index: rec.index,
        position_um: rec.commanded_um,
        run: rec.run,
        case: rec.case.clone(),
        repeat: rec.repeat,
        axis_um: rec.axis_um,
        interferometer_um: rec.interferometer_um,
        t_unix_s: unix_s(rec.frame.timestamp),
        sequence: rec.frame.sequence,
        move_ms: rec.timings.move_ms,
        settle_ms: rec.timings.settle_ms,
        grab_ms: rec.timings.grab_ms,
        piezo_commanded_um: rec.piezo_commanded_um,
        piezo_um: rec.piezo_um,
    }
}

/// A session error as a sink's.
pub fn disk_error(e: SessionError) -> SinkError {
    let (file, disk_full) = match &e {
        SessionError::Io { path, .. } | SessionError::Format { path, .. } => {
            (Some(path.clone()), false)
        }
        SessionError::DiskFull { path, .. } => (Some(path.clone()), true),
    };
    SinkError::Disk {
        file,
        disk_full,
        message: e.to_string(),
    }
}

impl StepSink for Recorder {
    fn step(&mut self, rec: Arc<StepRecord>) -> Result<(), SinkError> {
        self.write(&rec).map_err(disk_error)?;
        (self.on_recorded)(&rec);
        match self.processor.as_mut() {
            Some(p) => p.step(rec),
            None => Ok(()),
        }
    }
    fn end_run(&mut self, run: u32) -> Result<(), SinkError> {
        match self.processor.as_mut() {
            Some(p) => p.end_run(run),
            None => Ok(()),
        }
    }
    fn finish(&mut self) -> Result<(), SinkError> {
        match self.processor.as_mut() {
            Some(p) => p.finish(),
            None => Ok(()),
        }
    }
}
