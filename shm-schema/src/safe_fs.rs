//! Files in shared places: a private scratch directory under the system's temp directory, files
//! created without following symlinks, and bounded reads of regular files.
//!
//! Anything lmac writes outside a directory the user chose goes into a [`PrivateDir`]: a fresh
//! 0700 directory made by one `mkdir` (which fails on any existing name, a symlink included),
//! so another local user can neither predict a file in it nor plant a link there. Files that
//! must not exist yet are created with [`write_new`] (`O_CREAT | O_EXCL | O_NOFOLLOW`), so a
//! link planted where the file would go is refused instead of written through; files appended
//! to or locked are opened with `O_NOFOLLOW` ([`open_append`], [`open_lock`]).
//!
//! Every file lmac reads from outside (configs, protocols, checkpoints, datasets) is read with
//! [`read_capped`]: it must be a regular file (a FIFO, device or directory is refused without
//! blocking on it) no larger than a cap the error names, so `/dev/zero` linked in as a file
//! cannot exhaust memory and a FIFO cannot hang the reader.

use std::io::Write;
use std::os::unix::fs::{DirBuilderExt, OpenOptionsExt};
use std::path::{Path, PathBuf};

/// Take an exclusive advisory lock (`flock`) on `f`: wait for it (`wait`), or fail at once with
/// `WouldBlock` when another open file holds it. flock locks belong to the open file, so a second
/// open in the same process conflicts too; the lock ends when every descriptor of `f` is closed
/// (also when the process dies). Not `File::lock`: the workspace's rust-version is 1.85.
pub fn lock_exclusive(f: &std::fs::File, wait: bool) -> std::io::Result<()> {
    use std::os::unix::io::AsRawFd;
    let op = if wait { libc::LOCK_EX } else { libc::LOCK_EX | libc::LOCK_NB };
    // SAFETY: flock on a descriptor the caller's File owns for the duration of the call.
    match unsafe { libc::flock(f.as_raw_fd(), op) } {
        0 => Ok(()),
        _ => Err(std::io::Error::last_os_error()),
    }
}

/// A directory only this user can enter, fresh under the system's temp directory, removed
/// (with what is in it) when the value is dropped.
#[derive(Debug)]
pub struct PrivateDir {
    path: PathBuf,
}

impl PrivateDir {
    /// Make `<temp>/lmac-<tag>-<pid>-<random>` with mode 0700. A name that exists (planted or
    /// left over) is never reused: another random name is tried.
    pub fn new(tag: &str) -> std::io::Result<PrivateDir> {
        Self::new_in(&std::env::temp_dir(), tag)
    }

    /// The same under `parent`.
    pub fn new_in(parent: &Path, tag: &str) -> std::io::Result<PrivateDir> {
        let mut last = None;
        for _ in 0..16 {
            let path = parent.join(format!("lmac-{tag}-{}-{:016x}", std::process::id(), rand::random::<u64>()));
            match std::fs::DirBuilder::new().mode(0o700).create(&path) {
                Ok(()) => return Ok(PrivateDir { path }),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => last = Some(e),
                Err(e) => return Err(std::io::Error::new(e.kind(), format!("creating {}: {e}", path.display()))),
            }
        }
        Err(last.unwrap_or_else(|| std::io::Error::other("no name was free")))
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for PrivateDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

/// Create `path`, which must not exist (not even as a dangling symlink), and write `bytes` to
/// it. Errors name the file.
pub fn write_new(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .mode(0o600)
        .open(path)
        .map_err(|e| named(path, e))?;
    f.write_all(bytes).map_err(|e| named(path, e))
}

/// Write `bytes` to `path` atomically: into `<path>.tmp` (created fresh, a stale one or a link
/// in its place removed first, never followed), then renamed over `path`.
pub fn write_replace(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    // remove_file removes a symlink itself, not what it points to.
    match std::fs::remove_file(&tmp) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(std::io::Error::new(e.kind(), format!("{}: {e}", tmp.display()))),
        _ => {}
    }
    write_new(&tmp, bytes)?;
    std::fs::rename(&tmp, path).map_err(|e| std::io::Error::new(e.kind(), format!("renaming {} to {}: {e}", tmp.display(), path.display())))
}

/// Open `path` for appending, creating it when missing; a symlink in its place is
/// refused (`O_NOFOLLOW`) instead of written through. Errors name the file.
pub fn open_append(path: &Path) -> std::io::Result<std::fs::File> {
    let f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_CLOEXEC)
        .open(path)
        .map_err(|e| named(path, e))?;
    regular(path, f).map(|(f, _)| f)
}

