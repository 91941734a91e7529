//! One daemon per socket, per data root and per device: what `rigd` claims before it opens
//! a port, writes a byte to a controller or recovers a session, and holds until it exits.
//!
//! The order (each step refuses with one line naming what is held and by whom, having
//! changed nothing that another daemon owns):
//! 1. the socket's lock, `<socket>.lock`: a second daemon on the same socket, whatever its
//!    data root, is refused first (this also closes the check-then-bind race);
//! 2. the socket path: a live socket (an old daemon that takes no lock) is refused naming
//!    its pid; anything that is not a socket is refused and left alone; only a stale
//!    socket is removed;
//! 3. each device the config names (serial ports, a V4L2 camera path), in the shared lock
//!    folder ([`crate::lock::lock_dir`]) under every name it goes by;
//! 4. the data root's lock, `<data_root>/.rigd.lock`: sessions, recovery and job ids have
//!    one writer. Last, so an instance refused for a device does not even create its
//!    (new) data root.

use crate::config::{CameraDriver, Config, DaemonSettings, StageDriver};
use crate::lock::{device_lock_path, device_names, lock_dir, Holder, LockError, LockFile};
use std::os::unix::fs::FileTypeExt;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum OwnershipError {
    #[error(transparent)]
    Held(#[from] LockError),
    #[error("socket {}: {message}", path.display())]
    Socket { path: PathBuf, message: String },
    #[error("{what} {}: {source}", path.display())]
    Io {
        what: &'static str,
        path: PathBuf,
        source: std::io::Error,
    },
}

/// A device the rig's config names: which key (`[axis] port`) and the path it gives.
#[derive(Debug, Clone, PartialEq)]
pub struct Device {
    pub key: String,
    pub path: String,
}

/// The devices `cfg` would have rigd open: the serial ports of GRBL and GCS stages, and a
/// V4L2 camera given by path (a camera given by name is found at open time).
pub fn devices_of(cfg: &Config) -> Vec<Device> {
    let mut v = Vec::new();
    for (name, stage) in [("axis", &cfg.axis), ("piezo", &cfg.piezo)] {
        let Some(s) = stage else { continue };
        if matches!(s.driver, StageDriver::Grbl | StageDriver::Gcs) {
            if let Some(p) = s.port.as_ref().filter(|p| !p.is_empty()) {
                v.push(Device {
                    key: format!("[{name}] port"),
                    path: p.clone(),
                });
            }
        }
    }
    if let Some(c) = &cfg.camera {
        if c.driver == CameraDriver::V4l2 {
            if let Some(d) = c.device.as_ref().filter(|d| d.starts_with('/')) {
                v.push(Device {
                    key: "[camera] device".into(),
                    path: d.clone(),
                });
            }
        }
    }
    v
}

/// Lock every name of every device in `devices` for `holder`, in the lock folder `dir`.
pub fn lock_devices(
    dir: &Path,
    devices: &[Device],
    holder: &Holder,
    hint: &str,
) -> Result<Vec<LockFile>, OwnershipError> {
    if devices.is_empty() {
        return Ok(Vec::new());
    }
    std::fs::create_dir_all(dir).map_err(|source| OwnershipError::Io {
        what: "lock folder",
        path: dir.to_path_buf(),
        source,
    })?;
    let mut locks: Vec<LockFile> = Vec::new();
    for d in devices {
        for name in device_names(&d.path) {
            let path = device_lock_path(dir, &name);
            // Two keys naming one device (axis and piezo on one port): locked once.
            if locks.iter().any(|l| l.path() == path) {
                continue;
            }
            let what = format!("{} {}", d.key, name.display());
            locks.push(LockFile::acquire(&path, &what, holder, hint)?);
        }
    }
    Ok(locks)
}

/// What this daemon holds; dropped last, after the rig is closed.
#[derive(Debug)]
pub struct Ownership {
    settings: DaemonSettings,
    _locks: Vec<LockFile>,
}

/// The socket lock's path: `<socket>.lock` beside it.
pub fn socket_lock_path(socket: &Path) -> PathBuf {
    let mut s = socket.as_os_str().to_owned();
    s.push(".lock");
    PathBuf::from(s)
}

impl Ownership {
    /// Claim the socket, the data root and `devices` for `program` (see the module doc for
    /// the order). A stale socket at the path is removed; nothing else is changed.
    pub fn claim(
        settings: &DaemonSettings,
        devices: &[Device],
        program: &str,
    ) -> Result<Ownership, OwnershipError> {
        let me = Holder::me(program, Some(&settings.socket), Some(&settings.data_root));
        let socket = &settings.socket;
        if let Some(dir) = socket.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|source| OwnershipError::Io {
                what: "socket folder",
                path: dir.to_path_buf(),
                source,
            })?;
        }
        let mut locks = vec![LockFile::acquire(
            &socket_lock_path(socket),
            &format!("socket {}", socket.display()),
            &me,
            ": another daemon serves there (stop it, or give another --socket)",
        )?];
        clear_socket_path(socket)?;
        let dir = lock_dir(settings.lock_dir.as_deref());
        locks.extend(lock_devices(
            &dir,
            devices,
            &me,
            ": it owns the hardware (stop it first: `sudo systemctl stop rigd`)",
        )?);
        let root = &settings.data_root;
        std::fs::create_dir_all(root).map_err(|source| OwnershipError::Io {
            what: "data root",
            path: root.clone(),
            source,
        })?;
        locks.push(LockFile::acquire(
            &root.join(".rigd.lock"),
            &format!("data root {}", root.display()),
            &me,
            ": one daemon per data root (stop it, or give another --data-root)",
        )?);
        Ok(Ownership {
            settings: settings.clone(),
            _locks: locks,
        })
    }

    pub fn settings(&self) -> &DaemonSettings {
        &self.settings
    }
}

