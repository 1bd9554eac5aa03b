//! The discriminator D^(k) (paper section 4.1, appendix B.3): an autoencoder that reconstructs
//! the global state s_t from one agent's view (its observation history, the message it
//! received, its id). It is trained on the dataset B by MSE; its reconstructions give the
//! meta-information chi ([`super::meta`]).
//!
//! # Input encoding (one row per episode, step t and agent i)
//! The agents' shared row layout ([`lmac_learn::input_row`]) with a history window and a
//! message block:
//! `[o_t | o_{t-1} .. o_{t-h} | valid_{t-1} .. valid_{t-h} | a_{t-1} one-hot | m_t | one-hot(i)]`
//! - `o`: agent i's raw observation (`obs_dim`); `h` = [`DiscriminatorConfig::history`]
//!   previous observations, zeros before the episode start, with one 0/1 column per history slot
//!   saying whether that step exists (so a zero observation and "no step yet" differ);
//! - `a_{t-1}`: the action i took on the previous step (all zero on the first step);
//! - `m_t`: the message columns i received (`msg_dim` wide, from [`Dataset::messages`]); zeros
//!   for the no-message discriminator, which keeps the same width and architecture;
//! - the agent id one-hot (`n_agents`).
//!
//! This is a compact stand-in for the paper's tau_t^i (the full history): a short window plus
//! the last action, cheap to build on the fly for every sampled row, and messages carry the
//! sender's longer history themselves when a protocol asks for it.
//!
//! # Normalization
//! Inputs and targets are standardized per column with the training rows' mean and standard
//! deviation (constant columns are only centred), so every state dim weighs the same in the
//! loss whatever its scale. Predictions are mapped back to the state's own units before anyone
//! sees them, because alpha (the chi threshold) is defined there.
//!
//! # Network and training (paper Table B.1 defaults, all configurable)
//! Encoder `in -> hidden (ReLU, dropout) -> latent`, decoder `latent -> hidden (ReLU, dropout)
//! -> state_dim`; hidden 64, latent 20, dropout 0.1, Adam lr 5e-4, MSE, mini-batches of 32 rows
//! drawn epoch by epoch from a seeded shuffle of the training rows. Dropout masks and the
//! initial weights come from the host-side [`LearnRng`], so a seed fixes the result exactly.
//! The default is the paper's 1000 epochs x 10 iterations = 10 000 updates: measured on this
//! machine (2 shared cores) at LBF 8x8 widths (input 155 columns with 64 message columns,
//! state 300), batch 32 costs about 0.6 ms per update (batch 128: 1.5 ms), so one
//! discriminator trains in about 6 s and the six of a three-phase design (with and without
//! messages per phase) in about 40 s; the `design_data` test `discriminator_cost` prints it.
//!
//! Evaluation happens on held-out episodes ([`split_episodes`]): chi measures generalization
//! to trajectories the discriminator never saw, not memorization.

use anyhow::{bail, Result};
use burn::module::Module;
use burn::nn::Linear;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor, TensorData};
use lmac_learn::episode::EpisodeDims;
use lmac_learn::{init::linear, InputLayout, LearnRng, RowParts};
use lmac_run::dataset::Dataset;
use serde::{Deserialize, Serialize};

/// Everything about a discriminator that can be chosen.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DiscriminatorConfig {
    /// Hidden width of encoder and decoder (paper: 64).
    pub hidden: usize,
    /// Latent width (paper: 20).
    pub latent: usize,
    /// Dropout after each hidden layer while training (paper: 0.1).
    pub dropout: f32,
    /// Adam learning rate (paper: 5e-4).
    pub lr: f64,
    /// Rows (episode, step, agent) per update (paper: 32).
    pub batch_size: usize,
    /// Gradient updates (paper: 1000 epochs x 10 iterations = 10 000).
    pub updates: usize,
    /// Previous observations in the input besides the current one.
    pub history: usize,
    /// Fraction of episodes held out for measuring chi (at least one episode each side).
    pub holdout_fraction: f64,
    /// Rows per forward pass when predicting.
    pub eval_batch: usize,
}

