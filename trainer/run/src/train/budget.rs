//! How a run's step budget splits into updates and test episodes, and when the periodic events
//! (test phases, metric rows, checkpoints) fall due.
//!
//! The defaults were made for 25-50-step episodes (LBF, SMAC). With 500-step episodes the same
//! `run.updates_per_episode` gives twenty times fewer updates, and the same number of test
//! episodes costs twenty times more steps; `warnings` says so before a run spends hours on it.

use super::config::TrainConfig;

/// Below this many updates a value-based learner has barely started (QMIX's target network is
/// copied every 200 episodes by default; pymarl's runs make tens of thousands of updates).
pub const FEW_UPDATES: f64 = 1000.0;
/// Above this fraction of the run's own steps, test phases and the final evaluation cost more
/// than they are worth as a budget nobody asked for.
pub const TEST_SHARE: f64 = 0.25;

/// The first multiple of `interval` after `t`: events fall on a fixed grid (10k, 20k, ...)
/// whatever the episode lengths, even when one episode spans several intervals.
pub fn next_multiple(t: u64, interval: u64) -> u64 {
    (t / interval + 1) * interval
}

/// Warnings for a run of `cfg` on episodes of at most `episode_limit` steps.
pub fn warnings(cfg: &TrainConfig, episode_limit: usize) -> Vec<String> {
    let r = &cfg.run;
    let limit = episode_limit.max(1) as f64;
    let mut out = Vec::new();
    // Episodes that run to the limit: the fewest episodes, so the fewest updates.
    let updates = r.steps as f64 / limit * r.updates_per_episode;
    if updates < FEW_UPDATES {
        let fit = FEW_UPDATES * limit / r.steps.max(1) as f64;
        out.push(format!(
            "run.steps / episode_limit x run.updates_per_episode = {} / {episode_limit} x {} = {updates:.0} updates \
             if episodes run to their limit (fewer than {FEW_UPDATES}); for episodes this long raise \
             run.updates_per_episode (to {fit:.2} for {FEW_UPDATES}) or run.steps",
            r.steps, r.updates_per_episode
        ));
    }
    let phases = (r.steps / r.test_interval.max(1) + 1) as f64;
    let final_eval = r.final_eval_episodes.unwrap_or(10 * r.test_episodes) as f64;
    let test_steps = (phases * r.test_episodes as f64 + final_eval) * limit;
    if test_steps > TEST_SHARE * r.steps as f64 {
        out.push(format!(
            "test phases ({phases:.0} x run.test_episodes = {}) and the final evaluation ({final_eval:.0} episodes) may take \
             {test_steps:.0} env steps of {episode_limit}, {:.0}% of run.steps = {}; raise run.test_interval or lower \
             run.test_episodes / run.final_eval_episodes",
            r.test_episodes,
            100.0 * test_steps / r.steps.max(1) as f64,
            r.steps
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_stay_on_their_grid_when_an_episode_spans_intervals() {
        assert_eq!(next_multiple(0, 1000), 1000);
        assert_eq!(next_multiple(999, 1000), 1000);
        assert_eq!(next_multiple(1000, 1000), 2000);
        assert_eq!(next_multiple(3500, 1000), 4000, "not 2000: no burst of catch-up events");
    }

    #[test]
    fn long_episodes_with_the_defaults_warn_and_short_ones_do_not() {
        let mut cfg = TrainConfig::resolve(None, &[]).unwrap();
        cfg.run.steps = 200_000;
        let w = warnings(&cfg, 500);
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(w[0].contains("= 400 updates"), "{}", w[0]);
        assert!(w[1].contains("% of run.steps"), "{}", w[1]);
        cfg.run.steps = 2_000_000;
        assert!(warnings(&cfg, 25).is_empty(), "LBF's settings fit LBF");
    }
}
