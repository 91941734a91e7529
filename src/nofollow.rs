//! Files below a folder, opened without following a symlink at any step: the data root is
//! written by the daemon alone, but a symlink planted in it (a session folder, a frame, a
//! temporary) must not lead a read or a write out of it.
//!
//! [`open_in`] walks `rel` one component at a time with `openat(O_NOFOLLOW)` from the folder
//! `dir` (itself opened with O_NOFOLLOW), so neither `dir`'s last component, nor a folder
//! inside it, nor the file itself may be a symlink. A symlink found is an error that says
//! so (`ELOOP` otherwise reads "too many levels of symbolic links").

use nix::fcntl::{openat, OFlag};
use nix::sys::stat::Mode;
use std::fs::File;
use std::io::{self, Read};
use std::os::fd::OwnedFd;
use std::path::{Component, Path};

/// How [`open_in`] opens the file at the end of the walk.
#[derive(Debug, Clone, Copy)]
pub enum Access {
    /// Read only; a FIFO or device planted there is refused, not waited on.
    Read,
    /// Append to an existing file.
    Append,
}

fn symlink_error(path: &Path) -> io::Error {
    io::Error::other(format!(
        "{}: a symbolic link: not followed out of the data root",
        path.display()
    ))
}

fn errno(path: &Path, e: nix::errno::Errno) -> io::Error {
    use nix::errno::Errno;
    // O_NOFOLLOW on a symlink is ELOOP; with O_DIRECTORY (a folder on the way) ENOTDIR.
    let link = || std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink());
    if e == Errno::ELOOP || (e == Errno::ENOTDIR && link()) {
        return symlink_error(path);
    }
    io::Error::from(e)
}

/// Open `dir/rel` (rel: plain names only) without following a symlink anywhere from `dir`'s
/// last component on; the file must be a regular file.
pub fn open_in(dir: &Path, rel: &Path, access: Access) -> io::Result<File> {
    let folder = OFlag::O_RDONLY | OFlag::O_DIRECTORY | OFlag::O_NOFOLLOW | OFlag::O_CLOEXEC;
    let mut fd: OwnedFd =
        nix::fcntl::open(dir, folder, Mode::empty()).map_err(|e| errno(dir, e))?;
    let names: Vec<_> = rel.components().collect();
    let mut at = dir.to_path_buf();
    for (i, c) in names.iter().enumerate() {
        let Component::Normal(name) = c else {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("{}: not a plain relative path", rel.display()),
            ));
        };
        at.push(name);
        let last = i + 1 == names.len();
        let flags = match (last, access) {
            (false, _) => folder,
            // O_NONBLOCK: opening a FIFO for reading would wait for a writer.
            (true, Access::Read) => {
                OFlag::O_RDONLY | OFlag::O_NOFOLLOW | OFlag::O_CLOEXEC | OFlag::O_NONBLOCK
            }
            (true, Access::Append) => {
                OFlag::O_WRONLY | OFlag::O_APPEND | OFlag::O_NOFOLLOW | OFlag::O_CLOEXEC
            }
        };
        fd = openat(&fd, *name, flags, Mode::empty()).map_err(|e| errno(&at, e))?;
    }
    let file = File::from(fd);
    if !file.metadata()?.is_file() {
        return Err(io::Error::other(format!(
            "{}: not a regular file",
            at.display()
        )));
    }
    if matches!(access, Access::Read) {
        // Regular files ignore O_NONBLOCK, but clear it anyway: reads are meant to block.
        nix::fcntl::fcntl(&file, nix::fcntl::FcntlArg::F_SETFL(OFlag::empty()))
            .map_err(io::Error::from)?;
    }
    Ok(file)
}

/// The whole of `dir/rel`, read as [`open_in`] opens it.
pub fn read_in(dir: &Path, rel: impl AsRef<Path>) -> io::Result<Vec<u8>> {
    let mut bytes = Vec::new();
    open_in(dir, rel.as_ref(), Access::Read)?.read_to_end(&mut bytes)?;
    Ok(bytes)
}

/// [`read_in`] of a file of at most `max_bytes`: a larger one is refused, saying its size
/// and the bound, before it is read (and a file growing meanwhile is cut at the bound + 1
/// and also refused).
pub fn read_in_max(dir: &Path, rel: impl AsRef<Path>, max_bytes: u64) -> io::Result<Vec<u8>> {
    let rel = rel.as_ref();
    let file = open_in(dir, rel, Access::Read)?;
    read_max(file, &dir.join(rel), max_bytes)
}

/// The whole of an open file of at most `max_bytes` (`path` names it in the error).
pub fn read_max(file: File, path: &Path, max_bytes: u64) -> io::Result<Vec<u8>> {
    let too_big = |len: u64| {
        io::Error::new(
            io::ErrorKind::InvalidData,
            format!(
                "{}: {len} bytes, over the {max_bytes}-byte limit for this file",
                path.display()
            ),
        )
    };
    let len = file.metadata()?.len();
    if len > max_bytes {
        return Err(too_big(len));
    }
    let mut bytes = Vec::with_capacity(len as usize);
    file.take(max_bytes + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max_bytes {
        return Err(too_big(bytes.len() as u64));
    }
    Ok(bytes)
}

/// Open the file `path` for reading as [`open_in`] opens its last component: a symlink
/// there is refused, and so are a FIFO and a device (a file named on a command line,
/// whose folders are the user's to choose).
pub fn open_regular(path: &Path) -> io::Result<File> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let name = path.file_name().ok_or_else(|| {
        io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("{}: not a file name", path.display()),
        )
    })?;
    let flags = OFlag::O_RDONLY | OFlag::O_NOFOLLOW | OFlag::O_CLOEXEC | OFlag::O_NONBLOCK;
    let fd = nix::fcntl::open(&dir.join(name), flags, Mode::empty()).map_err(|e| errno(path, e))?;
    let file = File::from(fd);
    if !file.metadata()?.is_file() {
        return Err(io::Error::other(format!(
            "{}: not a regular file",
            path.display()
        )));
    }
    nix::fcntl::fcntl(&file, nix::fcntl::FcntlArg::F_SETFL(OFlag::empty()))
        .map_err(io::Error::from)?;
    Ok(file)
}