impl Default for DiscriminatorConfig {
    fn default() -> Self {
        DiscriminatorConfig {
            hidden: 64,
            latent: 20,
            dropout: 0.1,
            lr: 5e-4,
            batch_size: 32,
            updates: 10_000,
            history: 2,
            holdout_fraction: 0.2,
            eval_batch: 4096,
        }
    }
}

impl DiscriminatorConfig {
    /// Every problem at once, each naming the setting.
    pub fn validate(&self) -> Result<()> {
        let mut errs = Vec::new();
        for (name, v) in [
            ("hidden", self.hidden),
            ("latent", self.latent),
            ("batch_size", self.batch_size),
            ("updates", self.updates),
            ("eval_batch", self.eval_batch),
        ] {
            if v == 0 {
                errs.push(format!("discriminator.{name} must be at least 1"));
            }
        }
        if !(0.0..1.0).contains(&self.dropout) {
            errs.push(format!("discriminator.dropout is {}: it must be in [0, 1)", self.dropout));
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            errs.push(format!("discriminator.lr is {}: it must be a positive number", self.lr));
        }
        if !(self.holdout_fraction > 0.0 && self.holdout_fraction < 1.0) {
            errs.push(format!("discriminator.holdout_fraction is {}: it must be strictly between 0 and 1", self.holdout_fraction));
        }
        if self.history > 64 {
            errs.push(format!("discriminator.history is {}: at most 64 previous observations", self.history));
        }
        if errs.is_empty() {
            Ok(())
        } else {
            bail!("{}", errs.join("; "))
        }
    }
}

/// Split episode indices 0..n into (train, held out) by a seeded shuffle: `holdout_fraction`
/// of them (rounded, at least 1) are held out, at least 1 is kept for training. Both lists are
/// sorted. Fails with fewer than 2 episodes.
pub fn split_episodes(n: usize, holdout_fraction: f64, seed: u64) -> Result<(Vec<usize>, Vec<usize>)> {
    if n < 2 {
        bail!("the dataset has {n} episode(s): training and evaluating a discriminator needs at least 2 (one to train on, one held out)");
    }
    let mut idx: Vec<usize> = (0..n).collect();
    let mut rng = LearnRng::seed_from(seed ^ 0xD15C_5EED_0000_0001);
    for i in (1..n).rev() {
        idx.swap(i, rng.below(i + 1));
    }
    let held = ((n as f64 * holdout_fraction).round() as usize).clamp(1, n - 1);
    let mut test = idx[..held].to_vec();
    let mut train = idx[held..].to_vec();
    test.sort_unstable();
    train.sort_unstable();
    Ok((train, test))
}

/// The discriminator's view of B: the dataset and, for the with-message discriminator, every
/// episode's received messages (`len * n_agents * msg_dim`, as [`Dataset::messages`] returns).
#[derive(Clone, Copy)]
pub struct DiscInput<'a> {
    pub data: &'a Dataset,
    /// None: the message columns are zero (the no-communication baseline).
    pub messages: Option<&'a [Vec<f32>]>,
    pub msg_dim: usize,
}

impl<'a> DiscInput<'a> {
    pub fn with_messages(data: &'a Dataset, messages: &'a [Vec<f32>], msg_dim: usize) -> Self {
        DiscInput { data, messages: Some(messages), msg_dim }
    }

    /// Same width as `with_messages`, message columns zero.
    pub fn without_messages(data: &'a Dataset, msg_dim: usize) -> Self {
        DiscInput { data, messages: None, msg_dim }
    }

    fn check(&self) -> Result<()> {
        let h = &self.data.header;
        if h.n_agents == 0 || h.obs_dim == 0 || h.state_dim == 0 {
            bail!(
                "dataset {}: n_agents, obs_dim and state_dim must be non-zero (got {}, {}, {})",
                h.env,
                h.n_agents,
                h.obs_dim,
                h.state_dim
            );
        }
        if let Some(m) = self.messages {
            if m.len() != self.data.episodes.len() {
                bail!("messages for {} episodes, but the dataset has {}", m.len(), self.data.episodes.len());
            }
            for (k, (e, msg)) in self.data.episodes.iter().zip(m).enumerate() {
                let want = e.len * h.n_agents * self.msg_dim;
                if msg.len() != want {
                    bail!(
                        "episode {k}: {} message values, expected {want} ({} steps x {} agents x {} columns)",
                        msg.len(),
                        e.len,
                        h.n_agents,
                        self.msg_dim
                    );
                }
            }
        }
        Ok(())
    }
}

