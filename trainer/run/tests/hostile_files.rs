//! Hostile dataset files: header numbers that disagree with the payload, counts whose products
//! overflow or would allocate far more than the file holds. Each is an error naming the file and
//! the field, never a panic or a giant allocation. (The random version of this is the dataset
//! parser of `lmac-fuzz` in the tests crate.)

use lmac_run::dataset::{Dataset, DatasetHeader, Trajectory};
use std::path::{Path, PathBuf};

fn tmp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lmac-hostile-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn small() -> Dataset {
    let header = DatasetHeader {
        env: "test:tiny".into(),
        n_agents: 2,
        obs_dim: 3,
        state_dim: 4,
        n_actions: 5,
        episode_limit: 10,
        protocol: "none".into(),
        policy: "test".into(),
        seed: 1,
    };
    let ep = |len: usize| Trajectory {
        len,
        obs: vec![0.5; len * 6],
        state: vec![1.0; len * 4],
        actions: vec![1; len * 2],
        reward: vec![0.0; len],
        terminated: true,
        truncated: false,
    };
    Dataset { header, episodes: vec![ep(3), ep(2)] }
}

/// Load after rewriting one header field; the error text.
fn load_with(dir: &Path, field: &str, value: serde_json::Value) -> String {
    let hp = dir.join("header.json");
    let mut h: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&hp).unwrap()).unwrap();
    let keep = h.clone();
    h[field] = value;
    std::fs::write(&hp, h.to_string()).unwrap();
    let e = format!("{:#}", Dataset::load(dir).unwrap_err());
    std::fs::write(&hp, keep.to_string()).unwrap();
    e
}

#[test]
fn hostile_dataset_headers_are_errors_naming_file_and_field() {
    let dir = tmp_dir("header").join("data");
    let data = small();
    data.save(&dir).unwrap();
    assert_eq!(Dataset::load(&dir).unwrap(), data);
    let cases: [(&str, serde_json::Value, &str); 8] = [
        // Would have been Vec::with_capacity(2^64 - 1): a capacity overflow panic.
        ("episodes", serde_json::json!(u64::MAX), "episodes"),
        ("episodes", serde_json::json!(1_000_000), "cannot fit"),
        ("episodes", serde_json::json!(-1), "episodes"),
        ("n_agents", serde_json::json!(u64::MAX), "n_agents"),
        // n_agents * obs_dim overflowed usize before.
        ("obs_dim", serde_json::json!(1u64 << 40), "obs_dim"),
        ("state_dim", serde_json::json!(1u64 << 19), "truncated in episode 0"),
        ("episode_limit", serde_json::json!(2), "episode_limit"),
        ("steps", serde_json::json!(6), "steps"),
    ];
    for (field, value, want) in cases {
        let e = load_with(&dir, field, value.clone());
        assert!(e.contains(want), "{field} = {value}: {e}");
        assert!(e.contains("header.json") || e.contains("episodes.bin"), "{field} = {value}: {e}");
    }
}

#[test]
fn hostile_dataset_payloads_are_errors() {
    let dir = tmp_dir("payload").join("data");
    small().save(&dir).unwrap();
    let bin = dir.join("episodes.bin");
    let good = std::fs::read(&bin).unwrap();
    // An episode length far beyond the file (u32::MAX steps) with a large limit in the header.
    let hp = dir.join("header.json");
    // The payload's own checks, as for a dataset written before its checksum was recorded (the
    // checksum would refuse each of these first: see the test below).
    let mut h: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&hp).unwrap()).unwrap();
    h.as_object_mut().unwrap().remove("episodes_crc32c");
    h.as_object_mut().unwrap().remove("episodes_bytes");
    let header = h.to_string();
    std::fs::write(&hp, &header).unwrap();
    h["episode_limit"] = serde_json::json!(u64::MAX);
    std::fs::write(&hp, h.to_string()).unwrap();
    let mut bad = good.clone();
    bad[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
    std::fs::write(&bin, &bad).unwrap();
    let e = format!("{:#}", Dataset::load(&dir).unwrap_err());
    assert!(e.contains("episodes.bin") && e.contains("truncated in episode 0"), "{e}");
    std::fs::write(&hp, header).unwrap();
    // Every truncation point is an error, none a panic.
    for cut in 0..good.len() {
        std::fs::write(&bin, &good[..cut]).unwrap();
        let e = format!("{:#}", Dataset::load(&dir).unwrap_err());
        assert!(e.contains("episodes.bin"), "cut at {cut}: {e}");
    }
}

