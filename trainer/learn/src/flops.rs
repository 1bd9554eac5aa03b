//! Multiply-add FLOPs of one learner update (2 per multiply-add; elementwise work not
//! counted), the numerator of `lmac bench learner`'s achieved GFLOP/s. The plain agent and the
//! mixers count here; each communication method counts its own networks beside them
//! (`update_flops` on its config), and [`AgentConfig::update_flops`](crate::AgentConfig::update_flops)
//! dispatches.

use crate::{LearnConfig, MixerKind};
use serde::Serialize;

/// The update's shape: batch of episodes, steps, agents, agent input width (observation, last
/// action and id), actions, state, the agent's hidden width.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct UpdateShape {
    pub batch: usize,
    pub steps: usize,
    pub agents: usize,
    pub input: usize,
    pub actions: usize,
    pub state: usize,
    pub hidden: usize,
}

impl UpdateShape {
    /// Multiply-add FLOPs of one update (2 per multiply-add; elementwise work not counted):
    /// online forward, its backward (weight and input gradients, no input gradient for the first
    /// layer) and the target network's forward, agents and mixer, for lmac's default settings.
    pub fn plain(&self, mixer: MixerKind, cfg: &LearnConfig) -> f64 {
        let (h, a, n, s) = (self.hidden as f64, self.actions as f64, self.agents as f64, self.state as f64);
        let agent_rows = (self.batch * self.steps * self.agents) as f64;
        let mix_rows = (self.batch * self.steps) as f64;
        let first = 2.0 * self.input as f64 * h;
        let rest = 2.0 * h * 3.0 * h * 2.0 + 2.0 * h * a;
        let (mixer_first, mixer_rest) = match mixer {
            MixerKind::Vdn => (0.0, 0.0),
            MixerKind::Qmix => {
                let (e, he) = (cfg.mixing_embed_dim as f64, cfg.hypernet_embed as f64);
                // first layers read the state: w1, w_final (hypernets), b1, V
                let first = 2.0 * s * (he + he + e + e);
                let rest = 2.0 * he * e * n + 2.0 * he * e + 2.0 * e + 2.0 * n * e + 2.0 * e;
                (first, rest)
            }
            MixerKind::Qplex => {
                let (he, k, ae) = (cfg.hypernet_embed as f64, cfg.qplex_num_kernel as f64, cfg.qplex_adv_hypernet_embed as f64);
                let first = 2.0 * s * (he + he) + 2.0 * k * ae * (s + s + s + n * a);
                let rest = 2.0 * he * n * 2.0 + 2.0 * k * (ae * ae + ae) + 2.0 * k * (ae * ae + ae * n) * 2.0;
                (first, rest)
            }
        };
        let fwd = agent_rows * (first + rest) + mix_rows * (mixer_first + mixer_rest);
        let bwd_no_input_grad = agent_rows * first + mix_rows * mixer_first;
        // forward + backward (2x forward, minus the first layers' input gradients) + target
        fwd + (2.0 * fwd - bwd_no_input_grad) + fwd
    }
}