/// The discriminator's input row: the agents' shared row layout ([`InputLayout`]) with
/// `history` previous observations and a separate block for the received message.
fn row_layout(input: &DiscInput, history: usize) -> InputLayout {
    let h = &input.data.header;
    let dims = EpisodeDims { n_agents: h.n_agents, obs_width: h.obs_dim, state_dim: h.state_dim, n_actions: h.n_actions };
    InputLayout { dims, state: false, last_action: true, agent_id: true, history, messages: input.msg_dim }
}

/// Write the row of (episode `e`, step `t`, agent `i`) into `out` (length `layout.width()`).
fn write_row(layout: &InputLayout, input: &DiscInput, (e, t, i): (usize, usize, usize), out: &mut [f32]) {
    let (n, od, md) = (layout.dims.n_agents, layout.dims.obs_width, layout.messages);
    let ep = &input.data.episodes[e];
    let obs_at = |step: usize| &ep.obs[(step * n + i) * od..(step * n + i + 1) * od];
    let past = |back: usize| (back <= t).then(|| obs_at(t - back));
    layout.write(
        out,
        RowParts {
            obs: obs_at(t),
            past_obs: &past,
            state: None,
            last_action: if t > 0 { ep.actions[(t - 1) * n + i] } else { -1 },
            messages: input.messages.map(|m| &m[e][(t * n + i) * md..(t * n + i + 1) * md]),
            agent: i,
        },
    );
}

/// The autoencoder: encoder to the latent, decoder to the state.
#[derive(Module, Debug)]
pub struct StateAutoencoder {
    pub enc1: Linear,
    pub enc2: Linear,
    pub dec1: Linear,
    pub dec2: Linear,
}

impl StateAutoencoder {
    pub fn new(rng: &mut LearnRng, input: usize, hidden: usize, latent: usize, output: usize, device: &Device) -> Self {
        StateAutoencoder {
            enc1: linear(rng, input, hidden, device),
            enc2: linear(rng, hidden, latent, device),
            dec1: linear(rng, latent, hidden, device),
            dec2: linear(rng, hidden, output, device),
        }
    }

    /// x [B, in] -> [B, state_dim]; `masks` are the two dropout masks (already scaled by
    /// 1/(1-p)), None when evaluating.
    pub fn forward(&self, x: Tensor<2>, masks: Option<(Tensor<2>, Tensor<2>)>) -> Tensor<2> {
        let (m1, m2) = match masks {
            Some((a, b)) => (Some(a), Some(b)),
            None => (None, None),
        };
        let mut h = relu(self.enc1.forward(x));
        if let Some(m) = m1 {
            h = h * m;
        }
        let z = self.enc2.forward(h);
        let mut h = relu(self.dec1.forward(z));
        if let Some(m) = m2 {
            h = h * m;
        }
        self.dec2.forward(h)
    }
}

/// Per-column standardization: x' = (x - mean) * inv_std.
#[derive(Clone, Debug)]
pub(super) struct Standardize {
    mean: Vec<f32>,
    inv_std: Vec<f32>,
}

impl Standardize {
    /// Columns whose standard deviation is below 1e-6 of their scale are only centred.
    pub(super) fn fit(width: usize, rows: impl Iterator<Item = Vec<f32>>) -> Self {
        let m = lmac_learn::stats::ColumnMoments::of_rows(width, rows);
        let mean = m.mean.iter().map(|&x| x as f32).collect();
        let inv_std =
            m.sd.iter().zip(&m.mean).map(|(&sd, &mu)| if sd > 1e-6 * (1.0 + mu.abs()) { (1.0 / sd) as f32 } else { 1.0 }).collect();
        Standardize { mean, inv_std }
    }

    pub(super) fn apply(&self, row: &mut [f32]) {
        for ((v, m), s) in row.iter_mut().zip(&self.mean).zip(&self.inv_std) {
            *v = (*v - m) * s;
        }
    }

    fn invert(&self, row: &mut [f32]) {
        for ((v, m), s) in row.iter_mut().zip(&self.mean).zip(&self.inv_std) {
            *v = *v / s + m;
        }
    }
}

