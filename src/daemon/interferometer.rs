//! The interferometer in a job: the rig's [`PositionLog`] (`rig::FollowedLog` on hardware
//! and on the sim) asked for the reading at each frame, what it read written to the session.

use crate::daemon::session::{SessionError, SessionWriter};
use crate::rig::PositionLog;
use std::time::SystemTime;

/// At a job's start: point the log at the job and record its source in the session.
pub fn begin_job(
    log: Option<&mut (dyn PositionLog + 'static)>,
    session: &mut SessionWriter,
) -> Result<(), SessionError> {
    match log {
        Some(log) => {
            log.begin(SystemTime::now());
            session.begin_interferometer(log.source())
        }
        None => Ok(()),
    }
}

/// For a captured frame: the reading at its time, after the samples read so far are on disk.
pub fn at_frame(
    log: Option<&mut (dyn PositionLog + 'static)>,
    session: &mut SessionWriter,
    t: SystemTime,
) -> Result<Option<f64>, SessionError> {
    let Some(log) = log else {
        return Ok(None);
    };
    let at = log.position_at(t);
    session.append_interferometer(&log.take_samples())?;
    // The clock estimate may have moved: the manifest's final write records the last one.
    session.note_interferometer(log.source());
    Ok(at)
}
