//! What the end-to-end tests share: the `lmac` binary, waiting with a deadline, and the lmac
//! slabs in /dev/shm.

use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

/// The workspace root.
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_path_buf()
}

/// The release `lmac` built by `scripts/setup.sh` (or `$LMAC_BIN`), run from the workspace root.
pub fn lmac() -> Command {
    let bin = std::env::var("LMAC_BIN").map(PathBuf::from).unwrap_or_else(|_| root().join("target/release/lmac"));
    assert!(bin.exists(), "{} not found: run scripts/setup.sh (it builds the release binary) or set LMAC_BIN", bin.display());
    let mut c = Command::new(bin);
    c.current_dir(root());
    c
}

/// Poll `f` every 20 ms until it gives a value or `timeout` passes.
pub fn wait_for<T>(timeout: Duration, mut f: impl FnMut() -> Option<T>) -> Option<T> {
    let t0 = Instant::now();
    while t0.elapsed() < timeout {
        if let Some(v) = f() {
            return Some(v);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    None
}

/// The lmac slabs (`lmac-<run>-s<i>`) in /dev/shm.
pub fn lmac_shm_files() -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir("/dev/shm")
        .expect("/dev/shm")
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.starts_with("lmac-"))
        .collect();
    v.sort();
    v
}