/// `f` and its metadata if it is a regular file (opened non-blocking, a FIFO or device in its
/// place did not block the open; reading or writing one is refused here).
fn regular(path: &Path, f: std::fs::File) -> std::io::Result<(std::fs::File, std::fs::Metadata)> {
    let meta = f.metadata().map_err(|e| at(path, e))?;
    if !meta.is_file() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("{}: is {}, not a regular file; lmac reads and writes only regular files", path.display(), describe(&meta.file_type())),
        ));
    }
    Ok((f, meta))
}

/// Open `path` read-write for a lock file (created when missing, never truncated by the
/// open); a symlink in its place is refused. Errors name the file.
pub fn open_lock(path: &Path) -> std::io::Result<std::fs::File> {
    let f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_CLOEXEC)
        .open(path)
        .map_err(|e| named(path, e))?;
    regular(path, f).map(|(f, _)| f)
}

/// `e` with the path it happened at.
fn at(path: &Path, e: std::io::Error) -> std::io::Error {
    std::io::Error::new(e.kind(), format!("{}: {e}", path.display()))
}

/// [`at`], saying plainly when the open refused a symlink (`O_NOFOLLOW`).
fn named(path: &Path, e: std::io::Error) -> std::io::Error {
    let why =
        if e.raw_os_error() == Some(libc::ELOOP) { "is a symlink, which lmac does not write through".to_string() } else { e.to_string() };
    std::io::Error::new(e.kind(), format!("{}: {why}", path.display()))
}

/// Size caps of the files lmac reads, named in the errors.
pub const MIB: u64 = 1 << 20;
/// Configuration, protocol, design, metrics and JSON files a person, an LLM or a run writes.
pub const TEXT_CAP: u64 = 64 * MIB;
/// Checkpoint weights, replay buffers and design datasets.
pub const DATA_CAP: u64 = 16 << 30;

/// Open `path` for reading, refusing anything but a regular file (see [`read_capped`]).
pub fn open_regular(path: &Path) -> std::io::Result<std::fs::File> {
    open_regular_meta(path).map(|(f, _)| f)
}

fn open_regular_meta(path: &Path) -> std::io::Result<(std::fs::File, std::fs::Metadata)> {
    let f = std::fs::OpenOptions::new().read(true).custom_flags(libc::O_NONBLOCK | libc::O_CLOEXEC).open(path).map_err(|e| at(path, e))?;
    regular(path, f)
}

/// Read the whole of `path`, which must be a regular file of at most `cap` bytes. It is opened
/// non-blocking, so a FIFO is refused instead of waiting for a writer; a device (`/dev/zero`),
/// directory or socket is refused; a file over the cap (or growing past it while read) is an
/// error naming the cap. Symlinks are followed: what they point at is checked.
pub fn read_capped(path: &Path, cap: u64) -> std::io::Result<Vec<u8>> {
    use std::io::Read;
    let invalid = |why: String| std::io::Error::new(std::io::ErrorKind::InvalidInput, format!("{}: {why}", path.display()));
    let (f, meta) = open_regular_meta(path)?;
    if meta.len() > cap {
        return Err(invalid(format!("is {} bytes, more than the {} lmac reads from such a file", meta.len(), bytes_text(cap))));
    }
    let mut out = Vec::with_capacity(meta.len() as usize);
    f.take(cap + 1).read_to_end(&mut out).map_err(|e| at(path, e))?;
    if out.len() as u64 > cap {
        return Err(invalid(format!("grew past the {} lmac reads from such a file while it was read", bytes_text(cap))));
    }
    Ok(out)
}

