//! Task relevance of each state dim, measured on the dataset B: how much the team's
//! return depends on the dim, as opposed to how hard agents find it to recover.
//!
//! A value model V(s) -> discounted return-to-go is fitted on B's training episodes (on the
//! standardised state; the rewards B's collecting policy earned, discounted with
//! [`RelevanceConfig::gamma`]). Two models are fitted on the same batches, an MLP and a linear
//! model, each kept at the point of its training where it best predicted a tenth of the
//! training episodes set aside; the MLP is used only where it predicted those clearly better:
//! on a small B (400 training episodes of LBF 8x8) the MLP can explain less than nothing on
//! held-out episodes, where a linear model still ranks the dims the return moves with.
//!
//! A dim's relevance is its *permutation importance* on held-out steps: the rise of the model's squared error when that dim's column is shuffled across the
//! steps (breaking its link to the return while keeping its distribution), as a fraction of
//! the held-out return's variance. 0 = the model does not use it; 0.05 = shuffling it costs 5%
//! of the return's variance. The held-out R^2 of the unshuffled model says whether the ranking
//! means anything: a model that explains nothing ranks nothing.
//!
//! Why this measure: it needs no gradient through the environment, works for any state layout
//! (positions, health, one-hot cells) and for nonlinear dependence (the distance between two
//! units), and it measures on episodes the model did not see. Its limits are said where it is
//! used: it reflects the collecting policy's returns, and correlated dims share their
//! importance (shuffling one of two copies costs little).
//!
//! [`measure_actions`] ranks the state dims by what the collecting policy's actions depend on
//! instead (linear models of each agent's action, the same units): where things are, where the
//! return's value model ranks how the episode goes.

use super::discriminator::{split_episodes, Standardize};
use anyhow::{bail, Result};
use burn::module::Module;
use burn::nn::Linear;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor, TensorData};
use lmac_learn::{init::linear, LearnRng};
use lmac_run::dataset::{Dataset, DatasetHeader, Trajectory};
use serde::{Deserialize, Serialize};

/// The value model and its measurement.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RelevanceConfig {
    /// Discount of the return-to-go the value model predicts (the learner's default, 0.99).
    pub gamma: f64,
    /// Width of the value model's two hidden layers.
    pub hidden: usize,
    /// Adam learning rate.
    pub lr: f64,
    /// Steps per update.
    pub batch_size: usize,
    /// Gradient updates.
    pub updates: usize,
    /// Fraction of episodes held out for the importance measurement.
    pub holdout_fraction: f64,
    /// Most held-out steps the importance is measured on (an even spread of them).
    pub max_eval_rows: usize,
}

impl Default for RelevanceConfig {
    fn default() -> Self {
        RelevanceConfig { gamma: 0.99, hidden: 64, lr: 1e-3, batch_size: 64, updates: 3000, holdout_fraction: 0.2, max_eval_rows: 4000 }
    }
}

impl RelevanceConfig {
    pub fn validate(&self) -> Result<()> {
        if !(0.0..=1.0).contains(&self.gamma) {
            bail!("relevance.gamma must be in [0, 1], got {}", self.gamma);
        }
        if self.hidden == 0 || self.batch_size == 0 || self.updates == 0 || self.max_eval_rows == 0 {
            bail!("relevance: hidden, batch_size, updates and max_eval_rows must be at least 1");
        }
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            bail!("relevance.lr must be a positive number, got {}", self.lr);
        }
        if !(self.holdout_fraction > 0.0 && self.holdout_fraction < 1.0) {
            bail!("relevance.holdout_fraction must be in (0, 1), got {}", self.holdout_fraction);
        }
        Ok(())
    }
}

/// How much better (in R^2 on the check episodes) the MLP must predict than the linear model to
/// be used: a check set of a few dozen episodes cannot tell the two apart more finely, and on
/// LBF 8x8 an MLP level with the linear model on its check episodes explained -34.5% of the
/// held-out ones.
const MLP_MARGIN: f64 = 0.05;

/// The value model: an MLP with two hidden layers, or (no `hidden`) a linear model.
#[derive(Module, Debug)]
struct ValueModel {
    hidden: Option<(Linear, Linear)>,
    out: Linear,
}

impl ValueModel {
    fn mlp(rng: &mut LearnRng, inputs: usize, width: usize, device: &Device) -> Self {
        let hidden = (linear(rng, inputs, width, device), linear(rng, width, width, device));
        ValueModel { hidden: Some(hidden), out: linear(rng, width, 1, device) }
    }

    fn linear(rng: &mut LearnRng, inputs: usize, device: &Device) -> Self {
        ValueModel { hidden: None, out: linear(rng, inputs, 1, device) }
    }

    fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        match &self.hidden {
            Some((l1, l2)) => self.out.forward(relu(l2.forward(relu(l1.forward(x))))),
            None => self.out.forward(x),
        }
    }

    fn kind(&self) -> ValueModelKind {
        if self.hidden.is_some() {
            ValueModelKind::Mlp
        } else {
            ValueModelKind::Linear
        }
    }
}

/// Which value model the relevance was measured with.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ValueModelKind {
    #[default]
    Mlp,
    Linear,
}

impl ValueModelKind {
    /// How the designer's summary names it.
    pub fn describe(self) -> &'static str {
        match self {
            ValueModelKind::Mlp => "an MLP",
            ValueModelKind::Linear => "a linear model",
        }
    }
}

