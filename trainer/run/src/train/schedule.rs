//! The update schedule: how many updates the learner owes after a given number of episodes
//! (fresh, or resumed with or without its replay buffer). The actor paces itself by it and the
//! learner thread trains up to it, so both read the one rule here.

/// When the learner owes updates, as a function of the episodes collected so far: none until
/// `first_episode` (the buffer must hold a batch first), then `ratio` per episode, counting
/// the episode that completes the batch (pymarl trains right after inserting it).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UpdateSchedule {
    pub ratio: f64,
    pub first_episode: u64,
    pub updates_before: u64,
}

impl UpdateSchedule {
    /// For a learner that has added `episodes`, done `updates` and holds `buffered` episodes:
    /// a fresh run owes its first update at episode `batch_size`; a run resumed without its
    /// buffer refills `batch_size` episodes first; one resumed with it goes on at once.
    pub fn new(ratio: f64, batch_size: usize, episodes: u64, updates: u64, buffered: usize) -> Self {
        let refill = (batch_size.saturating_sub(buffered) as u64).max(1);
        UpdateSchedule { ratio, first_episode: episodes + refill, updates_before: updates }
    }

    /// Updates owed once `episodes` episodes have been collected.
    pub fn due(&self, episodes: u64) -> u64 {
        if episodes < self.first_episode {
            return self.updates_before;
        }
        self.updates_before + (((episodes - self.first_episode + 1) as f64) * self.ratio).floor() as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_update_schedule_starts_with_a_full_batch_and_refills_after_a_resume_without_buffer() {
        // EPyMARL's episode runner: an update right after the 32nd episode, then one per episode.
        let fresh = UpdateSchedule::new(1.0, 32, 0, 0, 0);
        assert_eq!([fresh.due(31), fresh.due(32), fresh.due(33), fresh.due(232)], [0, 1, 2, 201]);
        // The default: one update per 8 episodes.
        let slow = UpdateSchedule::new(0.125, 32, 0, 0, 0);
        assert_eq!([slow.due(32), slow.due(38), slow.due(39), slow.due(32 + 799)], [0, 0, 1, 100]);
        // Resumed at 1000 episodes and 969 updates without the buffer: 32 episodes to refill first.
        let refill = UpdateSchedule::new(1.0, 32, 1000, 969, 0);
        assert_eq!([refill.due(1000), refill.due(1031), refill.due(1032), refill.due(1033)], [969, 969, 970, 971]);
        // With the buffer: on from the next episode.
        let kept = UpdateSchedule::new(1.0, 32, 1000, 969, 5000);
        assert_eq!([kept.due(1000), kept.due(1001)], [969, 970]);
    }
}
