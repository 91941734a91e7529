//! Job ids unique across restarts. The next id is kept in `<data_root>/.next-job-id`,
//! written and synced (atomically: `atomic_file`) before an id is handed out, so an id is
//! never given twice: not after a crash, nor for jobs that never made a session (cancelled
//! while queued, refused at start), whose ids the sessions on disk cannot remember.

use crate::atomic_file;
use std::path::{Path, PathBuf};

/// The counter's file name in the data root (a dot file: not a session, never listed).
pub const FILE: &str = ".next-job-id";
/// The most of it read: a counter is a few digits.
const MAX_BYTES: u64 = 64;

#[derive(Debug, thiserror::Error)]
pub enum JobIdError {
    #[error("job id counter {path}: {message}")]
    Bad { path: String, message: String },
    #[error("cannot record the next job id in {path}: {source}")]
    Write {
        path: String,
        source: std::io::Error,
    },
}

/// Hands out job ids, each recorded on disk first.
#[derive(Debug)]
pub struct JobIds {
    /// `None`: ids in memory only (tests of the job table).
    path: Option<PathBuf>,
    next: u64,
}

impl JobIds {
    /// Ids in memory only, from `next`.
    pub fn in_memory(next: u64) -> JobIds {
        JobIds { path: None, next }
    }

    /// The counter of `data_root`, never below `highest_recorded + 1` (the highest job id a
    /// session records: a data root from before the counter, or one copied in).
    pub fn load(data_root: &Path, highest_recorded: u64) -> Result<JobIds, JobIdError> {
        let path = data_root.join(FILE);
        let bad = |message: String| JobIdError::Bad {
            path: path.display().to_string(),
            message,
        };
        // Below the data root, not through a symlink, and never echoed: a counter is a few
        // digits, anything else is not one.
        let stored = match crate::nofollow::read_in_max(data_root, FILE, MAX_BYTES) {
            Ok(bytes) => Some(
                std::str::from_utf8(&bytes)
                    .ok()
                    .and_then(|t| t.trim().parse::<u64>().ok())
                    .ok_or_else(|| {
                        bad(
                            "does not hold a job id (remove it only if no session is lost: \
                             ids would then restart after the highest one recorded)"
                                .into(),
                        )
                    })?,
            ),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => return Err(bad(e.to_string())),
        };
        let next = stored
            .unwrap_or(1)
            .max(highest_recorded.saturating_add(1))
            .max(1);
        Ok(JobIds {
            path: Some(path),
            next,
        })
    }

    /// The next id, once the one after it is on disk.
    pub fn take(&mut self) -> Result<u64, JobIdError> {
        let id = self.next;
        let after = id.checked_add(1).ok_or_else(|| JobIdError::Bad {
            path: self.path_text(),
            message: "job ids are exhausted".into(),
        })?;
        if let Some(path) = &self.path {
            // The rename made durable too: a power cut must not bring back the old count.
            let dir = path.parent().unwrap_or(Path::new("."));
            atomic_file::write(path, format!("{after}\n").as_bytes())
                .and_then(|()| atomic_file::sync_dir(dir))
                .map_err(|e| JobIdError::Write {
                    path: path.display().to_string(),
                    source: e.source,
                })?;
        }
        self.next = after;
        Ok(id)
    }

    fn path_text(&self) -> String {
        self.path
            .as_ref()
            .map_or_else(|| "(in memory)".into(), |p| p.display().to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_survive_a_restart_and_never_fall_below_the_recorded_ones() {
        let d = tempfile::tempdir().unwrap();
        let mut ids = JobIds::load(d.path(), 0).unwrap();
        assert_eq!((ids.take().unwrap(), ids.take().unwrap()), (1, 2));
        // Restart: job 2 made no session (the disk says 0), its id is still not reused.
        let mut ids = JobIds::load(d.path(), 0).unwrap();
        assert_eq!(ids.take().unwrap(), 3);
        assert_eq!(std::fs::read_to_string(d.path().join(FILE)).unwrap(), "4\n");
        // Sessions recording higher ids (an older data root) win.
        let mut ids = JobIds::load(d.path(), 41).unwrap();
        assert_eq!(ids.take().unwrap(), 42);
        std::fs::write(d.path().join(FILE), "forty\n").unwrap();
        let e = JobIds::load(d.path(), 0).unwrap_err().to_string();
        assert!(
            e.contains(".next-job-id") && e.contains("does not hold a job id"),
            "{e}"
        );
        assert!(!e.contains("forty"), "the contents are not echoed: {e}");
    }

    #[test]
    fn a_counter_symlinked_out_of_the_data_root_is_refused_and_not_echoed() {
        let d = tempfile::tempdir().unwrap();
        let outside = tempfile::tempdir().unwrap();
        let secret = outside.path().join("secret");
        std::fs::write(&secret, "hunter2\n").unwrap();
        std::os::unix::fs::symlink(&secret, d.path().join(FILE)).unwrap();
        let e = JobIds::load(d.path(), 0).unwrap_err().to_string();
        assert!(e.contains("symbolic link") && !e.contains("hunter2"), "{e}");
        std::fs::remove_file(d.path().join(FILE)).unwrap();
        std::fs::write(d.path().join(FILE), "9".repeat(100)).unwrap();
        let e = JobIds::load(d.path(), 0).unwrap_err().to_string();
        assert!(
            e.contains("over the 64-byte limit") && !e.contains("999"),
            "{e}"
        );
    }

    #[test]
    fn an_unwritable_counter_refuses_the_id() {
        let d = tempfile::tempdir().unwrap();
        let mut ids = JobIds::load(&d.path().join("gone"), 0).unwrap();
        let e = ids.take().unwrap_err().to_string();
        assert!(e.starts_with("cannot record the next job id in "), "{e}");
        // The id was not handed out: the next try gets it.
        std::fs::create_dir(d.path().join("gone")).unwrap();
        assert_eq!(ids.take().unwrap(), 1);
    }
}