/// Each state dim's relevance to the return on B.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Relevance {
    /// Permutation importance of each state dim (index = dim), >= 0.
    pub importance: Vec<f64>,
    /// Permutation importance of each group of columns shuffled together (the steps' rows
    /// move as one block): [`measure_joint_observation`]'s groups are the agents, so this is
    /// how much the return depends on all an agent sees, however its columns correlate.
    #[serde(default)]
    pub groups: Vec<f64>,
    /// [`measure_actions`] only: each agent's own importance of every state dim (what that
    /// agent's actions depend on), index [agent][dim]; empty for an agent with too few steps to
    /// fit, and empty altogether for the return's value model. `importance` is their mean.
    #[serde(default)]
    pub per_agent: Vec<Vec<f64>>,
    /// The value model's R^2 on the held-out steps (before any shuffling).
    pub held_out_r2: f64,
    /// The model measured with (the linear one unless the MLP predicted the check episodes
    /// clearly better).
    #[serde(default)]
    pub model: ValueModelKind,
    /// Each candidate's R^2 on the check episodes (a tenth of the training episodes, set aside
    /// to choose when to stop and which model to keep): (MLP, linear); empty on a B too small
    /// to set any aside (fewer than 10 training episodes), where the MLP is used.
    #[serde(default)]
    pub check_r2: Vec<(ValueModelKind, f64)>,
    pub gamma: f64,
    pub train_episodes: usize,
    pub held_out_episodes: usize,
    /// Held-out steps the importance was measured on.
    pub eval_rows: usize,
    pub seconds: f64,
}

impl Relevance {
    /// State dims by relevance, most relevant first (ties by index).
    pub fn ranking(&self) -> Vec<usize> {
        let mut d: Vec<usize> = (0..self.importance.len()).collect();
        d.sort_by(|&a, &b| self.importance[b].total_cmp(&self.importance[a]).then(a.cmp(&b)));
        d
    }

    /// Why this model: each candidate's R^2 on the check episodes, one sentence (empty when
    /// there was nothing to choose between).
    pub fn model_choice(&self) -> String {
        if self.check_r2.len() < 2 {
            return String::new();
        }
        let r2 = |k: ValueModelKind| self.check_r2.iter().find(|x| x.0 == k).map_or(f64::NAN, |x| x.1);
        format!(
            " Of the two value models fitted, the {} on the check episodes (a tenth of the training episodes, set aside): R^2 {:.1}% for the MLP, {:.1}% for the linear model.",
            match self.model {
                ValueModelKind::Mlp => format!("MLP is used: it predicted clearly better (by {:.0} points or more)", 100.0 * MLP_MARGIN),
                ValueModelKind::Linear =>
                    format!("linear model is used, the MLP not predicting clearly better (by {:.0} points or more)", 100.0 * MLP_MARGIN),
            },
            100.0 * r2(ValueModelKind::Mlp),
            100.0 * r2(ValueModelKind::Linear)
        )
    }

    /// 1-based rank of `dim` in [`Self::ranking`].
    pub fn rank_of(&self, dim: usize) -> usize {
        let v = self.importance.get(dim).copied().unwrap_or(0.0);
        1 + self.importance.iter().enumerate().filter(|&(d, &x)| x > v || (x == v && d < dim)).count()
    }
}

/// Discounted return-to-go of every step of episode `e`.
fn returns_to_go(data: &Dataset, e: usize, gamma: f64) -> Vec<f32> {
    let r = &data.episodes[e].reward;
    let mut g = vec![0f32; r.len()];
    let mut acc = 0f64;
    for t in (0..r.len()).rev() {
        acc = r[t] as f64 + gamma * acc;
        g[t] = acc as f32;
    }
    g
}

/// Fit the value model on B and measure every state dim's permutation importance.
pub fn measure(data: &Dataset, cfg: &RelevanceConfig, seed: u64) -> Result<Relevance> {
    measure_grouped(data, &[], cfg, seed)
}

/// [`measure`], and each group of state columns in `groups` shuffled together.
fn measure_grouped(data: &Dataset, groups: &[Vec<usize>], cfg: &RelevanceConfig, seed: u64) -> Result<Relevance> {
    let sd = data.header.state_dim;
    measure_on(data, sd, &|e, t| &data.episodes[e].state[t * sd..(t + 1) * sd], groups, cfg, seed)
}

/// The same measurement on the team's joint observation (every agent's observation side by
/// side, agent by agent: column j * obs_dim + d is agent j's o[d]): how much the return depends
/// on what each agent sees. Correlated columns share their importance, so what several agents
/// see alike ranks below what one agent alone sees (the offline designer's sender choice).
pub fn measure_joint_observation(data: &Dataset, cfg: &RelevanceConfig, seed: u64) -> Result<Relevance> {
    let (n, od) = (data.header.n_agents, data.header.obs_dim);
    let w = n * od;
    let agents: Vec<Vec<usize>> = (0..n).map(|j| (j * od..(j + 1) * od).collect()).collect();
    measure_on(data, w, &|e, t| &data.episodes[e].obs[t * w..(t + 1) * w], &agents, cfg, seed)
}

/// What one agent's observation adds, for the others, to predicting the team's return: the
/// held-out R^2 of a value model of the return-to-go on a receiver's own observation and the
/// sender's side by side, against one on the receiver's alone ([`receiver_return_gains`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReturnGain {
    pub sender: usize,
    pub r2_with: f64,
    pub r2_without: f64,
    /// Permutation importance of each of the sender's observation values in the model with
    /// them (index = observation dim): which of what it sees the receivers' prediction uses.
    pub sender_importance: Vec<f64>,
    /// Permutation importance of each of the sender's entities in that model (index = entity
    /// of the `entities` measured with), the entity's values shuffled together: correlated
    /// values of one thing (a unit's distance, offset and visibility) share their importance
    /// one by one, and count in full together.
    #[serde(default)]
    pub entity_importance: Vec<f64>,
}

