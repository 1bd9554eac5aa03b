//! A resumed run trains on with the settings its checkpoint was trained with: the run's whole
//! configuration is kept in every checkpoint, and a resume compares `config.toml` with it before
//! any process starts. Settings that only say how long to run, how often to test, log or save,
//! may change; any other difference refuses the resume with the list, unless the user allows it.

use super::config::TrainConfig;
use std::collections::BTreeMap;

/// Settings a resume may change without changing what is trained: the step target and the
/// cadence (and size) of tests, logs, checkpoints and the final evaluation. `[build]` is
/// compared separately (a warning: the same settings may still train the same way).
const FREE_TO_CHANGE: &[&str] =
    &["run.steps", "run.test_interval", "run.test_episodes", "run.log_interval", "run.checkpoint_interval", "run.final_eval_episodes"];

/// The differences between the configuration a checkpoint recorded (`recorded`, TOML text) and
/// the run's configuration now, one line per setting (`learn.lr: 0.0005 -> 0.001`), settings
/// free to change left out. Recorded text that does not parse is one difference saying so.
pub fn config_changes(recorded: &str, now: &TrainConfig) -> Vec<String> {
    let Ok(raw) = recorded.parse::<toml::Table>() else {
        return vec!["the checkpoint's recorded configuration is not TOML".into()];
    };
    // Read through today's settings, so a setting added since (with its default) is no change.
    let old = match toml::from_str::<TrainConfig>(recorded) {
        Ok(c) => toml::Value::try_from(c).expect("a TrainConfig serializes"),
        Err(_) => toml::Value::Table(raw),
    };
    let new = toml::Value::try_from(now).expect("a TrainConfig serializes");
    let (mut a, mut b) = (BTreeMap::new(), BTreeMap::new());
    flatten("", &old, &mut a);
    flatten("", &new, &mut b);
    let keys: std::collections::BTreeSet<&String> = a.keys().chain(b.keys()).collect();
    keys.into_iter()
        .filter(|k| !FREE_TO_CHANGE.contains(&k.as_str()) && !k.starts_with("build."))
        .filter_map(|k| {
            let (x, y) = (a.get(k), b.get(k));
            (x != y).then(|| format!("{k}: {} -> {}", x.map_or("(not set)", String::as_str), y.map_or("(not set)", String::as_str)))
        })
        .collect()
}

/// Every leaf setting of `v` by its dotted path.
fn flatten(prefix: &str, v: &toml::Value, out: &mut BTreeMap<String, String>) {
    match v {
        toml::Value::Table(t) => {
            for (k, x) in t {
                let key = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                flatten(&key, x, out);
            }
        }
        other => {
            out.insert(prefix.to_string(), other.to_string());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(sets: &[&str]) -> TrainConfig {
        let mut o: Vec<String> = vec!["run.env=\"lbf:8x8-2p-2f-s1-coop\"".into(), "run.algo=\"qmix\"".into()];
        o.extend(sets.iter().map(|s| s.to_string()));
        TrainConfig::resolve(None, &o).unwrap()
    }

    #[test]
    fn a_changed_setting_is_listed_and_the_step_target_is_free() {
        let base = config(&[]);
        let recorded = toml::to_string_pretty(&base).unwrap();
        assert!(config_changes(&recorded, &base).is_empty());
        assert!(config_changes(&recorded, &config(&["run.steps=5000000", "run.test_interval=20000"])).is_empty());
        let changed = config_changes(&recorded, &config(&["run.algo=\"vdn\"", "learn.lr=0.01"]));
        assert_eq!(changed.len(), 2, "{changed:?}");
        assert!(changed.iter().any(|c| c.starts_with("run.algo: \"qmix\" -> \"vdn\"")), "{changed:?}");
        assert!(changed.iter().any(|c| c.starts_with("learn.lr: ")), "{changed:?}");
        assert_eq!(config_changes("{not toml", &base), vec!["the checkpoint's recorded configuration is not TOML".to_string()]);
    }
}