/// Make way for the socket: nothing there, or a stale socket (removed). A live socket or
/// anything else at the path is an error, and is left as it is.
fn clear_socket_path(path: &Path) -> Result<(), OwnershipError> {
    let err = |message: String| OwnershipError::Socket {
        path: path.to_path_buf(),
        message,
    };
    let meta = match std::fs::symlink_metadata(path) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(err(e.to_string())),
    };
    let ft = meta.file_type();
    if !ft.is_socket() {
        let kind = if ft.is_symlink() {
            "a symbolic link"
        } else if ft.is_dir() {
            "a folder"
        } else if ft.is_file() {
            "a regular file"
        } else {
            "not a socket"
        };
        return Err(err(format!(
            "exists and is {kind}: left alone (remove it yourself, or give another --socket)"
        )));
    }
    match std::os::unix::net::UnixStream::connect(path) {
        Ok(s) => {
            let who = peer_pid(&s).map_or("a process".into(), |p| format!("pid {p}"));
            Err(err(format!(
                "another daemon ({who}) is listening on it: stop it first, or give another --socket"
            )))
        }
        Err(e) if e.raw_os_error() == Some(libc::ECONNREFUSED) => {
            tracing::info!(socket = %path.display(), "removing a stale socket");
            std::fs::remove_file(path)
                .map_err(|e| err(format!("cannot remove the stale socket: {e}")))
        }
        Err(e) => Err(err(format!("cannot tell whether it is in use: {e}"))),
    }
}

