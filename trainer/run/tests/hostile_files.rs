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
