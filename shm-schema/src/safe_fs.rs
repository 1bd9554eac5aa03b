//! Files in shared places: a private scratch directory under the system's temp directory, and
//! files created without following symlinks.
//!
//! Anything lmac writes outside a directory the user chose goes into a [`PrivateDir`]: a fresh
//! 0700 directory made by one `mkdir` (which fails on any existing name, a symlink included),
//! so another local user can neither predict a file in it nor plant a link there. Files that
//! must not exist yet are created with [`write_new`] (`O_CREAT | O_EXCL | O_NOFOLLOW`), so a
//! link planted where the file would go is refused instead of written through.

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
    let named = |e: std::io::Error| std::io::Error::new(e.kind(), format!("{}: {e}", path.display()));
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_CLOEXEC)
        .mode(0o600)
        .open(path)
        .map_err(named)?;
    f.write_all(bytes).map_err(named)
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
    }
}
