//! The Q-learner (pymarl `QLearner` / QPLEX `DMAQ_qattenLearner`): double-Q TD(0) targets from a
//! target network, masked mean-squared TD error, a global gradient-norm clip, Adam or RMSprop,
//! target copies every N collected episodes, and NaN/inf detection naming the step.

use std::sync::OnceLock;

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer, RmsPropConfig};
use burn::tensor::{Bool, Device, Int, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::buffer::{episode_rows, Batch, ReplayBuffer};
use super::config::{ConfigError, LearnConfig, MixerKind, OptimizerKind, RewardStandardisation, TimeLimit};
use super::methods::{AgentConfig, AgentNet, StepActions, TrainContext};
use super::mixer::{Mixer, QplexInputs};
use super::{InputLayout, LearnRng};
use crate::episode::{Episode, EpisodeDims};

/// Agent network plus mixer: the unit that is optimized, copied to the target and saved.
#[derive(Module, Debug)]
pub struct QNet {
    pub agent: AgentNet,
    pub mixer: Mixer,
}

impl QNet {
    /// Build with weights drawn from `rng` (deterministic for a given RNG state).
    pub fn new(rng: &mut LearnRng, dims: &EpisodeDims, cfg: &LearnConfig, agent: &AgentConfig, device: &Device) -> Self {
        let layout = InputLayout::new(*dims, cfg);
        QNet {
            agent: AgentNet::new(rng, agent, &layout, cfg, device),
            mixer: Mixer::new(rng, cfg.mixer, dims.n_agents, dims.state_dim, dims.n_actions, cfg, device),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum LearnError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("non-finite {what} ({value}) at update {update} (t_env {t_env}, episode {episode})")]
    NonFinite { what: &'static str, value: f32, update: u64, t_env: u64, episode: u64 },
    #[error("episode does not match the run's dimensions: {0}")]
    BadEpisode(String),
    #[error("checkpoint: {0}")]
    Checkpoint(String),
}

/// Running mean and variance of the rewards the TD targets read (`learn.reward_standardisation`),
/// updated per batch as EPyMARL's `RunningMeanStd` (parallel-moments update, unbiased batch
/// variance, prior count 1e-4 with mean 0 and variance 1).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RewardStats {
    pub mean: f64,
    pub var: f64,
    pub count: f64,
}

impl Default for RewardStats {
    fn default() -> Self {
        RewardStats { mean: 0.0, var: 1.0, count: 1e-4 }
    }
}

impl RewardStats {
    /// Fold in one batch of rewards.
    pub fn update(&mut self, values: &[f32]) {
        let k = values.len();
        if k == 0 {
            return;
        }
        let values: Vec<f64> = values.iter().map(|&v| v as f64).collect();
        let mean = crate::stats::mean(&values);
        // torch.var's default: the unbiased estimate (0 for a single value would be NaN there;
        // a one-value batch adds no spread here).
        let var = if k > 1 { crate::stats::variance(&values) * k as f64 / (k - 1) as f64 } else { 0.0 };
        let (n, m) = (self.count, k as f64);
        let delta = mean - self.mean;
        let total = n + m;
        let m2 = self.var * n + var * m + delta * delta * n * m / total;
        self.mean += delta * m / total;
        self.var = m2 / total;
        self.count = total;
    }

    /// (r - mean) / sqrt(var); a variance of 0 (every reward so far equal) leaves the centred
    /// value unscaled instead of dividing by zero.
    pub fn standardise(&self, r: f32) -> f32 {
        let sd = self.var.sqrt();
        let c = r as f64 - self.mean;
        (if sd > 1e-8 { c / sd } else { c }) as f32
    }
}

/// Progress counters; saved in checkpoints.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Counters {
    /// Environment steps of all episodes added.
    pub t_env: u64,
    /// Episodes added.
    pub episodes: u64,
    /// Gradient updates done.
    pub updates: u64,
    /// `episodes` at the last target copy.
    pub last_target_update_episode: u64,
    /// Reward statistics for standardised rewards (checkpoints from before it load the prior).
    #[serde(default)]
    pub reward_stats: RewardStats,
}

#[derive(Clone, Debug, Default)]
pub struct TrainStats {
    pub loss: f32,
    /// Global gradient norm before clipping.
    pub grad_norm: f32,
    pub td_error_abs: f32,
    pub q_taken_mean: f32,
    pub target_mean: f32,
    pub target_updated: bool,
    /// The method's extra terms (name, unweighted value), in `AgentConfig::stat_names` order.
    pub method: Vec<(&'static str, f32)>,
}

pub struct Learner {
    pub(crate) cfg: LearnConfig,
    /// The method's agent network (with its own settings).
    pub(crate) agent_cfg: AgentConfig,
    pub(crate) dims: EpisodeDims,
    pub(crate) layout: InputLayout,
    /// Plain (no autodiff) device; the online network lives on `device.autodiff()`.
    pub(crate) device: Device,
    pub(crate) net: QNet,
    pub(crate) target: QNet,
    pub(crate) optim: ModuleOptimizer,
    pub(crate) buffer: ReplayBuffer,
    pub(crate) rng: LearnRng,
    pub(crate) counters: Counters,
    /// The whole configuration of the run this learner trains, as its caller wrote it (lmac's
    /// `config.toml`); kept in every checkpoint so a resume can tell what was changed since.
    pub(crate) run_config: Option<String>,
}

pub(crate) fn make_optimizer(cfg: &LearnConfig) -> ModuleOptimizer {
    match cfg.optimizer {
        OptimizerKind::Adam => AdamConfig::new().with_epsilon(cfg.adam_eps).init(),
        OptimizerKind::Rmsprop => {
            RmsPropConfig::new().with_alpha(cfg.rmsprop_alpha).with_epsilon(cfg.rmsprop_eps).with_momentum(0.0).init()
        }
    }
}

impl Learner {
    /// Validate `cfg` and build online + target networks of pymarl's RNN agent, initialized
    /// from `cfg.seed`.
    pub fn new(dims: EpisodeDims, cfg: LearnConfig, device: Device) -> Result<Self, LearnError> {
        Self::with_agent(dims, cfg, AgentConfig::Rnn, device)
    }

    /// As [`new`](Self::new), with the agent network of a method (`methods::REGISTRY`).
    pub fn with_agent(dims: EpisodeDims, cfg: LearnConfig, agent_cfg: AgentConfig, device: Device) -> Result<Self, LearnError> {
        cfg.validate()?;
        agent_cfg.validate()?;
        if dims.n_agents == 0 || dims.n_actions == 0 || dims.obs_width == 0 {
            return Err(LearnError::BadEpisode(format!("dims must be non-zero: {dims:?}")));
        }
        let device = device.inner();
        let mut init_rng = LearnRng::seed_from(cfg.seed ^ 0x1417_0000_0000_0001);
        if let AgentConfig::Lmac(c) = &agent_cfg {
            if c.msg_cols > dims.obs_width || c.critical_dims.iter().any(|&d| d >= dims.state_dim) {
                return Err(LearnError::BadEpisode(format!(
                    "lmac settings ({} message columns, critical dims up to {:?}) do not fit {dims:?}",
                    c.msg_cols,
                    c.critical_dims.iter().max()
                )));
            }
        }
        let net = QNet::new(&mut init_rng, &dims, &cfg, &agent_cfg, &device.clone().autodiff());
        let target = net.valid();
        Ok(Learner {
            layout: InputLayout::new(dims, &cfg),
            optim: make_optimizer(&cfg),
            buffer: ReplayBuffer::new(cfg.buffer_size),
            rng: LearnRng::seed_from(cfg.seed ^ 0x5EED_1EA4_0000_0001),
            counters: Counters::default(),
            cfg,
            agent_cfg,
            dims,
            device,
            net,
            target,
            run_config: None,
        })
    }

    /// Record the run's whole configuration in the checkpoints this learner saves.
    pub fn set_run_config(&mut self, text: String) {
        self.run_config = Some(text);
    }

    pub fn config(&self) -> &LearnConfig {
        &self.cfg
    }
    pub fn agent_config(&self) -> &AgentConfig {
        &self.agent_cfg
    }
    pub fn dims(&self) -> &EpisodeDims {
        &self.dims
    }
    pub fn layout(&self) -> &InputLayout {
        &self.layout
    }
    pub fn counters(&self) -> Counters {
        self.counters
    }
    pub fn buffer(&self) -> &ReplayBuffer {
        &self.buffer
    }
    pub fn device(&self) -> &Device {
        &self.device
    }
    /// The learner's RNG (exploration and replay sampling share it so a checkpoint captures all).
    pub fn rng_mut(&mut self) -> &mut LearnRng {
        &mut self.rng
    }
    /// Online network snapshot without autodiff (for acting and evaluation).
    pub fn acting_net(&self) -> QNet {
        self.net.valid()
    }
    /// Trainable parameters of the online network (agent + mixer).
    pub fn num_params(&self) -> usize {
        self.net.num_params()
    }
    /// The online network (on the autodiff device), e.g. to map gradients to its parameters.
    pub fn online_net(&self) -> &QNet {
        &self.net
    }
    pub fn target_net(&self) -> &QNet {
        &self.target
    }
    /// Exploration rate at the current `t_env`.
    pub fn epsilon(&self) -> f32 {
        self.cfg.epsilon_at(self.counters.t_env)
    }

    /// Store a finished episode; advances `t_env` and the episode count.
    pub fn add_episode(&mut self, mut ep: Episode) -> Result<(), LearnError> {
        ep.check(&self.dims).map_err(LearnError::BadEpisode)?;
        if ep.truncated && self.cfg.time_limit == TimeLimit::Terminal {
            (ep.terminated, ep.truncated, ep.next) = (true, false, None);
        }
        let l = ep.len;
        self.counters.t_env += l as u64;
        self.counters.episodes += 1;
        self.buffer.push(ep);
        Ok(())
    }

    pub fn can_train(&self) -> bool {
        self.buffer.len() >= self.cfg.batch_size
    }

    /// Sample `batch_size` episodes and do one update; then copy the target if due.
    pub fn train_step(&mut self) -> Result<TrainStats, LearnError> {
        let batch = self.sample_batch();
        let mut stats = self.train_on(&batch)?;
        if self.counters.episodes - self.counters.last_target_update_episode >= self.cfg.target_update_interval_episodes {
            self.update_target();
            stats.target_updated = true;
        }
        Ok(stats)
    }

    /// Sample `batch_size` distinct episodes (uniformly) into a padded batch.
    pub fn sample_batch(&mut self) -> Batch {
        let idx = self.buffer.sample_indices(self.cfg.batch_size, &mut self.rng);
        let eps: Vec<&Episode> = idx.iter().map(|&i| self.buffer.get(i)).collect();
        Batch::from_episodes(&eps, &self.dims, &self.layout)
    }

    /// Copy the online network into the target network.
    pub fn update_target(&mut self) {
        self.target = self.net.valid();
        self.counters.last_target_update_episode = self.counters.episodes;
    }

    /// One gradient update on a prepared batch (no target-copy bookkeeping). With standardised
    /// rewards, the batch's rewards first update the running statistics.
    pub fn train_on(&mut self, batch: &Batch) -> Result<TrainStats, LearnError> {
        let rewards = self.standardised_rewards(batch);
        if self.cfg.data_parallel && batch.b >= 2 && self.net.agent.losses_are_step_means() {
            return self.train_on_halves(batch, rewards.as_deref());
        }
        let (loss, stats) = self.td_loss_with(batch, rewards.as_deref())?;
        self.apply_loss(loss, stats)
    }

    /// `learn.data_parallel`: the losses of the batch's two halves of episodes, each divided by
    /// the whole batch's trained steps, and their backward passes, on two threads; the gradients
    /// and statistics add up to the whole batch's (every term is a sum over trained steps
    /// divided by their count).
    fn train_on_halves(&mut self, batch: &Batch, rewards: Option<&[f32]>) -> Result<TrainStats, LearnError> {
        let mask_sum = batch.trained_steps();
        let ranges = [0..batch.b / 2, batch.b / 2..batch.b];
        // Both forward passes end before either backward pass starts: burn's autodiff keeps one
        // registry of graphs, and a thread recording a graph while another runs backward can
        // deadlock in it (measured: both threads waiting on its locks).
        let forwards_done = std::sync::Barrier::new(2);
        let part = |i: usize| -> Result<(f32, GradientsParams, TrainStats), LearnError> {
            let r = &ranges[i];
            let half = batch.episodes(r.clone());
            let rewards = rewards.map(|v| episode_rows(v, batch.t, batch.b, 1, r));
            // The network's parameters as leaves of this half's own autodiff graph (burn joins
            // the graphs of tensors that share a leaf into one); parameter ids stay, so the
            // gradients are the network's.
            let net = self.net.clone().map(&mut FreshLeaves);
            let forward = self.td_loss_part(&net, &half, rewards.as_deref(), (mask_sum, batch.b), i as u64, false);
            forwards_done.wait();
            let (loss, stats) = forward?;
            let value: f32 = loss.clone().detach().into_scalar();
            Ok((value, GradientsParams::from_grads(loss.backward(), &net), stats))
        };
        let (first, second) = std::thread::scope(|s| {
            let second = s.spawn(|| part(1));
            (part(0), second.join().expect("the second half's update thread panicked"))
        });
        let ((l1, mut grads, mut stats), (l2, g2, s2)) = (first?, second?);
        self.check_finite("loss", l1 + l2)?;
        add_grads(&self.net, &mut grads, g2);
        stats.td_error_abs += s2.td_error_abs;
        stats.q_taken_mean += s2.q_taken_mean;
        stats.target_mean += s2.target_mean;
        for (term, other) in stats.method.iter_mut().zip(&s2.method) {
            term.1 += other.1;
        }
        self.apply_grads(l1 + l2, grads, stats)
    }

    /// Whether this run standardises rewards (`learn.reward_standardisation`, by default the
    /// method's choice).
    pub fn standardises_rewards(&self) -> Option<RewardStandardisation> {
        match self.cfg.reward_standardisation {
            RewardStandardisation::Method => self.agent_cfg.standardises_rewards().then_some(RewardStandardisation::ValidSteps),
            RewardStandardisation::Off => None,
            other => Some(other),
        }
    }

    /// The batch's rewards standardised with the running statistics after folding this batch
    /// in (EPyMARL updates before it standardises), or `None` when the run keeps raw rewards.
    fn standardised_rewards(&mut self, batch: &Batch) -> Option<Vec<f32>> {
        let kind = self.standardises_rewards()?;
        let seen: Vec<f32> = match kind {
            // The released code folds in the padded steps' zero rewards too.
            RewardStandardisation::Released => batch.reward.clone(),
            _ => batch.reward.iter().zip(&batch.mask).filter(|(_, &m)| m > 0.0).map(|(&r, _)| r).collect(),
        };
        self.counters.reward_stats.update(&seen);
        let st = self.counters.reward_stats;
        Some(batch.reward.iter().map(|&r| st.standardise(r)).collect())
    }

    /// The masked double-Q TD(0) loss of `batch` (a scalar on the autodiff device, graph kept)
    /// and its statistics, with the method's extra losses (`AgentNet::unroll`) added in and
    /// each logged in `TrainStats::method`. Rewards as stored (see [`train_on`](Self::train_on)).
    pub fn td_loss(&self, batch: &Batch) -> Result<(Tensor<1>, TrainStats), LearnError> {
        self.td_loss_with(batch, None)
    }

    /// [`td_loss`](Self::td_loss) with the TD targets' rewards replaced by `rewards` (one per
    /// (t, b) row, as `batch.reward`).
    fn td_loss_with(&self, batch: &Batch, rewards: Option<&[f32]>) -> Result<(Tensor<1>, TrainStats), LearnError> {
        self.td_loss_part(&self.net, batch, rewards, (batch.trained_steps(), batch.b), 0, self.cfg.parallel_target)
    }

    /// [`td_loss_with`](Self::td_loss_with) of the online network `net` on `batch`, a part of an
    /// update's batch whose trained steps number `mask_sum` and whose episodes number
    /// `batch_episodes` (every mean over trained steps, or over all steps, divides by the whole
    /// batch's count; the method's terms see them in `TrainContext`); part `part`'s
    /// random draws; the target network unrolled on a second thread when `parallel_target`.
    fn td_loss_part(
        &self,
        net: &QNet,
        batch: &Batch,
        rewards: Option<&[f32]>,
        (mask_sum, batch_episodes): (f32, usize),
        part: u64,
        parallel_target: bool,
    ) -> Result<(Tensor<1>, TrainStats), LearnError> {
        let reward = rewards.unwrap_or(&batch.reward);
        let (b, t, n, a) = (batch.b, batch.t, batch.n_agents, batch.n_actions);
        let (nb, iw, sd) = (t * b, batch.input_dim, batch.state_dim);
        let dev = self.device.clone();
        let ad = dev.clone().autodiff();

        // Every step's inputs, time-major [T * B * n, iw]: the batch's own layout, one copy that
        // the target unroll reads as it is and the online unroll with autodiff (the same buffer).
        let inputs: Tensor<2> = Tensor::from_data(TensorData::new(batch.inputs[..t * b * n * iw].to_vec(), [t * b * n, iw]), &dev);
        let actions_i: Vec<i64> = batch.actions.iter().map(|&x| x as i64).collect();
        let actions_t = |device: &Device| -> Tensor<4, Int> { Tensor::from_data(TensorData::new(actions_i.clone(), [t, b, n, 1]), device) };
        let unavail: Vec<bool> = batch.avail.iter().map(|&x| x == 0).collect();
        let unavail_t: Tensor<4, Bool> = Tensor::from_data(TensorData::new(unavail, [t, b, n, a]), &dev);
        let states_t = |device: &Device| -> Tensor<2> { Tensor::from_data(TensorData::new(batch.state.clone(), [nb, sd]), device) };
        let kind = self.cfg.mixer;
        let onehot = |idx: Tensor<4, Int>| -> Tensor<2> {
            // idx [t, b, n, 1] -> [nb, n * a]
            idx.reshape([nb * n]).one_hot::<2>(a).float().reshape([nb, n * a])
        };

        // ---- online network (autodiff)
        // The target unroll (no autodiff) optionally runs on a second thread meanwhile.
        let mask_t: Tensor<1> = Tensor::from_data(TensorData::new(batch.mask.clone(), [nb]), &ad);
        // The batch's actions and (once the target unroll has run) the target network's greedy
        // available actions, per step and agent-row, for methods whose losses read them.
        let (step_actions, greedy_cell) = StepActions::pending(actions_t(&ad).reshape([t, b * n]));
        let ctx = TrainContext {
            state: states_t(&ad),
            mask: mask_t.clone(),
            mask_sum,
            b,
            batch_episodes,
            n_agents: n,
            seed: self.cfg.seed
                ^ (self.counters.updates + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                ^ part.wrapping_mul(0xD1B5_4A32_D192_ED03),
            actions: Some(step_actions),
            reward: Some(Tensor::from_data(TensorData::new(reward.to_vec(), [nb]), &ad)),
        };
        let target_seed = ctx.seed;
        let target_unroll = || {
            // Filled with `None` if the unroll panics, so an online unroll waiting for the greedy
            // actions fails instead of waiting forever.
            struct Fill<'a>(&'a OnceLock<Option<Tensor<2, Int>>>);
            impl Drop for Fill<'_> {
                fn drop(&mut self) {
                    let _ = self.0.set(None);
                }
            }
            let _fill = Fill(&greedy_cell);
            let out = self.target.agent.unroll_target_stacked(inputs.clone(), t, target_seed);
            let greedy = out.clone().reshape([t, b, n, a]).mask_fill(unavail_t.clone(), -1e9).argmax(3).reshape([t, b * n]);
            let _ = greedy_cell.set(Some(Tensor::from_data(greedy.into_data(), &ad)));
            out
        };
        let ((mac_out, aux), target_out) = if parallel_target {
            std::thread::scope(|s| {
                let target = s.spawn(target_unroll);
                let online = net.agent.unroll_stacked(inputs.clone().autodiff(), t, Some(&ctx));
                (online, target.join().expect("target unroll thread panicked"))
            })
        } else {
            // The target first: the online unroll's losses may read its greedy actions.
            let target = target_unroll();
            (net.agent.unroll_stacked(inputs.clone().autodiff(), t, Some(&ctx)), target)
        };
        let mac_out: Tensor<4> = mac_out.reshape([t, b, n, a]);
        let chosen = mac_out.clone().gather(3, actions_t(&ad)).reshape([nb, n]);
        let mac_plain = mac_out.clone().detach().inner().mask_fill(unavail_t.clone(), -1e9);

        // ---- target network (plain device)
        let target_out: Tensor<4> = target_out.reshape([t, b, n, a]);
        let target_masked = target_out.clone().mask_fill(unavail_t.clone(), -1e9);
        let (target_q, target_actions) = if self.cfg.double_q {
            let cur = mac_plain.clone().argmax(3);
            (target_out.gather(3, cur.clone()), cur)
        } else {
            let cur = target_masked.clone().argmax(3);
            (target_masked.clone().gather(3, cur.clone()), cur)
        };
        let target_q = target_q.reshape([nb, n]);
        let target_extra = (kind == MixerKind::Qplex)
            .then(|| QplexInputs { actions_onehot: onehot(target_actions), max_q: target_masked.max_dim(3).reshape([nb, n]) });
        let target_tot: Vec<f32> =
            self.target.mixer.forward(target_q, states_t(&dev), target_extra).into_data().try_into_vec::<f32>().expect("f32 target values");

        // ---- TD(0) targets on the host: y_t = r_t + gamma (1 - term_t) Q_tot'(t+1)
        let mut y = vec![0.0f32; nb];
        for ti in 0..t {
            for bi in 0..b {
                let i = ti * b + bi;
                let next = if batch.has_next[i] > 0.0 && batch.terminated[i] == 0.0 { target_tot[(ti + 1) * b + bi] } else { 0.0 };
                // Masked transitions get target 0 so a NaN in one cannot leak through `0 * NaN`.
                y[i] = if batch.mask[i] > 0.0 { reward[i] + self.cfg.gamma * next } else { 0.0 };
            }
        }
        let target_mean = y.iter().zip(&batch.mask).map(|(v, m)| v * m).sum::<f32>() / mask_sum;

        // ---- mixed online values and loss
        let extra = (kind == MixerKind::Qplex)
            .then(|| QplexInputs { actions_onehot: onehot(actions_t(&ad)), max_q: mac_plain.max_dim(3).reshape([nb, n]) });
        let q_tot = net.mixer.forward(chosen, states_t(&ad), extra);
        let y_t: Tensor<1> = Tensor::from_data(TensorData::new(y, [nb]), &ad);
        let td = (q_tot.clone() - y_t) * mask_t.clone();
        let mut loss = td.clone().square().sum().div_scalar(mask_sum);
        // The method's extra losses join the TD loss; every term is logged.
        let mut method = Vec::with_capacity(aux.len());
        for term in aux {
            if let Some(l) = term.loss {
                loss = loss + l;
            }
            method.push((term.name, term.value));
        }

        let td_abs: f32 = td.detach().abs().sum().into_scalar::<f32>() / mask_sum;
        let q_taken: f32 = (q_tot.detach() * mask_t).sum().into_scalar::<f32>() / mask_sum;
        let stats = TrainStats {
            loss: f32::NAN,
            grad_norm: f32::NAN,
            td_error_abs: td_abs,
            q_taken_mean: q_taken,
            target_mean,
            target_updated: false,
            method,
        };
        Ok((loss, stats))
    }

    /// Backward of `loss`, global gradient-norm clip, optimizer step. Fails (naming the update)
    /// when the loss or the gradient norm is NaN or infinite; the network is then unchanged.
    pub fn apply_loss(&mut self, loss: Tensor<1>, stats: TrainStats) -> Result<TrainStats, LearnError> {
        let loss_v: f32 = loss.clone().detach().into_scalar();
        self.check_finite("loss", loss_v)?;
        let grads = GradientsParams::from_grads(loss.backward(), &self.net);
        self.apply_grads(loss_v, grads, stats)
    }

    /// [`apply_loss`](Self::apply_loss) from the (finite) loss's value and its gradients.
    fn apply_grads(&mut self, loss_v: f32, mut grads: GradientsParams, mut stats: TrainStats) -> Result<TrainStats, LearnError> {
        let grad_norm = global_grad_norm(&self.net, &grads);
        self.check_finite("gradient norm", grad_norm)?;
        let clip = self.cfg.grad_norm_clip;
        let coef = clip / (grad_norm + 1e-6);
        if coef < 1.0 {
            scale_grads(&self.net, &mut grads, coef);
        }
        let QNet { agent, mixer } = self.optim.step(self.cfg.lr, self.net.clone(), grads);
        self.net = QNet { agent: agent.after_update(), mixer };
        self.counters.updates += 1;
        stats.loss = loss_v;
        stats.grad_norm = grad_norm;
        Ok(stats)
    }

    fn check_finite(&self, what: &'static str, value: f32) -> Result<(), LearnError> {
        if value.is_finite() {
            Ok(())
        } else {
            Err(LearnError::NonFinite {
                what,
                value,
                update: self.counters.updates + 1,
                t_env: self.counters.t_env,
                episode: self.counters.episodes,
            })
        }
    }
}

struct SquaredNorm<'a> {
    grads: &'a GradientsParams,
    acc: Option<Tensor<1>>,
}

