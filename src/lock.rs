//! One owner at a time: an exclusive `flock` on a lock file, held for as long as the
//! [`LockFile`] lives (the kernel drops it when the process dies, even by `kill -9`, so a
//! lock is never stale). The file records who holds it ([`Holder`]: pid, program, socket,
//! data root, since when), so whoever is refused can be told by whom.
//!
//! Lock files are opened without following a symlink (a lock directory such as /tmp is
//! writable by anyone) and are never removed: removing a lock file while another process
//! waits to lock it would let two processes hold "the same" lock.
//!
//! Device locks live in one directory every rigd and `rigctl hw` share ([`lock_dir`]), one
//! file per device name ([`device_lock_path`]).

use nix::fcntl::{Flock, FlockArg};
use serde::{Deserialize, Serialize};
use std::fs::{File, OpenOptions};
use std::io::{self, Read};
use std::os::unix::fs::{FileExt, OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};

/// Who holds a lock, as recorded in its file (one JSON line).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Holder {
    pub pid: u32,
    /// `rigd`, `rigctl hw`, `rigctl demo`.
    pub program: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub socket: Option<PathBuf>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data_root: Option<PathBuf>,
    pub since_unix_s: u64,
}

impl Holder {
    /// This process, now.
    pub fn me(program: &str, socket: Option<&Path>, data_root: Option<&Path>) -> Holder {
        let abs = |p: &Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
        Holder {
            pid: std::process::id(),
            program: program.into(),
            socket: socket.map(abs),
            data_root: data_root.map(abs),
            since_unix_s: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs()),
        }
    }
}

impl std::fmt::Display for Holder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} (pid {}", self.program, self.pid)?;
        if let Some(s) = &self.socket {
            write!(f, ", socket {}", s.display())?;
        }
        if let Some(d) = &self.data_root {
            write!(f, ", data root {}", d.display())?;
        }
        let since = time::OffsetDateTime::from_unix_timestamp(self.since_unix_s as i64)
            .ok()
            .and_then(|t| {
                t.format(&time::format_description::well_known::Rfc3339)
                    .ok()
            });
        if let Some(t) = since {
            write!(f, ", since {t}")?;
        }
        write!(f, ")")
    }
}

#[derive(Debug, thiserror::Error)]
pub enum LockError {
    /// Someone else holds it: `holder` says who (as far as the lock file tells).
    #[error("{what} is held by {holder}{hint}")]
    Held {
        what: String,
        path: PathBuf,
        holder: String,
        hint: String,
    },
    #[error("{what}: lock file {}: {source}", path.display())]
    Io {
        what: String,
        path: PathBuf,
        source: io::Error,
    },
}

/// An exclusive lock, held until dropped.
#[derive(Debug)]
pub struct LockFile {
    path: PathBuf,
    _lock: Flock<File>,
}