/// [`read_capped`] as UTF-8 text.
pub fn read_text_capped(path: &Path, cap: u64) -> std::io::Result<String> {
    String::from_utf8(read_capped(path, cap)?)
        .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, format!("{}: not UTF-8 text ({e})", path.display())))
}

fn describe(t: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if t.is_dir() {
        "a directory"
    } else if t.is_fifo() {
        "a FIFO"
    } else if t.is_char_device() || t.is_block_device() {
        "a device"
    } else if t.is_socket() {
        "a socket"
    } else {
        "not a regular file"
    }
}

fn bytes_text(n: u64) -> String {
    if n >= MIB && n % MIB == 0 {
        format!("{} MiB", n / MIB)
    } else {
        format!("{n} bytes")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_private_dir_is_fresh_0700_and_removed_with_its_value() {
        use std::os::unix::fs::PermissionsExt;
        let d = PrivateDir::new("safe-fs-test").unwrap();
        let p = d.path().to_path_buf();
        assert_eq!(std::fs::symlink_metadata(&p).unwrap().permissions().mode() & 0o777, 0o700);
        std::fs::write(p.join("x"), b"1").unwrap();
        drop(d);
        assert!(!p.exists());
    }

    #[test]
    fn write_new_never_follows_a_planted_link() {
        let d = PrivateDir::new("safe-fs-link").unwrap();
        let victim = d.path().join("victim");
        std::fs::write(&victim, b"keep").unwrap();
        let link = d.path().join("report.json.tmp");
        std::os::unix::fs::symlink(&victim, &link).unwrap();
        let e = write_new(&link, b"evil").unwrap_err();
        assert!(e.to_string().contains("report.json.tmp"), "{e}");
        // write_replace removes the link (not its target) and writes a file of its own.
        write_replace(&d.path().join("report.json"), b"mine").unwrap();
        assert_eq!(std::fs::read(&victim).unwrap(), b"keep");
        assert_eq!(std::fs::read(d.path().join("report.json")).unwrap(), b"mine");
        // Appending and locking refuse the link too, leaving its target alone.
        let log = d.path().join("metrics.csv");
        std::os::unix::fs::symlink(&victim, &log).unwrap();
        assert!(open_append(&log).unwrap_err().to_string().contains("is a symlink"));
        assert!(open_lock(&log).unwrap_err().to_string().contains("is a symlink"));
        assert_eq!(std::fs::read(&victim).unwrap(), b"keep");
    }

    #[test]
    fn reads_are_capped_and_refuse_fifos_and_devices_without_blocking() {
        let d = PrivateDir::new("safe-fs-read").unwrap();
        let ok = d.path().join("config.toml");
        std::fs::write(&ok, b"a = 1").unwrap();
        assert_eq!(read_capped(&ok, 5).unwrap(), b"a = 1");
        let e = read_capped(&ok, 4).unwrap_err().to_string();
        assert!(e.contains("config.toml") && e.contains("5 bytes, more than the 4 bytes"), "{e}");
        // /dev/zero linked in as a file: refused at once, nothing read.
        let zero = d.path().join("net.bpk");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        assert!(read_capped(&zero, TEXT_CAP).unwrap_err().to_string().contains("is a device, not a regular file"));
        // A FIFO with no writer: refused, not waited on.
        let fifo = d.path().join("protocol.json");
        let c = std::ffi::CString::new(fifo.as_os_str().as_encoded_bytes()).unwrap();
        // SAFETY: mkfifo with a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        assert!(read_capped(&fifo, TEXT_CAP).unwrap_err().to_string().contains("is a FIFO"));
        assert!(read_capped(d.path(), TEXT_CAP).unwrap_err().to_string().contains("is a directory"));
        assert_eq!(bytes_text(64 * MIB), "64 MiB");
    }
}