impl ModuleVisitor for SquaredNorm<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(g) = self.grads.get::<D>(param.id) {
            let s = g.square().sum();
            self.acc = Some(match self.acc.take() {
                Some(acc) => acc + s,
                None => s,
            });
        }
    }
}

/// sqrt(sum of squares of every parameter gradient), as torch's `clip_grad_norm_`.
pub fn global_grad_norm<M: Module>(module: &M, grads: &GradientsParams) -> f32 {
    let mut v = SquaredNorm { grads, acc: None };
    module.visit(&mut v);
    v.acc.map(|t| t.into_scalar::<f32>().sqrt()).unwrap_or(0.0)
}

struct Scale<'a> {
    grads: &'a mut GradientsParams,
    coef: f32,
    seen: Vec<ParamId>,
}

impl ModuleVisitor for Scale<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if self.seen.contains(&param.id) {
            return;
        }
        if let Some(g) = self.grads.remove::<D>(param.id) {
            self.grads.register::<D>(param.id, g.mul_scalar(self.coef));
            self.seen.push(param.id);
        }
    }
}

/// A module's parameters as new autodiff leaves (same values and ids, same need of gradients).
struct FreshLeaves;

impl ModuleMapper for FreshLeaves {
    fn map_float<const D: usize>(&mut self, p: Param<Tensor<D>>) -> Param<Tensor<D>> {
        p.map(|t| {
            let grad = t.is_require_grad();
            let t = t.detach();
            if grad {
                t.require_grad()
            } else {
                t
            }
        })
    }
}

struct Add<'a> {
    grads: &'a mut GradientsParams,
    other: GradientsParams,
}

impl ModuleVisitor for Add<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        // Taken out of `other` once: a parameter visited twice is added once.
        if let Some(o) = self.other.remove::<D>(param.id) {
            let sum = match self.grads.remove::<D>(param.id) {
                Some(g) => g + o,
                None => o,
            };
            self.grads.register::<D>(param.id, sum);
        }
    }
}

/// `grads += other`, parameter by parameter.
pub fn add_grads<M: Module>(module: &M, grads: &mut GradientsParams, other: GradientsParams) {
    module.visit(&mut Add { grads, other });
}

/// Multiply every parameter gradient by `coef`.
pub fn scale_grads<M: Module>(module: &M, grads: &mut GradientsParams, coef: f32) {
    let mut v = Scale { grads, coef, seen: Vec::new() };
    module.visit(&mut v);
}