impl LockFile {
    /// Take the lock at `path` for `what` (named in errors: "socket /run/rigd/rigd.sock"),
    /// recording `holder`; `hint` ends the refusal's message (what to do about it). Does
    /// not wait: a held lock is an error at once.
    pub fn acquire(
        path: &Path,
        what: &str,
        holder: &Holder,
        hint: &str,
    ) -> Result<LockFile, LockError> {
        let io_err = |source| LockError::Io {
            what: what.into(),
            path: path.to_path_buf(),
            source,
        };
        let (file, writable) = open_lock_file(path).map_err(io_err)?;
        let lock = match Flock::lock(file, FlockArg::LockExclusiveNonblock) {
            Ok(l) => l,
            Err((file, nix::errno::Errno::EWOULDBLOCK)) => {
                return Err(LockError::Held {
                    what: what.into(),
                    path: path.to_path_buf(),
                    holder: describe_holder(&file),
                    hint: hint.into(),
                })
            }
            Err((_, e)) => return Err(io_err(e.into())),
        };
        if writable {
            // Ours now: replace the last holder's record (truncate only once locked).
            let mut line = serde_json::to_vec(holder).unwrap_or_default();
            line.push(b'\n');
            lock.set_len(0)
                .and_then(|_| lock.write_all_at(&line, 0))
                .map_err(io_err)?;
        }
        Ok(LockFile {
            path: path.to_path_buf(),
            _lock: lock,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Open (or create, mode 0644 so others can lock it too) the lock file without following a
/// symlink; read-only when it is someone else's (a lock on a read-only descriptor is as
/// exclusive). True when it can be written.
fn open_lock_file(path: &Path) -> io::Result<(File, bool)> {
    let flags = libc::O_NOFOLLOW | libc::O_CLOEXEC;
    for _ in 0..3 {
        // Not O_CREAT first: in a sticky world-writable folder (/run/lock, /tmp) the kernel
        // refuses O_CREAT on another user's existing file (fs.protected_regular).
        let rw = OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(flags)
            .open(path);
        let (file, writable) = match rw {
            Ok(f) => (f, true),
            Err(e) if matches!(e.raw_os_error(), Some(libc::EACCES | libc::EROFS)) => {
                let ro = OpenOptions::new()
                    .read(true)
                    .custom_flags(flags)
                    .open(path)?;
                (ro, false)
            }
            Err(e) if e.kind() == io::ErrorKind::NotFound => {
                match OpenOptions::new()
                    .read(true)
                    .write(true)
                    .create_new(true)
                    .mode(0o644)
                    .custom_flags(flags)
                    .open(path)
                {
                    Ok(f) => {
                        // Readable by every user whatever the umask (rigctl hw locks it too).
                        f.set_permissions(std::fs::Permissions::from_mode(0o644))?;
                        (f, true)
                    }
                    Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
                    Err(e) => return Err(e),
                }
            }
            Err(e) if e.raw_os_error() == Some(libc::ELOOP) => {
                return Err(io::Error::other(
                    "is a symbolic link: not followed (remove it)",
                ))
            }
            Err(e) => return Err(e),
        };
        if !file.metadata()?.is_file() {
            return Err(io::Error::other("is not a regular file (remove it)"));
        }
        return Ok((file, writable));
    }
    Err(io::Error::other("keeps appearing and vanishing"))
}

/// The holder a held lock's file names; "an unknown process" when the record is missing
/// or names a process that has exited (a `rigctl hw` that could not write its record).
fn describe_holder(mut file: &File) -> String {
    let mut text = String::new();
    let _ = file.read_to_string(&mut text);
    match serde_json::from_str::<Holder>(text.trim()) {
        Ok(h) if alive(h.pid) => h.to_string(),
        _ => "an unknown process (its lock file names no live holder)".into(),
    }
}

fn alive(pid: u32) -> bool {
    let Ok(pid) = i32::try_from(pid) else {
        return false;
    };
    // Signal 0 checks that the process exists; EPERM means it does (another user's).
    match nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid), None) {
        Ok(()) => true,
        Err(e) => e == nix::errno::Errno::EPERM,
    }
}

/// The folder device locks live in: `configured` (`[daemon] lock_dir`), else `/run/lock`
/// when it is writable, else `$XDG_RUNTIME_DIR`, else `/tmp`.
pub fn lock_dir(configured: Option<&Path>) -> PathBuf {
    if let Some(d) = configured {
        return d.to_path_buf();
    }
    let run_lock = Path::new("/run/lock");
    if nix::unistd::access(run_lock, nix::unistd::AccessFlags::W_OK).is_ok() {
        return run_lock.to_path_buf();
    }
    match std::env::var_os("XDG_RUNTIME_DIR") {
        Some(d) if !d.is_empty() => PathBuf::from(d),
        _ => PathBuf::from("/tmp"),
    }
}

/// The names a device goes by: as configured (made absolute), and its canonical path if
/// that differs (a /dev/serial/by-id link resolved). Both are locked, so a second owner is
/// refused whichever name it uses, even after the link has moved to another node.
pub fn device_names(device: &str) -> Vec<PathBuf> {
    let given = std::path::absolute(device).unwrap_or_else(|_| PathBuf::from(device));
    let mut names = vec![given.clone()];
    if let Ok(real) = std::fs::canonicalize(&given) {
        if real != given {
            names.push(real);
        }
    }
    names
}

/// The lock file of the device named `device_path` in `dir`: `rigd-dev-ttyUSB0.lock` for
/// `/dev/ttyUSB0` ('/' becomes '-'; '-', '%' and anything unusual are %-escaped, so two
/// paths never share a file).
pub fn device_lock_path(dir: &Path, device_path: &Path) -> PathBuf {
    let mut name = String::from("rigd");
    for b in device_path.as_os_str().as_encoded_bytes() {
        match b {
            b'/' => name.push('-'),
            b'a'..=b'z' | b'A'..=b'Z' | b'0'..=b'9' | b'.' | b'_' => name.push(*b as char),
            _ => name.push_str(&format!("%{b:02X}")),
        }
    }
    name.push_str(".lock");
    dir.join(name)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn me() -> Holder {
        Holder::me("rigd", Some(Path::new("/run/rigd/rigd.sock")), None)
    }

    #[test]
    fn a_second_lock_is_refused_naming_the_holder_and_freed_on_drop() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("x.lock");
        let first = LockFile::acquire(&p, "data root /srv", &me(), "").unwrap();
        // flock is per open file: a second open in this very process is also refused.
        let e = LockFile::acquire(&p, "data root /srv", &me(), ": stop it first").unwrap_err();
        let msg = e.to_string();
        let pid = std::process::id();
        assert!(
            msg.starts_with(&format!(
                "data root /srv is held by rigd (pid {pid}, socket /run/rigd/rigd.sock, since "
            )) && msg.ends_with("): stop it first"),
            "{msg}"
        );
        assert!(matches!(e, LockError::Held { .. }));
        drop(first);
        let again = LockFile::acquire(&p, "data root /srv", &me(), "").unwrap();
        assert_eq!(again.path(), p);
    }

    #[test]
    fn a_symlinked_lock_file_is_not_followed_and_its_target_is_untouched() {
        let d = tempfile::tempdir().unwrap();
        let victim = d.path().join("victim");
        std::fs::write(&victim, b"precious").unwrap();
        let p = d.path().join("x.lock");
        std::os::unix::fs::symlink(&victim, &p).unwrap();
        let e = LockFile::acquire(&p, "socket s", &me(), "").unwrap_err();
        assert!(e.to_string().contains("symbolic link"), "{e}");
        assert_eq!(std::fs::read(&victim).unwrap(), b"precious");
    }

    #[test]
    fn a_record_naming_a_dead_process_says_unknown() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("x.lock");
        let held = LockFile::acquire(&p, "port /dev/x", &me(), "").unwrap();
        // Overwrite the record with a pid that cannot be alive (beyond pid_max).
        let mut h = me();
        h.pid = 1 << 30;
        std::fs::write(&p, serde_json::to_vec(&h).unwrap()).unwrap();
        let e = LockFile::acquire(&p, "port /dev/x", &me(), "").unwrap_err();
        assert!(e.to_string().contains("an unknown process"), "{e}");
        drop(held);
    }