/// How a training run went.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainReport {
    pub updates: usize,
    pub train_episodes: usize,
    /// Rows (episode, step, agent) of the training episodes.
    pub train_rows: usize,
    pub seconds: f64,
    pub ms_per_update: f64,
    /// Mean standardized MSE of the last 10% of updates (at most 200), dropout on.
    pub final_loss: f64,
}

/// A trained discriminator (weights on the plain device, no autodiff).
pub struct Discriminator {
    model: StateAutoencoder,
    layout: InputLayout,
    inputs: Standardize,
    targets: Standardize,
    state_dim: usize,
    eval_batch: usize,
    device: Device,
}

/// Every (episode, step, agent) row of `episodes`.
fn rows_of(data: &Dataset, episodes: &[usize]) -> Vec<(u32, u32, u32)> {
    let n = data.header.n_agents;
    let mut v = Vec::new();
    for &e in episodes {
        for t in 0..data.episodes[e].len {
            for i in 0..n {
                v.push((e as u32, t as u32, i as u32));
            }
        }
    }
    v
}

impl Discriminator {
    /// Train on the rows of `train_episodes` (indices into the dataset).
    pub fn train(
        input: &DiscInput,
        train_episodes: &[usize],
        cfg: &DiscriminatorConfig,
        seed: u64,
        device: &Device,
    ) -> Result<(Self, TrainReport)> {
        cfg.validate()?;
        input.check()?;
        let data = input.data;
        let h = &data.header;
        if let Some(&e) = train_episodes.iter().find(|&&e| e >= data.episodes.len()) {
            bail!("training episode {e} is out of range: the dataset has {} episodes", data.episodes.len());
        }
        let rows = rows_of(data, train_episodes);
        if rows.is_empty() {
            bail!("no training rows: the {} training episodes are empty", train_episodes.len());
        }
        let layout = row_layout(input, cfg.history);
        let (iw, sd) = (layout.width(), h.state_dim);
        let row_in = |&(e, t, i): &(u32, u32, u32)| {
            let mut r = vec![0f32; iw];
            write_row(&layout, input, (e as usize, t as usize, i as usize), &mut r);
            r
        };
        let inputs = Standardize::fit(iw, rows.iter().map(row_in));
        let state_of =
            |&(e, t, _): &(u32, u32, u32)| -> &[f32] { &data.episodes[e as usize].state[t as usize * sd..(t as usize + 1) * sd] };
        let targets = Standardize::fit(sd, rows.iter().map(|r| state_of(r).to_vec()));

        let dev = device.clone().inner();
        let ad = dev.clone().autodiff();
        let mut init_rng = LearnRng::seed_from(seed ^ 0xD15C_0000_0000_0002);
        let mut model = StateAutoencoder::new(&mut init_rng, iw, cfg.hidden, cfg.latent, sd, &ad);
        let mut optim = AdamConfig::new().init();
        let mut rng = LearnRng::seed_from(seed ^ 0xD15C_0000_0000_0003);

        let b = cfg.batch_size;
        let keep = 1.0 - cfg.dropout;
        let mut order: Vec<usize> = (0..rows.len()).collect();
        let mut cursor = order.len();
        let mut xb = vec![0f32; b * iw];
        let mut yb = vec![0f32; b * sd];
        let tail = (cfg.updates / 10).clamp(1, 200);
        let (mut tail_sum, mut tail_n) = (0f64, 0usize);
        let mask = |rng: &mut LearnRng, len: usize| -> Vec<f32> {
            (0..len).map(|_| if rng.uniform() < keep { 1.0 / keep } else { 0.0 }).collect()
        };
        let start = std::time::Instant::now();
        for u in 0..cfg.updates {
            for k in 0..b {
                if cursor == order.len() {
                    for j in (1..order.len()).rev() {
                        order.swap(j, rng.below(j + 1));
                    }
                    cursor = 0;
                }
                let r = &rows[order[cursor]];
                cursor += 1;
                let x = &mut xb[k * iw..(k + 1) * iw];
                write_row(&layout, input, (r.0 as usize, r.1 as usize, r.2 as usize), x);
                inputs.apply(x);
                let y = &mut yb[k * sd..(k + 1) * sd];
                y.copy_from_slice(state_of(r));
                targets.apply(y);
            }
            let x: Tensor<2> = Tensor::from_data(TensorData::new(xb.clone(), [b, iw]), &ad);
            let y: Tensor<2> = Tensor::from_data(TensorData::new(yb.clone(), [b, sd]), &ad);
            let masks = (cfg.dropout > 0.0).then(|| {
                let m1 = Tensor::from_data(TensorData::new(mask(&mut rng, b * cfg.hidden), [b, cfg.hidden]), &ad);
                let m2 = Tensor::from_data(TensorData::new(mask(&mut rng, b * cfg.hidden), [b, cfg.hidden]), &ad);
                (m1, m2)
            });
            let loss = (model.forward(x, masks) - y).square().mean();
            // Reading the loss forces a host sync; only the tail is read (for the report),
            // plus a periodic finiteness check.
            if u + tail >= cfg.updates || u % 500 == 0 {
                let v: f32 = loss.clone().detach().into_scalar();
                if !v.is_finite() {
                    bail!(
                        "discriminator training diverged: loss {v} at update {} of {} (try a lower discriminator.lr)",
                        u + 1,
                        cfg.updates
                    );
                }
                if u + tail >= cfg.updates {
                    tail_sum += v as f64;
                    tail_n += 1;
                }
            }
            let grads = GradientsParams::from_grads(loss.backward(), &model);
            model = optim.step(cfg.lr, model, grads);
        }
        let seconds = start.elapsed().as_secs_f64();
        let report = TrainReport {
            updates: cfg.updates,
            train_episodes: train_episodes.len(),
            train_rows: rows.len(),
            seconds,
            ms_per_update: seconds * 1000.0 / cfg.updates as f64,
            final_loss: tail_sum / tail_n.max(1) as f64,
        };
        Ok((
            Discriminator { model: model.valid(), layout, inputs, targets, state_dim: sd, eval_batch: cfg.eval_batch, device: dev },
            report,
        ))
    }