/// The pid of the process at the other end of a Unix socket (SO_PEERCRED).
fn peer_pid(s: &std::os::unix::net::UnixStream) -> Option<i32> {
    use std::os::fd::AsRawFd;
    let mut cred = libc::ucred {
        pid: 0,
        uid: 0,
        gid: 0,
    };
    let mut len = std::mem::size_of::<libc::ucred>() as libc::socklen_t;
    // SAFETY: `cred` and `len` are valid for writes of the sizes passed; the fd is open.
    // (nix wraps this behind its `socket` feature, which needs a crate we do not build.)
    let r = unsafe {
        libc::getsockopt(
            s.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_PEERCRED,
            (&mut cred as *mut libc::ucred).cast(),
            &mut len,
        )
    };
    (r == 0 && cred.pid > 0).then_some(cred.pid)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(dir: &Path, sock: &str, data: &str) -> DaemonSettings {
        DaemonSettings {
            socket: dir.join(sock),
            group: None,
            data_root: dir.join(data),
            lock_dir: Some(dir.join("locks")),
            ..DaemonSettings::default()
        }
    }

    #[test]
    fn a_second_claim_on_the_socket_or_the_data_root_is_refused() {
        let d = tempfile::tempdir().unwrap();
        let first = Ownership::claim(&settings(d.path(), "a.sock", "data"), &[], "rigd").unwrap();
        let e = Ownership::claim(&settings(d.path(), "a.sock", "other"), &[], "rigd")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with(&format!(
                "socket {} is held by rigd (pid ",
                d.path().join("a.sock").display()
            )),
            "{e}"
        );
        // The refused claim never reached the other data root.
        assert!(!d.path().join("other").exists());
        let e = Ownership::claim(&settings(d.path(), "b.sock", "data"), &[], "rigd")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with(&format!(
                "data root {} is held by",
                d.path().join("data").display()
            )),
            "{e}"
        );
        drop(first);
        Ownership::claim(&settings(d.path(), "b.sock", "data"), &[], "rigd").unwrap();
    }

    #[test]
    fn devices_are_locked_by_every_name() {
        let d = tempfile::tempdir().unwrap();
        let real = d.path().join("ttyUSB3");
        std::fs::write(&real, b"").unwrap();
        let link = d.path().join("by-id-link");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        let dev = |p: &Path| Device {
            key: "[axis] port".into(),
            path: p.display().to_string(),
        };
        let first =
            Ownership::claim(&settings(d.path(), "a.sock", "a"), &[dev(&link)], "rigd").unwrap();
        // Another daemon naming the node itself, not the link, is refused all the same.
        let e = Ownership::claim(&settings(d.path(), "b.sock", "b"), &[dev(&real)], "rigd")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with(&format!("[axis] port {} is held by rigd", real.display())),
            "{e}"
        );
        drop(first);
    }

    #[test]
    fn the_devices_of_a_config_are_its_serial_ports_and_a_camera_path() {
        let text = r#"
[axis]
driver = "grbl"
port = "/dev/serial/by-id/usb-grbl"
soft_min_um = 0.0
soft_max_um = 1.0
max_step_um = 1.0
[piezo]
driver = "sim"
port = "/dev/ttyUSB9"
soft_min_um = 0.0
soft_max_um = 1.0
max_step_um = 1.0
[camera]
driver = "v4l2"
device = "/dev/video0"
"#;
        let cfg = Config::from_toml_str(text, Path::new("/etc/rigd/rigd.toml")).unwrap();
        let keys: Vec<(String, String)> = devices_of(&cfg)
            .into_iter()
            .map(|d| (d.key, d.path))
            .collect();
        // A sim piezo opens no port, whatever its `port` says.
        assert_eq!(
            keys,
            [
                ("[axis] port".into(), "/dev/serial/by-id/usb-grbl".into()),
                ("[camera] device".into(), "/dev/video0".into()),
            ]
        );
        // A camera given by name is found at open time: no path to lock.
        let by_name = text.replace("/dev/video0", "USB Camera");
        let cfg = Config::from_toml_str(&by_name, Path::new("/etc/rigd/rigd.toml")).unwrap();
        assert_eq!(devices_of(&cfg).len(), 1);
    }

    #[test]
    fn only_a_stale_socket_is_removed() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("s.sock");
        std::fs::write(&p, b"keep me").unwrap();
        let e = clear_socket_path(&p).unwrap_err().to_string();
        assert!(e.contains("is a regular file: left alone"), "{e}");
        assert_eq!(std::fs::read(&p).unwrap(), b"keep me");
        std::fs::remove_file(&p).unwrap();
        let live = std::os::unix::net::UnixListener::bind(&p).unwrap();
        let e = clear_socket_path(&p).unwrap_err().to_string();
        let pid = std::process::id();
        assert!(
            e.contains(&format!("another daemon (pid {pid}) is listening")),
            "{e}"
        );
        drop(live); // the socket file stays, nobody listens: stale
        clear_socket_path(&p).unwrap();
        assert!(!p.exists());
    }
}
