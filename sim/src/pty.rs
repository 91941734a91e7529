//! Pseudo-terminals for the controller emulators.
//!
//! The emulator keeps the master side; a driver opens the slave path exactly as it would
//! open `/dev/ttyUSB0`. The emulator does not keep the slave open itself, so it can tell
//! when a driver opens and closes the port (the master polls `POLLHUP` while no one holds
//! the slave), which is how it knows to print its power-on banner, like a board reset by DTR.
//!
//! A [`PtyLink`] adds a stable path (a symlink, as `socat ... link=` makes) that survives the
//! port vanishing and coming back on a new `/dev/pts/N`, so a driver can reopen "the same"
//! port after a fault, as after unplugging and replugging a USB adapter.

use std::ffi::CStr;
use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd, RawFd};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The master side of a pseudo-terminal and the path of its slave.
#[derive(Debug)]
pub struct Pty {
    master: OwnedFd,
    slave_path: PathBuf,
}

/// What polling the master saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PollResult {
    /// Bytes are waiting to be read.
    Readable,
    /// Nobody has the slave open.
    Hangup,
    /// Nothing happened within the timeout.
    Quiet,
}

impl Pty {
    /// Open a new pseudo-terminal in raw mode (no echo, no line editing, no CR/LF mapping).
    pub fn open() -> io::Result<Pty> {
        let mut master: libc::c_int = -1;
        let mut slave: libc::c_int = -1;
        // SAFETY: openpty writes two fds; the name/termios/winsize pointers may be null.
        let rc = unsafe {
            libc::openpty(
                &mut master,
                &mut slave,
                std::ptr::null_mut(),
                std::ptr::null(),
                std::ptr::null(),
            )
        };
        if rc != 0 {
            return Err(io::Error::last_os_error());
        }
        // SAFETY: both fds were just returned by openpty and are owned by nobody else.
        let master = unsafe { OwnedFd::from_raw_fd(master) };
        let slave = unsafe { OwnedFd::from_raw_fd(slave) };
        set_raw(slave.as_raw_fd())?;
        set_raw(master.as_raw_fd())?;
        let slave_path = tty_name(slave.as_raw_fd())?;
        set_cloexec(master.as_raw_fd())?;
        // Dropping `slave` closes our copy: from now on HUP on the master means "no client".
        drop(slave);
        Ok(Pty { master, slave_path })
    }

    /// The path a driver opens (`/dev/pts/N`).
    pub fn slave_path(&self) -> &Path {
        &self.slave_path
    }

    pub fn master_fd(&self) -> RawFd {
        self.master.as_raw_fd()
    }

