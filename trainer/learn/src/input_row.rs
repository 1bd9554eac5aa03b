//! The one layout of an agent's input row, shared by every agent network (the learner's batch,
//! the acting controller) and by the protocol designer's discriminator, so "what an agent sees"
//! is written in one place.
//!
//! Columns, in order (a part of width zero is absent):
//! `obs_t | obs_{t-1} .. obs_{t-h} | h validity flags | state | last action one-hot | messages | agent id one-hot`
//!
//! The learner uses `obs | state (qmix-state only) | last action | agent id` (pymarl's order; its
//! message columns already sit inside the observation row the pipeline hands it). The
//! discriminator adds `h` previous observations (zeros before the episode start, each with a 0/1
//! column saying whether it exists) and a separate block for the message it is scored with.

use crate::episode::EpisodeDims;

use super::LearnConfig;

/// Which parts an input row has, and their widths.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InputLayout {
    /// `obs_width` is the observation part (for the learner, including the message columns).
    pub dims: EpisodeDims,
    pub state: bool,
    pub last_action: bool,
    pub agent_id: bool,
    /// Previous observations in the row (0 for agent networks, which remember through their RNN).
    pub history: usize,
    /// Width of a separate message block (0 when the messages are part of the observation).
    pub messages: usize,
}

/// One agent's inputs at one step.
pub struct RowParts<'a> {
    pub obs: &'a [f32],
    /// The observation `back` steps earlier (1..=history), None before the episode start.
    pub past_obs: &'a dyn Fn(usize) -> Option<&'a [f32]>,
    /// The state, when the layout has one.
    pub state: Option<&'a [f32]>,
    /// The action taken at the previous step; negative means none (the first step).
    pub last_action: i32,
    /// The message block (`messages` wide); None leaves it zero.
    pub messages: Option<&'a [f32]>,
    pub agent: usize,
}

impl<'a> RowParts<'a> {
    /// The parts of an agent network's row: no history, no separate message block.
    pub fn step(obs: &'a [f32], state: Option<&'a [f32]>, last_action: i32, agent: usize) -> Self {
        RowParts { obs, past_obs: &|_| None, state, last_action, messages: None, agent }
    }
}

impl InputLayout {
    /// An agent network's layout under `cfg`.
    pub fn new(dims: EpisodeDims, cfg: &LearnConfig) -> Self {
        InputLayout {
            dims,
            state: cfg.agent_sees_state,
            last_action: cfg.obs_last_action,
            agent_id: cfg.obs_agent_id,
            history: 0,
            messages: 0,
        }
    }

    pub fn width(&self) -> usize {
        let d = &self.dims;
        (self.history + 1) * d.obs_width
            + self.history
            + if self.state { d.state_dim } else { 0 }
            + if self.last_action { d.n_actions } else { 0 }
            + self.messages
            + if self.agent_id { d.n_agents } else { 0 }
    }

    /// Write one row into `out` (length `width()`, overwritten entirely).
    pub fn write(&self, out: &mut [f32], row: RowParts<'_>) {
        let d = &self.dims;
        let (ow, h) = (d.obs_width, self.history);
        out.fill(0.0);
        out[..ow].copy_from_slice(row.obs);
        for back in 1..=h {
            let Some(past) = (row.past_obs)(back) else { break };
            out[back * ow..(back + 1) * ow].copy_from_slice(past);
            out[(h + 1) * ow + back - 1] = 1.0;
        }
        let mut o = (h + 1) * ow + h;
        if self.state {
            if let Some(s) = row.state {
                out[o..o + d.state_dim].copy_from_slice(s);
            }
            o += d.state_dim;
        }
        if self.last_action {
            if row.last_action >= 0 && (row.last_action as usize) < d.n_actions {
                out[o + row.last_action as usize] = 1.0;
            }
            o += d.n_actions;
        }
        if let Some(m) = row.messages {
            out[o..o + self.messages].copy_from_slice(m);
        }
        o += self.messages;
        if self.agent_id {
            out[o + row.agent] = 1.0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout(history: usize, messages: usize, state: bool) -> InputLayout {
        let dims = EpisodeDims { n_agents: 3, obs_width: 2, state_dim: 4, n_actions: 5 };
        InputLayout { dims, state, last_action: true, agent_id: true, history, messages }
    }

    #[test]
    fn agent_row_is_obs_state_last_action_id() {
        let l = layout(0, 0, true);
        assert_eq!(l.width(), 2 + 4 + 5 + 3);
        let mut out = vec![9.0; l.width()];
        l.write(&mut out, RowParts::step(&[1.0, 2.0], Some(&[3.0, 4.0, 5.0, 6.0]), 4, 1));
        let want = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0];
        assert_eq!(out, want);
        // First step: no last action.
        l.write(&mut out, RowParts::step(&[1.0, 2.0], Some(&[3.0, 4.0, 5.0, 6.0]), -1, 2));
        assert_eq!(&out[6..], &[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
    }

    #[test]
    fn history_rows_flag_the_steps_that_exist() {
        let l = layout(2, 1, false);
        assert_eq!(l.width(), 3 * 2 + 2 + 5 + 1 + 3);
        let prev = [7.0f32, 8.0];
        // One step into the episode: one previous observation, the second slot stays zero.
        let past = |back: usize| if back == 1 { Some(&prev[..]) } else { None };
        let mut out = vec![9.0; l.width()];
        let m = [0.5f32];
        l.write(&mut out, RowParts { obs: &[1.0, 2.0], past_obs: &past, state: None, last_action: 0, messages: Some(&m), agent: 0 });
        let want = [1.0, 2.0, 7.0, 8.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.5, 1.0, 0.0, 0.0];
        assert_eq!(out, want);
    }
}