/// A dataset records its payload's size and CRC-32C: flipped bytes, an action out of range and
/// a payload that is a link to a device are refused naming the file (before, flipped bytes and
/// actions of 1e9 loaded silently and a link to /dev/zero was read until memory ran out).
#[test]
fn corrupt_dataset_payloads_are_refused_by_their_checksum() {
    let dir = tmp_dir("crc").join("data");
    small().save(&dir).unwrap();
    let bin = dir.join("episodes.bin");
    let good = std::fs::read(&bin).unwrap();
    let h: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("header.json")).unwrap()).unwrap();
    assert_eq!(h["episodes_bytes"].as_u64(), Some(good.len() as u64));
    let mut flipped = good.clone();
    let last = flipped.len() - 1;
    flipped[last] ^= 0x40;
    std::fs::write(&bin, &flipped).unwrap();
    let e = format!("{:#}", Dataset::load(&dir).unwrap_err());
    assert!(e.contains("episodes.bin") && e.contains("CRC-32C"), "{e}");
    std::fs::write(&bin, &good[..good.len() - 4]).unwrap();
    let e = format!("{:#}", Dataset::load(&dir).unwrap_err());
    assert!(e.contains("episodes.bin") && e.contains("episodes_bytes"), "{e}");
    std::fs::remove_file(&bin).unwrap();
    std::os::unix::fs::symlink("/dev/zero", &bin).unwrap();
    let e = format!("{:#}", Dataset::load(&dir).unwrap_err());
    assert!(e.contains("episodes.bin") && e.contains("not a regular file"), "{e}");
    // An action out of range, in a dataset whose checksum matches it.
    let mut data = small();
    data.episodes[0].actions[0] = 1_000_000_000;
    data.save(&dir).unwrap();
    let e = format!("{:#}", Dataset::load(&dir).unwrap_err());
    assert!(e.contains("episodes.bin") && e.contains("action 1000000000"), "{e}");
}

#[test]
fn config_override_values_cannot_smuggle_in_other_keys() {
    use lmac_run::train::TrainConfig;
    // One TOML value: taken as it is.
    let cfg = TrainConfig::resolve(None, &["run.steps=1234".to_string()]).unwrap();
    assert_eq!(cfg.run.steps, 1234);
    // A value followed by another key is not a value: it stays text, and text is no step count.
    let e = format!("{:#}", TrainConfig::resolve(None, &["run.steps=1\nenvs = 0".to_string()]).unwrap_err());
    assert!(e.contains("config") && e.contains("steps"), "{e}");
    for bad in ["run.steps.deeper=1", "=1", "run.steps"] {
        assert!(TrainConfig::resolve(None, &[bad.to_string()]).is_err(), "{bad}");
    }
}

fn mkfifo(p: &Path) {
    let c = std::ffi::CString::new(p.as_os_str().as_encoded_bytes()).unwrap();
    // SAFETY: mkfifo with a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
}

/// `f` on another thread, which must return within 10 s (a read blocked on a FIFO never would).
fn within_10s<T: Send + 'static>(what: &str, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(std::time::Duration::from_secs(10)).unwrap_or_else(|_| panic!("{what}: still blocked after 10 s"))
}

/// Every file lmac reads from outside is a regular file read with a cap: a config, a run's
/// `config.toml` or a dataset header that is `/dev/zero` (linked in) or a FIFO is refused at once,
/// naming the file and what it is, never read until memory runs out or waited on forever.
#[test]
fn devices_and_fifos_in_place_of_files_are_refused_without_reading_or_blocking() {
    use lmac_run::train::TrainConfig;
    let dir = tmp_dir("devices");
    let zero = dir.join("zero.toml");
    std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
    let fifo = dir.join("fifo.toml");
    mkfifo(&fifo);
    for (p, kind) in [(zero.clone(), "a device"), (fifo.clone(), "a FIFO")] {
        let q = p.clone();
        let e = within_10s("--config", move || format!("{:#}", TrainConfig::resolve(Some(&q), &[]).unwrap_err()));
        assert!(e.contains(&p.display().to_string()) && e.contains(kind), "{e}");
    }
    // A run directory's config.toml, and a dataset's header.json.
    let run = dir.join("run");
    std::fs::create_dir(&run).unwrap();
    mkfifo(&run.join("config.toml"));
    let r = run.clone();
    let e = within_10s("config.toml", move || format!("{:#}", TrainConfig::load(&r).unwrap_err()));
    assert!(e.contains("config.toml") && e.contains("a FIFO"), "{e}");
    let data = dir.join("data");
    std::fs::create_dir(&data).unwrap();
    std::os::unix::fs::symlink("/dev/zero", data.join("header.json")).unwrap();
    let e = format!("{:#}", Dataset::load(&data).unwrap_err());
    assert!(e.contains("header.json") && e.contains("a device"), "{e}");
    // A file over its cap is refused naming the cap (a sparse 65 MiB config).
    let big = dir.join("big.toml");
    std::fs::File::create(&big).unwrap().set_len(65 << 20).unwrap();
    let e = format!("{:#}", TrainConfig::resolve(Some(&big), &[]).unwrap_err());
    assert!(e.contains("more than the 64 MiB"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Writes inside a run directory never go through a link planted there: the lock and the
/// metrics are refused, leaving the link's target as it was.
#[test]
fn planted_links_in_a_run_directory_are_not_written_through() {
    let dir = tmp_dir("run-links");
    let victim = dir.join("victim");
    std::fs::write(&victim, b"keep\n").unwrap();
    let run = dir.join("run");
    std::fs::create_dir(&run).unwrap();
    std::os::unix::fs::symlink(&victim, run.join("lock")).unwrap();
    let e = format!("{:#}", lmac_run::run_dir::lock(&run).err().expect("a linked lock is refused"));
    assert!(e.contains("lock") && e.contains("symlink"), "{e}");
    std::fs::remove_file(run.join("lock")).unwrap();
    std::os::unix::fs::symlink(&victim, run.join("metrics.csv")).unwrap();
    let e = format!("{:#}", lmac_run::train::Metrics::open(&run, 0, &[]).err().expect("linked metrics are refused"));
    assert!(e.contains("metrics.csv") && e.contains("symlink"), "{e}");
    assert_eq!(std::fs::read(&victim).unwrap(), b"keep\n");
    let _ = std::fs::remove_dir_all(&dir);
}
