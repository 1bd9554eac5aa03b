//! Names of runs: the time stamp of a run directory and the short id of a pipeline run (its
//! shared memory and iceoryx2 services carry it).

/// UTC time as `YYYYMMDD-HHMMSS`, the name of a training group or design directory.
pub fn stamp() -> String {
    chrono::Utc::now().format("%Y%m%d-%H%M%S").to_string()
}

/// 8 hex digits from the clock and the process id: unique among the runs of one machine.
pub fn run_id() -> String {
    let t = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
    format!("{:08x}", (t as u64 ^ ((std::process::id() as u64) << 32)) as u32)
}

/// An exclusive advisory lock on a run directory (`<dir>/lock`), held while the value lives (and
/// its pipeline's children live) and released by the kernel when they end, however they end.
pub struct RunLock {
    _file: std::fs::File,
}

/// Lock `dir` for this process, or say which process holds it.
pub fn lock(dir: &std::path::Path) -> anyhow::Result<RunLock> {
    use std::io::{Read, Seek, Write};
    use std::os::unix::io::AsRawFd;
    let path = dir.join("lock");
    let mut f = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(|e| anyhow::anyhow!("opening {}: {e}", path.display()))?;
    // SAFETY: flock on a descriptor this function owns.
    if unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
        let mut holder = String::new();
        let _ = f.read_to_string(&mut holder);
        anyhow::bail!("{} is being trained by another lmac (pid {}); wait for it or stop it first", dir.display(), holder.trim());
    }
    let _ = f.set_len(0).and_then(|_| f.rewind()).and_then(|_| write!(f, "{}", std::process::id()));
    // The pipeline's children inherit the descriptor (no close-on-exec), so the lock lasts until
    // every process of the run is gone: a killed parent's trainer may still be writing its last
    // checkpoint, and a resume must not start meanwhile.
    // SAFETY: fcntl on a descriptor this function owns.
    unsafe { libc::fcntl(f.as_raw_fd(), libc::F_SETFD, 0) };
    Ok(RunLock { _file: f })
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_stamp_is_a_sortable_utc_time() {
        let s = super::stamp();
        assert_eq!(s.len(), 15, "{s}");
        assert_eq!(&s[8..9], "-");
        assert!(s[..8].chars().chain(s[9..].chars()).all(|c| c.is_ascii_digit()), "{s}");
        assert!(s.as_str() > "20260101-000000");
    }

    #[test]
    fn a_run_directory_is_trained_by_one_lmac_at_a_time() {
        let dir = std::env::temp_dir().join(format!("lmac-lock-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let held = super::lock(&dir).unwrap();
        // flock locks belong to open files: a second open in this process conflicts too.
        let err = super::lock(&dir).err().expect("locked").to_string();
        assert!(err.contains("being trained by another lmac") && err.contains(&std::process::id().to_string()), "{err}");
        drop(held);
        assert!(super::lock(&dir).is_ok(), "released with its holder");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