impl ReturnGain {
    pub fn gain(&self) -> f64 {
        self.r2_with - self.r2_without
    }
}

/// The sender question asked of the task: for each agent j, how much its whole
/// observation, put beside another agent's own, raises a value model's held-out R^2 of the
/// return-to-go. Each episode of B is seen by one receiver i != j, the receivers taken in turn
/// over the episodes (so an episode is never in both the training and the held-out half, and
/// every receiver counts alike), with rows [o_i | o_j] against [o_i]; both models see the same
/// episodes and the same split. An agent that alone sees what the return depends on scores
/// high; one whose view the receivers share, or that sees nothing the return moves with, near 0.
/// `entities(j)` are runs of agent j's observation dims measured as groups too (the schema's
/// [`obs_entities_of`](lmac_shm_schema::schema::EnvSchema::obs_entities_of); may be empty).
pub fn receiver_return_gains(
    data: &Dataset,
    entities: impl Fn(usize) -> Vec<std::ops::Range<usize>>,
    cfg: &RelevanceConfig,
    seed: u64,
) -> Result<Vec<ReturnGain>> {
    let (n, od) = (data.header.n_agents, data.header.obs_dim);
    if n < 2 {
        bail!("relevance: a sender needs another agent to receive (the dataset has {n} agent)");
    }
    (0..n)
        .map(|j| {
            let entities = entities(j);
            if let Some(e) = entities.iter().find(|e| e.end > od || e.is_empty()) {
                bail!("relevance: entity {e:?} of agent {j} is not a run of the observation's {od} dims");
            }
            // The sender's entities, in the columns of [o_i | o_j].
            let groups: Vec<Vec<usize>> = entities.iter().map(|e| e.clone().map(|d| od + d).collect()).collect();
            let with = measure_grouped(&receiver_view(data, j, true), &groups, cfg, seed)?;
            let without = measure(&receiver_view(data, j, false), cfg, seed)?;
            Ok(ReturnGain {
                sender: j,
                r2_with: with.held_out_r2,
                r2_without: without.held_out_r2,
                sender_importance: with.importance[od..].to_vec(),
                entity_importance: with.groups,
            })
        })
        .collect::<Result<Vec<_>>>()
        .map_err(|e| {
            e.context(format!("relevance: measuring what each of the {n} agents' observation adds to the others' ({od} values each)"))
        })
}

/// B as receivers other than `j` see it, one receiver per episode in turn: each step's row is
/// the receiver's observation, then (`with_sender`) agent j's; rewards as in B.
fn receiver_view(data: &Dataset, j: usize, with_sender: bool) -> Dataset {
    let (n, od) = (data.header.n_agents, data.header.obs_dim);
    let receivers: Vec<usize> = (0..n).filter(|&i| i != j).collect();
    let w = if with_sender { 2 * od } else { od };
    let episodes = data
        .episodes
        .iter()
        .enumerate()
        .map(|(e, ep)| {
            let i = receivers[e % receivers.len()];
            let mut state = Vec::with_capacity(ep.len * w);
            for t in 0..ep.len {
                let obs = |a: usize| &ep.obs[(t * n + a) * od..(t * n + a + 1) * od];
                state.extend_from_slice(obs(i));
                if with_sender {
                    state.extend_from_slice(obs(j));
                }
            }
            Trajectory {
                len: ep.len,
                obs: Vec::new(),
                state,
                actions: Vec::new(),
                reward: ep.reward.clone(),
                terminated: ep.terminated,
                truncated: ep.truncated,
            }
        })
        .collect();
    Dataset { header: DatasetHeader { state_dim: w, ..data.header.clone() }, episodes }
}