    #[test]
    fn device_lock_names_are_distinct_and_readable() {
        let d = Path::new("/run/lock");
        assert_eq!(
            device_lock_path(d, Path::new("/dev/ttyUSB0")),
            Path::new("/run/lock/rigd-dev-ttyUSB0.lock")
        );
        // '-' in a name cannot collide with a '/'.
        let a = device_lock_path(d, Path::new("/dev/serial/by-id/usb-FTDI-if00"));
        let b = device_lock_path(d, Path::new("/dev/serial/by/id/usb/FTDI/if00"));
        assert_ne!(a, b);
        assert_eq!(
            a,
            Path::new("/run/lock/rigd-dev-serial-by%2Did-usb%2DFTDI%2Dif00.lock")
        );
    }

    #[test]
    fn a_by_id_link_is_locked_under_both_names() {
        let d = tempfile::tempdir().unwrap();
        let real = d.path().join("ttyUSB7");
        std::fs::write(&real, b"").unwrap();
        let link = d.path().join("usb-FTDI-if00");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        let names = device_names(link.to_str().unwrap());
        assert_eq!(names, vec![link, std::fs::canonicalize(&real).unwrap()]);
        // A name that does not resolve keeps only its given form.
        assert_eq!(device_names("/dev/nonexistent-tty").len(), 1);
    }
}