    /// Wait up to `timeout` for input or a hangup.
    pub fn poll(&self, timeout: Duration) -> io::Result<PollResult> {
        let mut pfd = libc::pollfd {
            fd: self.master.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        let ms = timeout.as_millis().min(i32::MAX as u128) as libc::c_int;
        // SAFETY: one valid pollfd.
        let n = unsafe { libc::poll(&mut pfd, 1, ms) };
        if n < 0 {
            let e = io::Error::last_os_error();
            if e.kind() == io::ErrorKind::Interrupted {
                return Ok(PollResult::Quiet);
            }
            return Err(e);
        }
        if n == 0 {
            return Ok(PollResult::Quiet);
        }
        if pfd.revents & libc::POLLIN != 0 {
            return Ok(PollResult::Readable);
        }
        if pfd.revents & libc::POLLHUP != 0 {
            return Ok(PollResult::Hangup);
        }
        Ok(PollResult::Quiet)
    }

    /// Read what is available (after `poll` said `Readable`). EIO means the slave closed.
    pub fn read(&self, buf: &mut [u8]) -> io::Result<usize> {
        // SAFETY: buf is valid for buf.len() bytes.
        let n = unsafe { libc::read(self.master.as_raw_fd(), buf.as_mut_ptr().cast(), buf.len()) };
        if n < 0 {
            return Err(io::Error::last_os_error());
        }
        Ok(n as usize)
    }

    /// Write all of `data` to the slave's input.
    pub fn write_all(&self, mut data: &[u8]) -> io::Result<()> {
        while !data.is_empty() {
            // SAFETY: data is valid for data.len() bytes.
            let n =
                unsafe { libc::write(self.master.as_raw_fd(), data.as_ptr().cast(), data.len()) };
            if n < 0 {
                let e = io::Error::last_os_error();
                if e.kind() == io::ErrorKind::Interrupted {
                    continue;
                }
                return Err(e);
            }
            data = &data[n as usize..];
        }
        Ok(())
    }
}

fn set_raw(fd: RawFd) -> io::Result<()> {
    // SAFETY: termios is plain data filled by tcgetattr before use.
    unsafe {
        let mut t: libc::termios = std::mem::zeroed();
        if libc::tcgetattr(fd, &mut t) != 0 {
            return Err(io::Error::last_os_error());
        }
        libc::cfmakeraw(&mut t);
        if libc::tcsetattr(fd, libc::TCSANOW, &t) != 0 {
            return Err(io::Error::last_os_error());
        }
    }
    Ok(())
}

fn set_cloexec(fd: RawFd) -> io::Result<()> {
    // SAFETY: fcntl on a valid fd.
    let rc = unsafe { libc::fcntl(fd, libc::F_SETFD, libc::FD_CLOEXEC) };
    if rc < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

fn tty_name(fd: RawFd) -> io::Result<PathBuf> {
    let mut buf = [0 as libc::c_char; 256];
    // SAFETY: buf is valid for its length; ttyname_r NUL-terminates on success.
    let rc = unsafe { libc::ttyname_r(fd, buf.as_mut_ptr(), buf.len()) };
    if rc != 0 {
        return Err(io::Error::from_raw_os_error(rc));
    }
    // SAFETY: NUL-terminated by ttyname_r.
    let name = unsafe { CStr::from_ptr(buf.as_ptr()) };
    Ok(PathBuf::from(name.to_string_lossy().into_owned()))
}

/// A stable path (symlink) to whichever pty currently serves.
#[derive(Debug)]
pub struct PtyLink {
    link: PathBuf,
}

impl PtyLink {
    pub fn new(link: impl Into<PathBuf>) -> PtyLink {
        PtyLink { link: link.into() }
    }

    pub fn path(&self) -> &Path {
        &self.link
    }

    /// Point the link at `target`, atomically (rename over the old link).
    pub fn point_to(&self, target: &Path) -> io::Result<()> {
        let tmp = self.link.with_extension("tmp-link");
        let _ = std::fs::remove_file(&tmp);
        std::os::unix::fs::symlink(target, &tmp)?;
        std::fs::rename(&tmp, &self.link)
    }

    /// Remove the link (the port vanished).
    pub fn remove(&self) {
        let _ = std::fs::remove_file(&self.link);
    }
}

impl Drop for PtyLink {
    fn drop(&mut self) {
        self.remove();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Write};

    #[test]
    fn the_master_sees_a_client_open_write_and_close_the_slave() {
        let pty = Pty::open().unwrap();
        assert_eq!(
            pty.poll(Duration::from_millis(5)).unwrap(),
            PollResult::Hangup
        );
        let mut client = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(pty.slave_path())
            .unwrap();
        assert_eq!(
            pty.poll(Duration::from_millis(5)).unwrap(),
            PollResult::Quiet
        );
        client.write_all(b"?\n").unwrap();
        assert_eq!(
            pty.poll(Duration::from_millis(500)).unwrap(),
            PollResult::Readable
        );
        let mut buf = [0u8; 16];
        let n = pty.read(&mut buf).unwrap();
        // Raw mode: no CR/LF translation, no echo.
        assert_eq!(&buf[..n], b"?\n");
        pty.write_all(b"ok\r\n").unwrap();
        let mut got = [0u8; 4];
        client.read_exact(&mut got).unwrap();
        assert_eq!(&got, b"ok\r\n");
        drop(client);
        assert_eq!(
            pty.poll(Duration::from_millis(50)).unwrap(),
            PollResult::Hangup
        );
    }
}
