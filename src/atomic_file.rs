//! Files that appear whole or not at all: written under a hidden temporary name beside the
//! final one (`.NAME.tmp`), synced, then renamed into place, so a reader (or a restart after
//! a crash) sees the old version or the new one, never half a file.
//!
//! [`write`] does one file. [`stage`] writes without renaming, for a set of files that should
//! appear together: stage them all, then [`Staged::commit`] each (a staged file that is
//! dropped uncommitted is removed). [`sync_dir`] makes the renames themselves durable.
//!
//! A failure removes the temporary file (a write that filled the disk leaves no partial file
//! taking the space), and the error names the file that was not written, not the temporary.
//! Temporaries are created with O_EXCL|O_NOFOLLOW, so a symlink planted at a temporary's
//! name is removed, never written through; the rename replaces a symlink at the final name.

use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// Which file was not written, and what failed (`cannot write`, `cannot rename into place`,
/// `cannot sync`).
#[derive(Debug, thiserror::Error)]
#[error("{path}: {what}: {source}")]
pub struct AtomicWriteError {
    pub path: PathBuf,
    pub what: &'static str,
    pub source: io::Error,
}

fn fail<'a>(path: &'a Path, what: &'static str) -> impl FnOnce(io::Error) -> AtomicWriteError + 'a {
    move |source| AtomicWriteError {
        path: path.to_path_buf(),
        what,
        source,
    }
}

/// The temporary name beside `path`: `dir/.NAME.tmp`.
fn temp_path(path: &Path) -> PathBuf {
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
    path.with_file_name(format!(".{name}.tmp"))
}

/// `bytes` written and synced under the temporary name, not yet in place.
#[derive(Debug)]
#[must_use = "a staged file is removed unless committed"]
pub struct Staged {
    tmp: PathBuf,
    path: PathBuf,
    committed: bool,
}

/// Write `bytes` to the temporary beside `path` and sync it to disk.
pub fn stage(path: &Path, bytes: &[u8]) -> Result<Staged, AtomicWriteError> {
    let staged = Staged {
        tmp: temp_path(path),
        path: path.to_path_buf(),
        committed: false,
    };
    // On an error `staged` drops here, removing what was written of the temporary.
    create_temp(&staged.tmp)
        .and_then(|mut f| {
            f.write_all(bytes)?;
            f.sync_all()
        })
        .map_err(fail(path, "cannot write"))?;
    Ok(staged)
}

/// Create the temporary afresh (O_EXCL: never through a symlink planted at its name, never
/// into someone else's file). Something already there is a leftover (a crash mid-write) or
/// was planted: the name is ours, so it is unlinked (a symlink itself, never its target)
/// and the file created again.
fn create_temp(tmp: &Path) -> io::Result<fs::File> {
    use std::os::unix::fs::OpenOptionsExt;
    let create = || {
        fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
            .open(tmp)
    };
    match create() {
        Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {
            let kind = fs::symlink_metadata(tmp)?.file_type();
            if kind.is_dir() {
                return Err(e);
            }
            tracing::warn!(path = %tmp.display(), symlink = kind.is_symlink(), "removing a leftover temporary before writing");
            fs::remove_file(tmp)?;
            create()
        }
        r => r,
    }
}

impl Staged {
    /// Rename into place; returns the final path. On failure the temporary is removed.
    pub fn commit(mut self) -> Result<PathBuf, AtomicWriteError> {
        fs::rename(&self.tmp, &self.path).map_err(fail(&self.path, "cannot rename into place"))?;
        self.committed = true;
        Ok(std::mem::take(&mut self.path))
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        if !self.committed {
            let _ = fs::remove_file(&self.tmp);
        }
    }
}

/// Write `bytes` to `path` atomically: temporary file, sync, rename.
pub fn write(path: &Path, bytes: &[u8]) -> Result<(), AtomicWriteError> {
    stage(path, bytes)?.commit().map(drop)
}

/// Sync a folder, so the renames into it survive a power cut.
pub fn sync_dir(dir: &Path) -> Result<(), AtomicWriteError> {
    fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(fail(dir, "cannot sync"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn write_replaces_the_file_and_leaves_no_temporary() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("a.json");
        write(&p, b"old").unwrap();
        write(&p, b"new").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"new");
        assert_eq!(names(d.path()), ["a.json"]);
        sync_dir(d.path()).unwrap();
    }

    #[test]
    fn staged_files_appear_only_when_committed() {
        let d = tempfile::tempdir().unwrap();
        let a = stage(&d.path().join("a.png"), b"A").unwrap();
        let b = stage(&d.path().join("b.png"), b"B").unwrap();
        assert_eq!(names(d.path()), [".a.png.tmp", ".b.png.tmp"]);
        assert_eq!(a.commit().unwrap(), d.path().join("a.png"));
        drop(b);
        assert_eq!(names(d.path()), ["a.png"]);
    }

    #[test]
    fn a_planted_temporary_symlink_is_replaced_not_written_through() {
        let d = tempfile::tempdir().unwrap();
        let outside = tempfile::tempdir().unwrap();
        let victim = outside.path().join("victim.json");
        fs::write(&victim, b"precious").unwrap();
        let p = d.path().join("manifest.json");
        std::os::unix::fs::symlink(&victim, d.path().join(".manifest.json.tmp")).unwrap();
        write(&p, b"{}").unwrap();
        assert_eq!(fs::read(&victim).unwrap(), b"precious");
        assert_eq!(fs::read(&p).unwrap(), b"{}");
        assert!(!fs::symlink_metadata(&p).unwrap().file_type().is_symlink());
        // A leftover regular temporary (kill -9 mid-write) is replaced too.
        fs::write(d.path().join(".manifest.json.tmp"), b"half").unwrap();
        write(&p, b"{\"a\":1}").unwrap();
        assert_eq!(names(d.path()), ["manifest.json"]);
    }

    #[test]
    fn failures_name_the_path_and_what_was_done() {
        let d = tempfile::tempdir().unwrap();
        let missing = d.path().join("no").join("x.csv");
        let e = write(&missing, b"x").unwrap_err();
        assert_eq!(e.path, missing);
        assert!(e.to_string().contains("cannot write"), "{e}");
        // Renaming over a non-empty folder fails: the final path is named.
        let target = d.path().join("full");
        fs::create_dir_all(target.join("inside")).unwrap();
        let e = write(&target, b"x").unwrap_err();
        assert_eq!(e.path, target);
        assert!(e.to_string().contains("cannot rename into place"), "{e}");
        // The temporary is gone with the failure.
        assert_eq!(names(d.path()), ["full"]);
    }
}