/// [`measure`] on the rows `row(episode, step)` of width `sd`, and of each group of columns in
/// `groups` shuffled together.
fn measure_on<'a>(
    data: &'a Dataset,
    sd: usize,
    row: &dyn Fn(usize, usize) -> &'a [f32],
    groups: &[Vec<usize>],
    cfg: &RelevanceConfig,
    seed: u64,
) -> Result<Relevance> {
    cfg.validate()?;
    let (train, test) = split_episodes(data.episodes.len(), cfg.holdout_fraction, seed ^ 0x5E1E_0000_0000_0001)?;
    let start = std::time::Instant::now();
    let steps =
        |eps: &[usize]| -> Vec<(usize, usize)> { eps.iter().flat_map(|&e| (0..data.episodes[e].len).map(move |t| (e, t))).collect() };
    // Every 10th training episode checks the fit while it trains (the model kept is the one
    // that predicted those best): on a small B (400 training episodes) the full schedule
    // overfits, to a negative held-out R^2 on LBF 8x8's main-job dataset.
    let checked = |k: usize| train.len() >= 10 && k % 10 == 9;
    let fit: Vec<usize> = train.iter().enumerate().filter(|&(k, _)| !checked(k)).map(|(_, &e)| e).collect();
    let check: Vec<usize> = train.iter().enumerate().filter(|&(k, _)| checked(k)).map(|(_, &e)| e).collect();
    let (train_rows, test_rows, check_rows) = (steps(&fit), steps(&test), steps(&check));
    if train_rows.is_empty() || test_rows.is_empty() {
        bail!("relevance: the dataset's training or held-out episodes have no steps");
    }
    let g: Vec<Vec<f32>> = (0..data.episodes.len()).map(|e| returns_to_go(data, e, cfg.gamma)).collect();
    let state = |&(e, t): &(usize, usize)| row(e, t);
    let inputs = Standardize::fit(sd, train_rows.iter().map(|r| state(r).to_vec()));
    // The standardised rows of `rows`, side by side.
    let standardized = |rows: &[(usize, usize)]| -> Vec<f32> {
        let mut x = vec![0f32; rows.len() * sd];
        for (k, r) in rows.iter().enumerate() {
            let row = &mut x[k * sd..(k + 1) * sd];
            row.copy_from_slice(state(r));
            inputs.apply(row);
        }
        x
    };
    let ys: Vec<f64> = train_rows.iter().map(|&(e, t)| g[e][t] as f64).collect();
    let held_out_ys: Vec<f64> = test_rows.iter().map(|&(e, t)| g[e][t] as f64).collect();
    if lmac_learn::stats::variance(&ys) < 1e-12 || lmac_learn::stats::variance(&held_out_ys) < 1e-12 {
        // A constant return (no reward on B, or none in its held-out episodes): nothing
        // depends on any dim, and a held-out R^2 against no variance would be noise over ~0.
        return Ok(Relevance {
            importance: vec![0.0; sd],
            groups: vec![0.0; groups.len()],
            per_agent: Vec::new(),
            held_out_r2: 0.0,
            model: ValueModelKind::Mlp,
            check_r2: Vec::new(),
            gamma: cfg.gamma,
            train_episodes: train.len(),
            held_out_episodes: test.len(),
            eval_rows: 0,
            seconds: start.elapsed().as_secs_f64(),
        });
    }
    let y_mean = lmac_learn::stats::mean(&ys);
    let y_sd = lmac_learn::stats::variance(&ys).sqrt().max(1e-6);
    let target = |&(e, t): &(usize, usize)| ((g[e][t] as f64 - y_mean) / y_sd) as f32;

    let dev = Device::default();
    let ad = dev.clone().autodiff();
    let mut init_rng = LearnRng::seed_from(seed ^ 0x5E1E_0000_0000_0002);
    // The MLP first, so its initial weights are those it had when it was the only model.
    let mlp = ValueModel::mlp(&mut init_rng, sd, cfg.hidden, &ad);
    let mut models = vec![mlp, ValueModel::linear(&mut init_rng, sd, &ad)];
    if check_rows.is_empty() {
        // Nothing to choose between them on.
        models.truncate(1);
    }
    let mut optims: Vec<_> = models.iter().map(|_| AdamConfig::new().init()).collect();
    let mut rng = LearnRng::seed_from(seed ^ 0x5E1E_0000_0000_0003);
    let check_every = (cfg.updates / 12).max(1);
    let check_x: Tensor<2> = Tensor::from_data(TensorData::new(standardized(&check_rows), [check_rows.len(), sd]), &dev);
    let check_y: Vec<f32> = check_rows.iter().map(target).collect();
    let check_var = lmac_learn::stats::variance(&check_y.iter().map(|&y| y as f64).collect::<Vec<f64>>()).max(1e-12);
    let check_t: Tensor<2> = Tensor::from_data(TensorData::new(check_y, [check_rows.len(), 1]), &dev);
    // Per model: the lowest check error so far and the model at that point.
    let mut best: Vec<Option<(f32, ValueModel)>> = models.iter().map(|_| None).collect();
    let b = cfg.batch_size;
    let (mut xb, mut yb) = (vec![0f32; b * sd], vec![0f32; b]);
    for u in 0..cfg.updates {
        for k in 0..b {
            let r = &train_rows[rng.below(train_rows.len())];
            let x = &mut xb[k * sd..(k + 1) * sd];
            x.copy_from_slice(state(r));
            inputs.apply(x);
            yb[k] = target(r);
        }
        let x: Tensor<2> = Tensor::from_data(TensorData::new(xb.clone(), [b, sd]), &ad);
        let y: Tensor<2> = Tensor::from_data(TensorData::new(yb.clone(), [b, 1]), &ad);
        let checking = !check_rows.is_empty() && ((u + 1) % check_every == 0 || u + 1 == cfg.updates);
        for ((model, optim), best) in models.iter_mut().zip(optims.iter_mut()).zip(best.iter_mut()) {
            let loss = (model.forward(x.clone()) - y.clone()).square().mean();
            if u % 500 == 0 {
                let v: f32 = loss.clone().detach().into_scalar();
                if !v.is_finite() {
                    bail!("relevance: the value model diverged (loss {v} at update {u}); try a lower relevance.lr");
                }
            }
            let grads = GradientsParams::from_grads(loss.backward(), &*model);
            *model = optim.step(cfg.lr, model.clone(), grads);
            if checking {
                let m = model.valid();
                let err = m.forward(check_x.clone()) - check_t.clone();
                let v: f32 = err.square().mean().into_scalar();
                if best.as_ref().is_none_or(|(b, _)| v < *b) {
                    *best = Some((v, m));
                }
            }
        }
    }
    let check_r2: Vec<(ValueModelKind, f64)> =
        best.iter().zip(&models).filter_map(|(b, m)| b.as_ref().map(|(v, _)| (m.kind(), 1.0 - *v as f64 / check_var))).collect();
    // The MLP only where it predicted the check episodes better by MLP_MARGIN of their
    // variance; without check episodes, the MLP as trained.
    let model = match (best.pop().flatten(), best.pop().flatten()) {
        (Some((lin, lin_model)), Some((mlp, mlp_model))) => {
            if ((lin - mlp) as f64) / check_var > MLP_MARGIN {
                mlp_model
            } else {
                lin_model
            }
        }
        _ => models.swap_remove(0).valid(),
    };
    let kind = model.kind();

    // The held-out steps, an even spread of at most max_eval_rows.
    let stride = test_rows.len().div_ceil(cfg.max_eval_rows).max(1);
    let rows: Vec<(usize, usize)> = test_rows.iter().step_by(stride).copied().collect();
    let n = rows.len();
    let x = standardized(&rows);
    let y: Vec<f64> = rows.iter().map(|r| target(r) as f64).collect();
    let var_y = lmac_learn::stats::variance(&y).max(1e-12);
    let mse = |x: &[f32]| -> Result<f64> {
        let pred = model.forward(Tensor::from_data(TensorData::new(x.to_vec(), [n, sd]), &dev));
        let p: Vec<f32> = pred.into_data().try_into_vec::<f32>().map_err(|e| anyhow::anyhow!("relevance: reading predictions: {e:?}"))?;
        Ok(p.iter().zip(&y).map(|(&a, &b)| (a as f64 - b).powi(2)).sum::<f64>() / n as f64)
    };
    let base = mse(&x)?;
    // One shuffle of the rows, the same for every dim (so the dims are compared on one footing).
    let mut perm: Vec<usize> = (0..n).collect();
    let mut prng = LearnRng::seed_from(seed ^ 0x5E1E_0000_0000_0004);
    for i in (1..n).rev() {
        perm.swap(i, prng.below(i + 1));
    }
    let mut importance = Vec::with_capacity(sd);
    let mut shuffled = x.clone();
    for d in 0..sd {
        for k in 0..n {
            shuffled[k * sd + d] = x[perm[k] * sd + d];
        }
        importance.push(((mse(&shuffled)? - base) / var_y).max(0.0));
        for k in 0..n {
            shuffled[k * sd + d] = x[k * sd + d];
        }
    }
    let mut group_importance = Vec::with_capacity(groups.len());
    for g in groups {
        for k in 0..n {
            for &d in g {
                shuffled[k * sd + d] = x[perm[k] * sd + d];
            }
        }
        group_importance.push(((mse(&shuffled)? - base) / var_y).max(0.0));
        shuffled.copy_from_slice(&x);
    }
    Ok(Relevance {
        importance,
        groups: group_importance,
        per_agent: Vec::new(),
        held_out_r2: 1.0 - base / var_y,
        model: kind,
        check_r2,
        gamma: cfg.gamma,
        train_episodes: train.len(),
        held_out_episodes: test.len(),
        eval_rows: n,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// What the collecting policy's actions depend on: for each agent, a ridge-regularised linear
/// model of its action (one-hot) on the standardised state, fitted on B's training episodes at
/// the steps where the agent observes anything (a dead agent's forced no-op would otherwise
/// make its health the first thing its actions depend on); a dim's importance is the expected
/// share of the held-out action variance lost when the dim is shuffled (for a linear model,
/// 2 x its coefficients' squares x its held-out variance), averaged over the agents. Where the
/// return's value model ranks how the episode is going (a unit's health), this ranks what an
/// agent must know to act (where the units are), when B's policy could see it: a policy that
/// cannot see the state acts on it only through what it observes. The importance is in the
/// same units as [`measure`]'s (shares of a held-out variance), and `held_out_r2` is the
/// agents' mean held-out R^2 of their actions.
pub fn measure_actions(data: &Dataset, cfg: &RelevanceConfig, seed: u64) -> Result<Relevance> {
    cfg.validate()?;
    let start = std::time::Instant::now();
    let (train, test) = split_episodes(data.episodes.len(), cfg.holdout_fraction, seed ^ 0x5E1E_0000_0000_0011)?;
    let DatasetHeader { n_agents: n, obs_dim: od, state_dim: sd, n_actions: na, .. } = data.header.clone();
    // The (episode, step) rows where agent i observes anything.
    let rows = |eps: &[usize], i: usize| -> Vec<(usize, usize)> {
        eps.iter()
            .flat_map(|&e| (0..data.episodes[e].len).map(move |t| (e, t)))
            .filter(|&(e, t)| data.episodes[e].obs[(t * n + i) * od..(t * n + i + 1) * od].iter().any(|&v| v != 0.0))
            .collect()
    };
    let state = |(e, t): (usize, usize)| &data.episodes[e].state[t * sd..(t + 1) * sd];
    let train_rows: Vec<Vec<(usize, usize)>> = (0..n).map(|i| rows(&train, i)).collect();
    let norm = Standardize::fit(sd, train_rows.iter().flatten().map(|&r| state(r).to_vec()));
    // The standardised state of each row, row after row.
    let standardized = |rows: &[(usize, usize)]| -> Vec<f64> {
        let mut x = vec![0f32; sd];
        let mut out = Vec::with_capacity(rows.len() * sd);
        for &r in rows {
            x.copy_from_slice(state(r));
            norm.apply(&mut x);
            out.extend(x.iter().map(|&v| f64::from(v)));
        }
        out
    };
    let mut importance = vec![0f64; sd];
    let mut per_agent = vec![Vec::new(); n];
    let (mut r2_sum, mut fitted, mut eval_rows) = (0f64, 0usize, 0usize);
    for (i, tr) in train_rows.iter().enumerate() {
        let te = rows(&test, i);
        if tr.len() < 2 || te.len() < 2 {
            continue;
        }
        let action = |(e, t): (usize, usize)| data.episodes[e].actions[t * n + i].clamp(0, na as i32 - 1) as usize;
        let (xtr, xte) = (standardized(tr), standardized(&te));
        // Centred normal equations: (X'X / m + ridge I) B = X'Y / m.
        let m = tr.len() as f64;
        let (mut xm, mut ym) = (vec![0f64; sd], vec![0f64; na]);
        for (&r, x) in tr.iter().zip(xtr.chunks_exact(sd)) {
            xm.iter_mut().zip(x).for_each(|(a, v)| *a += v / m);
            ym[action(r)] += 1.0 / m;
        }
        let (mut xx, mut xy) = (vec![0f64; sd * sd], vec![0f64; sd * na]);
        for (&r, x) in tr.iter().zip(xtr.chunks_exact(sd)) {
            let x: Vec<f64> = x.iter().zip(&xm).map(|(v, mu)| v - mu).collect();
            let a = action(r);
            for p in 0..sd {
                if x[p] == 0.0 {
                    continue;
                }
                for q in 0..sd {
                    xx[p * sd + q] += x[p] * x[q] / m;
                }
                for k in 0..na {
                    xy[p * na + k] += x[p] * ((k == a) as u8 as f64 - ym[k]) / m;
                }
            }
        }
        for p in 0..sd {
            xx[p * sd + p] += 1e-3;
        }
        let Some(beta) = solve_spd(&mut xx, sd, &xy, na) else { continue };
        // Held out: R^2 of the actions, and each dim's variance there.
        let mut sse = 0f64;
        let mut sst = 0f64;
        let (mut sum, mut sq) = (vec![0f64; sd], vec![0f64; sd]);
        for (&r, x) in te.iter().zip(xte.chunks_exact(sd)) {
            let a = action(r);
            for k in 0..na {
                let pred = ym[k] + (0..sd).map(|p| (x[p] - xm[p]) * beta[p * na + k]).sum::<f64>();
                let y = (k == a) as u8 as f64;
                sse += (y - pred).powi(2);
                sst += (y - ym[k]).powi(2);
            }
            for p in 0..sd {
                sum[p] += x[p];
                sq[p] += x[p] * x[p];
            }
        }
        if sst < 1e-12 {
            continue;
        }
        let mt = te.len() as f64;
        let own: Vec<f64> = (0..sd)
            .map(|p| {
                let var = (sq[p] / mt - (sum[p] / mt).powi(2)).max(0.0);
                let b2: f64 = (0..na).map(|k| beta[p * na + k].powi(2)).sum();
                2.0 * b2 * var * mt / sst
            })
            .collect();
        importance.iter_mut().zip(&own).for_each(|(a, x)| *a += x);
        per_agent[i] = own;
        r2_sum += 1.0 - sse / sst;
        fitted += 1;
        eval_rows += te.len();
    }
    if fitted == 0 {
        bail!("action relevance: no agent has steps to fit its actions on in both B's training and held-out episodes");
    }
    importance.iter_mut().for_each(|x| *x /= fitted as f64);
    Ok(Relevance {
        importance,
        groups: Vec::new(),
        per_agent,
        held_out_r2: r2_sum / fitted as f64,
        model: ValueModelKind::Linear,
        check_r2: Vec::new(),
        gamma: cfg.gamma,
        train_episodes: train.len(),
        held_out_episodes: test.len(),
        eval_rows,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Solve A X = B for a symmetric positive definite `a` (p x p, overwritten by its Cholesky
/// factor) and `b` (p x k); None when `a` is not positive definite.
fn solve_spd(a: &mut [f64], p: usize, b: &[f64], k: usize) -> Option<Vec<f64>> {
    for j in 0..p {
        let d = a[j * p + j] - (0..j).map(|l| a[j * p + l].powi(2)).sum::<f64>();
        if d <= 1e-12 {
            return None;
        }
        let d = d.sqrt();
        a[j * p + j] = d;
        for i in j + 1..p {
            let v = a[i * p + j] - (0..j).map(|l| a[i * p + l] * a[j * p + l]).sum::<f64>();
            a[i * p + j] = v / d;
        }
    }
    let mut x = b.to_vec();
    for c in 0..k {
        // L y = b, then L' x = y.
        for i in 0..p {
            let v = x[i * k + c] - (0..i).map(|l| a[i * p + l] * x[l * k + c]).sum::<f64>();
            x[i * k + c] = v / a[i * p + i];
        }
        for i in (0..p).rev() {
            let v = x[i * k + c] - (i + 1..p).map(|l| a[l * p + i] * x[l * k + c]).sum::<f64>();
            x[i * k + c] = v / a[i * p + i];
        }
    }
    Some(x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use lmac_run::dataset::{DatasetHeader, Trajectory};

    /// A dataset of `episodes` with these sizes (2 actions, random policy).
    fn synthetic(n_agents: usize, obs_dim: usize, state_dim: usize, len: usize, episodes: Vec<Trajectory>) -> Dataset {
        let header = DatasetHeader {
            env: "synthetic".into(),
            n_agents,
            obs_dim,
            state_dim,
            n_actions: 2,
            episode_limit: len,
            protocol: String::new(),
            policy: "random".into(),
            seed: 0,
        };
        Dataset { header, episodes }
    }

    /// Two agents move towards a target (action 1 when it is to their right, 2 when to their
    /// left) and take the no-op (0) when dead (their observation all zero, their health 0).
    /// Their actions depend on the target's x first (both agents), then each agent's own x;
    /// not on the noise dim, and not on health, which only the dead steps' no-op follows.
    #[test]
    fn actions_rank_where_the_target_is_not_how_the_episode_goes() {
        let (n, od, sd, len) = (2, 1, 5, 20);
        let mut rng = LearnRng::seed_from(3);
        let episodes: Vec<Trajectory> = (0..150)
            .map(|_| {
                let (mut obs, mut state, mut actions) = (Vec::new(), Vec::new(), Vec::new());
                let dies_at = [rng.below(len * 2), rng.below(len * 2)];
                for t in 0..len {
                    let target = rng.uniform() * 2.0 - 1.0;
                    let x = [rng.uniform() * 2.0 - 1.0, rng.uniform() * 2.0 - 1.0];
                    let alive = [t < dies_at[0], t < dies_at[1]];
                    let health = (alive[0] as u8 + alive[1] as u8) as f32;
                    state.extend([target, x[0], x[1], rng.uniform(), health]);
                    for i in 0..n {
                        obs.push(if alive[i] { 1.0 } else { 0.0 });
                        actions.push(if !alive[i] {
                            0
                        } else if target > x[i] {
                            1
                        } else {
                            2
                        });
                    }
                }
                Trajectory { len, obs, state, actions, reward: vec![0.0; len], terminated: true, truncated: false }
            })
            .collect();
        let mut data = synthetic(n, od, sd, len, episodes);
        data.header.n_actions = 3;
        let r = measure_actions(&data, &RelevanceConfig::default(), 0).unwrap();
        assert_eq!(r.ranking()[0], 0, "{r:?}");
        assert!(r.importance[1] > 0.05 && r.importance[2] > 0.05, "{r:?}");
        assert!(r.importance[3] < 0.01 && r.importance[4] < 0.01, "{r:?}");
        assert!(r.held_out_r2 > 0.3, "{r:?}");
        // Each agent's own dependence: agent 0 acts on its own x (dim 1), not on agent 1's.
        let own = &r.per_agent;
        assert!(own[0][1] > 5.0 * own[0][2] && own[1][2] > 5.0 * own[1][1], "{own:?}");
        for d in 0..sd {
            assert!((r.importance[d] - (own[0][d] + own[1][d]) / 2.0).abs() < 1e-12, "the mean over agents");
        }
    }

    /// A dataset whose reward depends on state dim 1 only (dims 0 and 2 are noise of the same
    /// scale): dim 1 must rank first, with most of the importance, and the model must fit.
    #[test]
    fn the_dim_the_return_depends_on_ranks_first() {
        let (sd, len) = (3, 20);
        let mut rng = LearnRng::seed_from(7);
        let episodes: Vec<Trajectory> = (0..120)
            .map(|_| {
                let state: Vec<f32> = (0..len * sd).map(|_| rng.uniform() * 2.0 - 1.0).collect();
                let reward: Vec<f32> = (0..len).map(|t| if state[t * sd + 1] > 0.0 { 1.0 } else { 0.0 }).collect();
                Trajectory { len, obs: vec![0.0; len * 2], state, actions: vec![0; len * 2], reward, terminated: true, truncated: false }
            })
            .collect();
        let data = synthetic(2, 1, sd, len, episodes);
        // gamma 0: the target is the step's own reward, a step function of dim 1.
        let cfg = RelevanceConfig { gamma: 0.0, updates: 1500, ..Default::default() };
        let r = measure(&data, &cfg, 3).unwrap();
        assert_eq!(r.ranking()[0], 1, "{r:?}");
        assert!(r.held_out_r2 > 0.5, "{r:?}");
        assert!(r.importance[1] > 5.0 * (r.importance[0] + r.importance[2]), "{r:?}");
        assert_eq!(r.rank_of(1), 1);
        // Deterministic for a seed.
        assert_eq!(measure(&data, &cfg, 3).unwrap().importance, r.importance);
    }

    /// Three agents, the reward depends on agent 2's o[0]: what agent 2 sees adds to the others'
    /// prediction of the return; what agents 0 and 1 see (noise) adds nothing.
    #[test]
    fn the_agent_whose_view_the_return_needs_adds_most_for_the_others() {
        let (n, od, len) = (3, 2, 20);
        let mut rng = LearnRng::seed_from(13);
        let episodes: Vec<Trajectory> = (0..150)
            .map(|_| {
                let obs: Vec<f32> = (0..len * n * od).map(|_| rng.uniform() * 2.0 - 1.0).collect();
                let reward: Vec<f32> = (0..len).map(|t| obs[(t * n + 2) * od]).collect();
                Trajectory { len, obs, state: vec![0.0; len], actions: vec![0; len * n], reward, terminated: true, truncated: false }
            })
            .collect();
        let data = synthetic(n, od, 1, len, episodes);
        let g =
            receiver_return_gains(&data, |_| Vec::new(), &RelevanceConfig { gamma: 0.0, updates: 1500, ..Default::default() }, 4).unwrap();
        assert_eq!(g.iter().map(|x| x.sender).collect::<Vec<_>>(), vec![0, 1, 2]);
        assert!(g[2].gain() > 0.5, "{g:?}");
        assert!(g[0].gain() < 0.2 && g[1].gain() < 0.2, "{g:?}");
        // Half of agent 0's episodes are seen by agent 2, who needs nothing from it.
        assert!(g[0].r2_without > 0.2 && g[0].r2_with < g[0].r2_without + 0.2, "{g:?}");
        // Of agent 2's view, the receivers' model uses its o[0].
        assert_eq!(g[2].sender_importance.len(), od);
        assert!(g[2].sender_importance[0] > 5.0 * g[2].sender_importance[1], "{g:?}");
    }

    /// Agent 2 sees the value the return follows three times over, each copy noisy (one thing:
    /// its entity o[0..3]), and a second value with half the weight (o[3], an entity of its
    /// own): one by one the copies share their importance and each ranks below o[3]; shuffled
    /// together the entity ranks first.
    #[test]
    fn an_entity_counts_in_full_what_its_values_share() {
        let (n, od, len) = (3, 4, 20);
        let mut rng = LearnRng::seed_from(17);
        let mut u = move || rng.uniform() * 2.0 - 1.0;
        let episodes: Vec<Trajectory> = (0..200)
            .map(|_| {
                let mut obs = Vec::with_capacity(len * n * od);
                let mut reward = Vec::with_capacity(len);
                for _ in 0..len {
                    let (x, z) = (u(), u());
                    obs.extend((0..2 * od).map(|_| u()));
                    obs.extend((0..3).map(|_| x + 0.3 * u()));
                    obs.push(z);
                    reward.push(x + 0.6 * z);
                }
                Trajectory { len, obs, state: vec![0.0; len], actions: vec![0; len * n], reward, terminated: true, truncated: false }
            })
            .collect();
        let data = synthetic(n, od, 1, len, episodes);
        let cfg = RelevanceConfig { gamma: 0.0, updates: 2000, ..Default::default() };
        let g = receiver_return_gains(&data, |_| vec![0..3, 3..4], &cfg, 6).unwrap();
        let (v, e) = (&g[2].sender_importance, &g[2].entity_importance);
        assert_eq!(e.len(), 2);
        assert!(v[0].max(v[1]).max(v[2]) < v[3], "one by one a copy ranks below o[3]: {g:?}");
        assert!(e[0] > 1.5 * e[1], "together the copies rank first: {g:?}");
        let e = format!("{:#}", receiver_return_gains(&data, |_| vec![3..5], &cfg, 6).unwrap_err());
        assert!(e.contains("entity 3..5 of agent 0 is not a run of the observation's 4 dims"), "{e}");
    }

    /// A return that moves linearly with dim 2, plus noise, on few episodes: the linear model
    /// is used (the MLP cannot predict the check episodes clearly better), says so, and ranks
    /// dim 2 first; each candidate's check R^2 is reported.
    #[test]
    fn a_linear_return_on_few_episodes_is_measured_with_the_linear_model() {
        let (sd, len) = (4, 10);
        let mut rng = LearnRng::seed_from(5);
        let episodes: Vec<Trajectory> = (0..60)
            .map(|_| {
                let state: Vec<f32> = (0..len * sd).map(|_| rng.uniform() * 2.0 - 1.0).collect();
                let reward: Vec<f32> = (0..len).map(|t| state[t * sd + 2] + 0.3 * (rng.uniform() - 0.5)).collect();
                Trajectory { len, obs: vec![0.0; len * 2], state, actions: vec![0; len * 2], reward, terminated: true, truncated: false }
            })
            .collect();
        let data = synthetic(2, 1, sd, len, episodes);
        let r = measure(&data, &RelevanceConfig { gamma: 0.0, updates: 1500, ..Default::default() }, 9).unwrap();
        assert_eq!(r.model, ValueModelKind::Linear, "{r:?}");
        assert_eq!(r.ranking()[0], 2, "{r:?}");
        assert!(r.held_out_r2 > 0.8, "{r:?}");
        assert_eq!(r.check_r2.iter().map(|x| x.0).collect::<Vec<_>>(), vec![ValueModelKind::Mlp, ValueModelKind::Linear]);
        assert!(r.model_choice().contains("linear model is used"), "{}", r.model_choice());
    }

    /// The joint observation: the reward depends on agent 1's o[0]; agent 0's two values and
    /// agent 1's o[1] are noise. Agent 1 ranks first as a group, its o[0] first as a column.
    #[test]
    fn the_agent_that_sees_what_the_return_depends_on_ranks_first() {
        let (n, od, len) = (2, 2, 20);
        let mut rng = LearnRng::seed_from(11);
        let episodes: Vec<Trajectory> = (0..120)
            .map(|_| {
                let obs: Vec<f32> = (0..len * n * od).map(|_| rng.uniform() * 2.0 - 1.0).collect();
                let reward: Vec<f32> = (0..len).map(|t| if obs[(t * n + 1) * od] > 0.0 { 1.0 } else { 0.0 }).collect();
                Trajectory { len, obs, state: vec![0.0; len], actions: vec![0; len * n], reward, terminated: true, truncated: false }
            })
            .collect();
        let data = synthetic(n, od, 1, len, episodes);
        let cfg = RelevanceConfig { gamma: 0.0, updates: 1500, ..Default::default() };
        let r = measure_joint_observation(&data, &cfg, 3).unwrap();
        assert_eq!(r.importance.len(), n * od);
        assert_eq!(r.ranking()[0], od, "agent 1's o[0] is column {od}: {r:?}");
        assert_eq!(r.groups.len(), n);
        assert!(r.groups[1] > 5.0 * r.groups[0], "{r:?}");
        // The group holds at least what its best column does.
        assert!(r.groups[1] >= 0.9 * r.importance[od], "{r:?}");
    }
}
