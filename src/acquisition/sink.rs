//! The step engine's consumers. The engine hands every step record to one [`StepSink`]
//! (after ripgrep's `Sink` and bluesky's callbacks); the session writer, the event
//! publisher and the processor are sinks. [`Threaded`] runs a sink on its own thread behind
//! a short queue, so what a sink does (PNG encoding, fsync, processing) stays off the motion
//! path: the next move starts while the previous frame is written.

use crate::acquisition::record::StepRecord;

use crate::text::panic_message;
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

/// Why a sink could not take a step.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SinkError {
    /// A session file could not be written (`message` names the file and the cause).
    #[error("disk: {message}")]
    Disk {
        file: Option<String>,
        disk_full: bool,
        message: String,
    },
    /// The job registers by the interferometer and the log does not cover frame `index`.
    #[error("frame {index}: no interferometer reading at its time")]
    NoInterferometerReading { index: u32 },
    /// The sink's thread panicked.
    #[error("{sink} panicked: {message}")]
    Panicked { sink: String, message: String },
}

/// A consumer of step records. Every method but `step` has a do-nothing default.
pub trait StepSink: Send {
    /// A frame was captured. An error stops the job.
    fn step(&mut self, rec: Arc<StepRecord>) -> Result<(), SinkError>;
    /// Run `run` has had its last frame.
    fn end_run(&mut self, _run: u32) -> Result<(), SinkError> {
        Ok(())
    }
    /// The job has captured everything it will: flush. Called once, whatever the outcome.
    fn finish(&mut self) -> Result<(), SinkError> {
        Ok(())
    }
    /// While the job is paused: whether someone wants a fresh frame now (the live view).
    fn wants_paused_frame(&self) -> bool {
        false
    }
    /// A frame grabbed while the job is paused (not one of its steps: nothing records it),
    /// with where the job's stage is; or why the grab failed.
    fn paused_frame(
        &mut self,
        _frame: Result<crate::hw::Frame, crate::hw::HwError>,
        _stage_um: Option<f64>,
    ) {
    }
}

/// A sink that keeps every record (tests, tools).
#[derive(Default)]
pub struct Collect {
    pub records: Vec<Arc<StepRecord>>,
    pub runs_ended: Vec<u32>,
    pub finished: bool,
}

impl StepSink for Collect {
    fn step(&mut self, rec: Arc<StepRecord>) -> Result<(), SinkError> {
        self.records.push(rec);
        Ok(())
    }
    fn end_run(&mut self, run: u32) -> Result<(), SinkError> {
        self.runs_ended.push(run);
        Ok(())
    }
    fn finish(&mut self) -> Result<(), SinkError> {
        self.finished = true;
        Ok(())
    }
}

enum Msg {
    Step(Arc<StepRecord>),
    EndRun(u32),
}

/// Runs sink `S` on its own thread behind a queue of `depth` messages. `step` returns at
/// once unless the queue is full (then the engine waits: back-pressure, not a backlog).
/// The first error the sink returns is reported by the next call; a panic is reported as
/// [`SinkError::Panicked`] with its message.
pub struct Threaded<S: StepSink + 'static> {
    name: String,
    tx: Option<mpsc::SyncSender<Msg>>,
    failed: Arc<Mutex<Option<SinkError>>>,
    handle: Option<JoinHandle<S>>,
    inner: Option<S>,
}

impl<S: StepSink + 'static> Threaded<S> {
    pub fn spawn(name: &str, mut sink: S, depth: usize) -> Threaded<S> {
        let (tx, rx) = mpsc::sync_channel::<Msg>(depth);
        let failed = Arc::new(Mutex::new(None));
        let slot = failed.clone();
        let handle = std::thread::Builder::new()
            .name(format!("rigd-{name}"))
            .spawn(move || {
                for msg in rx {
                    let r = match msg {
                        Msg::Step(rec) => sink.step(rec),
                        Msg::EndRun(run) => sink.end_run(run),
                    };
                    if let Err(e) = r {
                        *slot.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
                        break;
                    }
                }
                sink
            })
            .expect("spawning a sink thread");
        Threaded {
            name: name.to_string(),
            tx: Some(tx),
            failed,
            handle: Some(handle),
            inner: None,
        }
    }

    fn check(&self) -> Result<(), SinkError> {
        match self
            .failed
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
        {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    fn send(&mut self, msg: Msg) -> Result<(), SinkError> {
        self.check()?;
        let Some(tx) = self.tx.as_ref() else {
            return Ok(());
        };
        if tx.send(msg).is_err() {
            // The thread ended: it failed (reported) or panicked (found by `join`).
            self.check()?;
            self.join()?;
        }
        Ok(())
    }

    /// Wait for the thread to drain its queue and end; keeps the sink for `into_inner`.
    fn join(&mut self) -> Result<(), SinkError> {
        self.tx = None;
        if let Some(h) = self.handle.take() {
            match h.join() {
                Ok(s) => self.inner = Some(s),
                Err(p) => {
                    return Err(SinkError::Panicked {
                        sink: self.name.clone(),
                        message: panic_message(p.as_ref()),
                    })
                }
            }
        }
        self.check()
    }

    /// The sink back, after `finish` (`None` if its thread panicked).
    pub fn into_inner(mut self) -> Option<S> {
        let _ = self.join();
        self.inner.take()
    }
}

impl<S: StepSink + 'static> StepSink for Threaded<S> {
    fn step(&mut self, rec: Arc<StepRecord>) -> Result<(), SinkError> {
        self.send(Msg::Step(rec))
    }
    fn end_run(&mut self, run: u32) -> Result<(), SinkError> {
        self.send(Msg::EndRun(run))
    }
    fn finish(&mut self) -> Result<(), SinkError> {
        self.join()?;
        match self.inner.as_mut() {
            Some(s) => s.finish(),
            None => Ok(()),
        }
    }
}

impl<S: StepSink + 'static> Drop for Threaded<S> {
    fn drop(&mut self) {
        let _ = self.join();
    }
}