/// The whole of the file `path`, opened as [`open_regular`] opens it, at most `max_bytes`.
pub fn read_regular_max(path: &Path, max_bytes: u64) -> io::Result<Vec<u8>> {
    read_max(open_regular(path)?, path, max_bytes)
}

/// Make the folder `path` if it is not there; an existing entry must be a real folder,
/// not a symlink to one.
pub fn create_dir(path: &Path) -> io::Result<()> {
    match std::fs::create_dir(path) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {
            let ft = std::fs::symlink_metadata(path)?.file_type();
            if ft.is_symlink() {
                Err(symlink_error(path))
            } else if ft.is_dir() {
                Ok(())
            } else {
                Err(io::Error::other(format!(
                    "{}: not a folder",
                    path.display()
                )))
            }
        }
        Err(e) => Err(e),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::symlink;

    #[test]
    fn bounded_reads_refuse_large_files_fifos_devices_and_symlinks() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(d.path().join("small"), b"12345").unwrap();
        assert_eq!(read_in_max(d.path(), "small", 5).unwrap(), b"12345");
        let e = read_in_max(d.path(), "small", 4).unwrap_err().to_string();
        assert!(e.contains("5 bytes, over the 4-byte limit"), "{e}");
        assert_eq!(
            read_regular_max(&d.path().join("small"), 5).unwrap(),
            b"12345"
        );
        nix::unistd::mkfifo(&d.path().join("fifo"), Mode::S_IRWXU).unwrap();
        symlink("/dev/zero", d.path().join("zero")).unwrap();
        let fifo = read_regular_max(&d.path().join("fifo"), 100).unwrap_err();
        assert!(fifo.to_string().contains("not a regular file"), "{fifo}");
        let link = read_regular_max(&d.path().join("zero"), 100).unwrap_err();
        assert!(link.to_string().contains("symbolic link"), "{link}");
        let dev = read_regular_max(Path::new("/dev/zero"), 100).unwrap_err();
        assert!(dev.to_string().contains("not a regular file"), "{dev}");
        let e = read_in_max(d.path(), "fifo", 100).unwrap_err();
        assert!(e.to_string().contains("not a regular file"), "{e}");
    }

    #[test]
    fn reads_below_the_folder_and_refuses_every_symlink_on_the_way() {
        let d = tempfile::tempdir().unwrap();
        let outside = tempfile::tempdir().unwrap();
        std::fs::write(outside.path().join("secret.png"), b"outside").unwrap();
        let s = d.path().join("s");
        std::fs::create_dir_all(s.join("frames")).unwrap();
        std::fs::write(s.join("frames/000000.png"), b"inside").unwrap();
        assert_eq!(read_in(&s, "frames/000000.png").unwrap(), b"inside");
        // The file, a folder on the way, and the session folder itself, each a symlink.
        symlink(
            outside.path().join("secret.png"),
            s.join("frames/000001.png"),
        )
        .unwrap();
        symlink(outside.path(), s.join("images")).unwrap();
        symlink(&s, d.path().join("link")).unwrap();
        for (dir, rel) in [
            (s.clone(), "frames/000001.png"),
            (s.clone(), "images/secret.png"),
            (d.path().join("link"), "frames/000000.png"),
        ] {
            let e = read_in(&dir, rel).unwrap_err().to_string();
            assert!(
                e.contains("a symbolic link: not followed"),
                "{dir:?} {rel}: {e}"
            );
        }
        assert!(read_in(&s, "../s/frames/000000.png").is_err());
    }

    #[test]
    fn a_fifo_is_refused_without_waiting_and_appends_stay_inside() {
        let d = tempfile::tempdir().unwrap();
        let fifo = d.path().join("steps.csv");
        nix::unistd::mkfifo(&fifo, Mode::from_bits_truncate(0o600)).unwrap();
        let e = read_in(d.path(), "steps.csv").unwrap_err().to_string();
        assert!(e.contains("not a regular file"), "{e}");
        let outside = tempfile::tempdir().unwrap();
        let victim = outside.path().join("v.csv");
        std::fs::write(&victim, b"keep").unwrap();
        symlink(&victim, d.path().join("interferometer.csv")).unwrap();
        assert!(open_in(d.path(), Path::new("interferometer.csv"), Access::Append).is_err());
        assert_eq!(std::fs::read(&victim).unwrap(), b"keep");
        symlink(outside.path(), d.path().join("images")).unwrap();
        assert!(create_dir(&d.path().join("images")).is_err());
        create_dir(&d.path().join("fresh")).unwrap();
        create_dir(&d.path().join("fresh")).unwrap();
    }
}