    /// Input columns per row (see the module doc).
    pub fn input_width(&self) -> usize {
        self.layout.width()
    }

    /// Reconstructed states, in the state's own units, for every (episode, step, agent) row of
    /// `episodes` in that order (episode as listed, then step, then agent): `rows * state_dim`
    /// values. `input` must have the widths the discriminator was trained with.
    pub fn predict(&self, input: &DiscInput, episodes: &[usize]) -> Result<Vec<f32>> {
        input.check()?;
        let (want, got) = (self.layout, row_layout(input, self.layout.history));
        if want != got {
            let (w, g) = (want.dims, got.dims);
            bail!(
                "the discriminator was trained for {} agents, obs {}, {} actions, {} message columns, state {}; this input has {}, {}, {}, {}, {}",
                w.n_agents, w.obs_width, w.n_actions, want.messages, w.state_dim, g.n_agents, g.obs_width, g.n_actions, got.messages, g.state_dim
            );
        }
        if let Some(&e) = episodes.iter().find(|&&e| e >= input.data.episodes.len()) {
            bail!("episode {e} is out of range: the dataset has {} episodes", input.data.episodes.len());
        }
        let rows = rows_of(input.data, episodes);
        let (iw, sd) = (self.layout.width(), self.state_dim);
        let mut out = Vec::with_capacity(rows.len() * sd);
        let mut xb = Vec::new();
        for chunk in rows.chunks(self.eval_batch) {
            xb.clear();
            xb.resize(chunk.len() * iw, 0.0);
            for (k, r) in chunk.iter().enumerate() {
                let x = &mut xb[k * iw..(k + 1) * iw];
                write_row(&self.layout, input, (r.0 as usize, r.1 as usize, r.2 as usize), x);
                self.inputs.apply(x);
            }
            let x: Tensor<2> = Tensor::from_data(TensorData::new(xb.clone(), [chunk.len(), iw]), &self.device);
            let mut y: Vec<f32> = self.model.forward(x, None).into_data().try_into_vec::<f32>().expect("f32 predictions");
            for row in y.chunks_mut(sd) {
                self.targets.invert(row);
            }
            out.extend_from_slice(&y);
        }
        Ok(out)
    }
}
