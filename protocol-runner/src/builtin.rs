//! Built-in protocols: `none` (no messages) and `fullcomm` (the FullComm baseline: every agent
//! receives every other agent's whole observation, each block tagged with the sender's one-hot
//! id). Compiled protocol descriptions (`protocol/`) implement the same `MessagePlan`.

use crate::plan::{MessagePlan, StepView};

/// No communication: message columns stay zero.
#[derive(Clone)]
pub struct NoMessages;

impl MessagePlan for NoMessages {
    fn msg_dim(&self) -> usize {
        0
    }
    fn name(&self) -> String {
        "none".into()
    }
    fn fresh(&self) -> Box<dyn MessagePlan> {
        Box::new(self.clone())
    }
    fn apply(&mut self, step: &mut StepView<'_>) {
        // Reserved but unused columns are kept at zero (the slab starts zeroed; this makes it
        // hold even if another plan wrote them before).
        if step.msg_dim == 0 {
            return;
        }
        let (od, rw) = (step.obs_dim, step.row_width());
        for row in step.rows.chunks_exact_mut(rw) {
            row[od..].fill(0.0);
        }
    }
}

/// Every agent receives, for every other agent j in order, [obs_j, onehot(j)].
#[derive(Clone)]
pub struct FullComm {
    pub n_agents: usize,
    pub obs_dim: usize,
}

impl FullComm {
    pub fn columns(n_agents: usize, obs_dim: usize) -> usize {
        n_agents.saturating_sub(1) * (obs_dim + n_agents)
    }
}

impl MessagePlan for FullComm {
    fn msg_dim(&self) -> usize {
        Self::columns(self.n_agents, self.obs_dim)
    }
    fn name(&self) -> String {
        "fullcomm".into()
    }
    fn fresh(&self) -> Box<dyn MessagePlan> {
        Box::new(self.clone())
    }
    fn apply(&mut self, step: &mut StepView<'_>) {
        let (n, od, rw) = (step.n_agents, step.obs_dim, step.row_width());
        let block = od + n;
        let used = self.msg_dim();
        assert!(used <= step.msg_dim, "fullcomm needs {used} message columns, the slab reserves {}", step.msg_dim);
        for env in step.rows.chunks_exact_mut(n * rw) {
            for i in 0..n {
                let mut col = od; // write position inside receiver i's row
                for j in (0..n).filter(|&j| j != i) {
                    // Rows i and j are disjoint; copy within the env's slice.
                    env.copy_within(j * rw..j * rw + od, i * rw + col);
                    let tag = &mut env[i * rw + col + od..i * rw + col + block];
                    tag.fill(0.0);
                    tag[j] = 1.0;
                    col += block;
                }
                env[i * rw + od + used..(i + 1) * rw].fill(0.0);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fullcomm_copies_other_agents_rows_with_sender_tags() {
        let (b, n, od) = (2, 3, 2);
        let md = FullComm::columns(n, od);
        let rw = od + md;
        let mut rows = vec![-7.0f32; b * n * rw];
        for e in 0..b {
            for a in 0..n {
                for d in 0..od {
                    rows[(e * n + a) * rw + d] = (100 * e + 10 * a + d) as f32;
                }
            }
        }
        let first = vec![false; b];
        let la = vec![0i32; b * n];
        let mut view = StepView { num_envs: b, n_agents: n, obs_dim: od, msg_dim: md, rows: &mut rows, first: &first, last_actions: &la };
        FullComm { n_agents: n, obs_dim: od }.apply(&mut view);
        // env 1, receiver 1: senders 0 then 2
        let r = &rows[(n + 1) * rw..(n + 2) * rw];
        assert_eq!(&r[..od], &[110.0, 111.0]);
        assert_eq!(&r[od..], &[100.0, 101.0, 1.0, 0.0, 0.0, 120.0, 121.0, 0.0, 0.0, 1.0]);
    }
}
