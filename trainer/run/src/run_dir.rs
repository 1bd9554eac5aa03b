//! Names of runs: the time stamp of a run directory and the short id of a pipeline run (its
//! shared memory and iceoryx2 services carry it).

/// UTC time as `YYYYMMDD-HHMMSS`, the name of a training group or design directory (made with
/// [`create_unique_dir`]: two launches in the same second get two directories).
/// `$LMAC_STAMP` fixes it, so tests can make launches collide.
pub fn stamp() -> String {
    match std::env::var("LMAC_STAMP") {
        Ok(s) if !s.is_empty() => s,
        _ => chrono::Utc::now().format("%Y%m%d-%H%M%S").to_string(),
    }
}

/// Create `parent/name`, or `parent/name-2`, `-3`, ... when taken: each `mkdir` fails if the
/// name exists, so two processes racing for the same name get different directories, and a
/// directory another process made is never reused. Returns the directory made.
pub fn create_unique_dir(parent: &std::path::Path, name: &str) -> anyhow::Result<std::path::PathBuf> {
    std::fs::create_dir_all(parent).map_err(|e| anyhow::anyhow!("creating {}: {e}", parent.display()))?;
    for n in 1..10_000u32 {
        let d = if n == 1 { parent.join(name) } else { parent.join(format!("{name}-{n}")) };
        match std::fs::create_dir(&d) {
            Ok(()) => return Ok(d),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => anyhow::bail!("creating {}: {e}", d.display()),
        }
    }
    anyhow::bail!("creating a directory in {}: {name} and 9999 suffixed names are taken", parent.display())
}

/// The folder name of an environment's runs and designs: its name with ':' and any character
/// other than letters, digits, '.', '_' and '-' as '_' (`pz:mpe2.simple_spread_v3,N=4` ->
/// `pz_mpe2.simple_spread_v3_N_4`), so a name's commas and '=' never reach a path that
/// `--variant` or `--protocol` must parse.
pub fn env_dir_name(env: &str) -> String {
    env.chars().map(|c| if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') { c } else { '_' }).collect()
}

/// 12 hex digits, unique among the live runs of one machine: the process id (live processes
/// have distinct ones) and 20 random bits (a pid reused after a crash, or two runs of one
/// process). Short, because it is part of shared-memory and iceoryx2 names.
pub fn run_id() -> String {
    format!("{:07x}{:05x}", std::process::id() & 0xfff_ffff, rand::random::<u32>() & 0xf_ffff)
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
    // Never through a symlink planted in a run directory someone else made (copied, untarred).
    let mut f = crate::safe_fs::open_lock(&path).map_err(|e| anyhow::anyhow!("opening the run's lock: {e}"))?;
    if crate::safe_fs::lock_exclusive(&f, false).is_err() {
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
    fn an_env_names_folder_has_no_commas_or_equals() {
        use super::env_dir_name;
        assert_eq!(env_dir_name("smaclite:1o_10b_vs_1r"), "smaclite_1o_10b_vs_1r");
        assert_eq!(env_dir_name("pz:mpe2.simple_spread_v3,N=4,team_reward=mean"), "pz_mpe2.simple_spread_v3_N_4_team_reward_mean");
        assert_eq!(env_dir_name("lbf:8x8-2p-2f-s1-coop"), "lbf_8x8-2p-2f-s1-coop");
    }

    #[test]
    fn a_stamp_is_a_sortable_utc_time() {
        let s = super::stamp();
        assert_eq!(s.len(), 15, "{s}");
        assert_eq!(&s[8..9], "-");
        assert!(s[..8].chars().chain(s[9..].chars()).all(|c| c.is_ascii_digit()), "{s}");
        assert!(s.as_str() > "20260101-000000");
    }

    #[test]
    fn run_ids_carry_the_pid_and_do_not_repeat() {
        let a = super::run_id();
        assert_eq!(a.len(), 12, "{a}");
        assert_eq!(u32::from_str_radix(&a[..7], 16).unwrap(), std::process::id() & 0xfff_ffff, "{a}");
        let ids: std::collections::HashSet<String> = (0..64).map(|_| super::run_id()).collect();
        assert!(ids.len() > 60, "ids of one process differ by their random bits: {ids:?}");
    }

    #[test]
    fn a_taken_name_gets_a_suffix_never_the_same_directory() {
        let parent = std::env::temp_dir().join(format!("lmac-unique-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&parent);
        let a = super::create_unique_dir(&parent, "20260101-000000").unwrap();
        let b = super::create_unique_dir(&parent, "20260101-000000").unwrap();
        assert_eq!(a, parent.join("20260101-000000"));
        assert_eq!(b, parent.join("20260101-000000-2"));
        let _ = std::fs::remove_dir_all(&parent);
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
