//! The communication baselines' extra losses reduce as `docs/reference/fidelity.md` says: each test
//! recomputes a term from the network's public pieces (or from weights set so the term has a
//! closed form) and checks the default (the papers' losses over the trained steps) and the
//! setting that gives the released code's reduction.

use burn::module::Param;
use burn::tensor::{Device, Int, Tensor, TensorData};
use lmac_learn::episode::EpisodeDims;
use lmac_learn::methods::maic::{EntropyAttention, MaicAgent, MaicConfig, MaicSettings, MiPairs};
use lmac_learn::methods::ndq::{NdqAgent, NdqConfig, NdqSettings};
use lmac_learn::methods::{leaky_relu, AgentConfig, AgentNet, AuxTerm, StepActions, TrainContext};
use lmac_learn::{InputLayout, LearnConfig, LearnRng};

const DIMS: EpisodeDims = EpisodeDims { n_agents: 3, obs_width: 4, state_dim: 5, n_actions: 4 };
const T: usize = 4;
const B: usize = 2;
/// Time-major [T * B]: environment 0 trains steps 0-2 (row 3 is the row after a truncated
/// episode's last step), environment 1 trains step 0 only (rows 1-3 are padding).
const MASK: [f32; T * B] = [1., 1., 1., 0., 1., 0., 0., 0.];
/// The released pymarl learners' batch ends at the longest episode: 3 steps here.
const LONGEST: usize = 3;

fn net(cfg: AgentConfig) -> AgentNet {
    let learn = LearnConfig::default();
    AgentNet::new(&mut LearnRng::seed_from(5), &cfg, &InputLayout::new(DIMS, &learn), &learn, &Device::default())
}

fn ndq(settings: NdqSettings) -> NdqAgent {
    match net(AgentConfig::Ndq(NdqConfig { settings })) {
        AgentNet::Ndq(a) => a,
        other => panic!("not NDQ: {other:?}"),
    }
}

fn maic(settings: MaicSettings) -> MaicAgent {
    match net(AgentConfig::Maic(MaicConfig { settings })) {
        AgentNet::Maic(a) => a,
        other => panic!("not MAIC: {other:?}"),
    }
}

/// Random inputs per step, random taken actions, and the context over `MASK`.
fn data() -> (Vec<Tensor<2>>, TrainContext, Vec<i64>) {
    let device = Device::default();
    let width = InputLayout::new(DIMS, &LearnConfig::default()).width();
    let mut rng = LearnRng::seed_from(17);
    let rows = B * DIMS.n_agents;
    let inputs = (0..T)
        .map(|_| {
            let v: Vec<f32> = (0..rows * width).map(|_| rng.uniform() * 2.0 - 1.0).collect();
            Tensor::from_data(TensorData::new(v, [rows, width]), &device)
        })
        .collect();
    let taken: Vec<i64> = (0..T * rows).map(|_| (rng.uniform() * DIMS.n_actions as f32) as i64 % DIMS.n_actions as i64).collect();
    let taken_t: Tensor<2, Int> = Tensor::from_data(TensorData::new(taken.clone(), [T, rows]), &device);
    let ctx = TrainContext {
        state: Tensor::zeros([T * B, DIMS.state_dim], &device),
        mask: Tensor::from_data(TensorData::new(MASK.to_vec(), [T * B]), &device),
        mask_sum: MASK.iter().sum(),
        b: B,
        batch_episodes: B,
        n_agents: DIMS.n_agents,
        seed: 3,
        actions: Some(StepActions::new(taken_t.clone(), taken_t)),
        reward: Some(Tensor::zeros([T * B], &device)),
    };
    (inputs, ctx, taken)
}

fn term(terms: &[AuxTerm], name: &str) -> f32 {
    terms.iter().find(|t| t.name == name).unwrap_or_else(|| panic!("no {name}")).value
}

fn close(got: f32, want: f64, what: &str) {
    assert!((got as f64 - want).abs() <= 1e-4 * want.abs().max(1e-3), "{what}: got {got}, want {want}");
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().iter::<f32>().collect()
}

/// NDQ's KL term, KL(N(mu, 1) || N(0, 1)) = |mu|^2 / 2 summed over an agent's message dims and
/// over the agents, divided by the count of trained steps: over the trained steps by default,
/// over every step up to the longest episode with `mask_losses = false` (the released learner
/// sums over its padded batch). Before the setting, the released reduction was not available.
#[test]
fn ndq_losses_count_the_trained_steps_unless_told_to_sum_over_the_padded_batch() {
    assert!(NdqSettings::default().mask_losses, "the default is the mean over real data");
    let (inputs, ctx, _) = data();
    let n = DIMS.n_agents;
    // Per (t, b): the KL of its agents' messages, from the message encoder itself.
    let a = ndq(NdqSettings::default());
    let mut per_step = vec![0.0f64; T * B];
    for (ti, u) in inputs.iter().enumerate() {
        let mu = host(a.message_means(u.clone()));
        let width = mu.len() / (B * n);
        for bi in 0..B {
            let rows = &mu[bi * n * width..(bi + 1) * n * width];
            per_step[ti * B + bi] = rows.iter().map(|&m| 0.5 * (m as f64).powi(2)).sum();
        }
    }
    let denom: f64 = MASK.iter().map(|&m| m as f64).sum();
    let masked: f64 = per_step.iter().zip(MASK).map(|(k, m)| k * m as f64).sum::<f64>() / denom;
    let released: f64 = per_step[..LONGEST * B].iter().sum::<f64>() / denom;
    assert!(released > masked * 1.2, "the padding weighs: {released} vs {masked}");

    let kl = |mask_losses: bool| {
        let a = ndq(NdqSettings { mask_losses, ..NdqSettings::default() });
        term(&a.unroll(inputs.clone(), Some(&ctx)).1, "ndq_kl")
    };
    close(kl(true), masked, "masked KL");
    close(kl(false), released, "released KL");
}

/// MAIC's MI term, recomputed from the network's layers: KL(N(mu_ij, var_ij) || q(z | h_i,
/// a_j)) summed over the latent dims, averaged over the teammate pairs i != j and the trained
/// steps by default; over all n^2 pairs (`mi_pairs = "all"`) and every step of the batch
/// (`mask_losses = false`) as the released code does.
#[test]
fn maic_mi_averages_over_teammates_and_trained_steps_unless_told_to_reduce_as_released() {
    let d = MaicSettings::default();
    assert!(d.mask_losses && d.mi_pairs == MiPairs::Teammates, "the defaults are the paper's loss over real data");
    let (inputs, ctx, taken) = data();
    let device = Device::default();
    let (n, a_n, l) = (DIMS.n_agents, DIMS.n_actions, d.latent_dim);
    let a = maic(d.clone());
    let rows_mask = |per: usize| -> Tensor<3> {
        let v: Vec<f32> = MASK.iter().flat_map(|&m| std::iter::repeat_n(m, per)).collect();
        Tensor::from_data(TensorData::new(v, [T, B * per, 1]), &device)
    };
    // The teammate models and the inference net, as the module builds them in training (batch
    // statistics of the trained rows).
    let h = a.agent.hidden_states(&inputs); // [T, B n, H]
    let hd = h.dims()[2];
    let e = a.embed_norm.forward_masked(a.embed1.forward(h.clone()), rows_mask(n), false);
    let e = a.embed2.forward(leaky_relu(e, 0.01));
    let mu = host(e.clone().narrow(2, 0, n * l)); // [T, B, i, j, L]
    let var = host(e.narrow(2, n * l, n * l).exp().clamp_min(d.var_floor));
    let hi = h.reshape([T, B, n, 1, hd]).expand([T, B, n, n, hd]);
    let onehot: Vec<f32> =
        (0..T * B * n * n * a_n).map(|k| (taken[(k / a_n / (n * n)) * n + (k / a_n) % n] == (k % a_n) as i64) as u8 as f32).collect();
    let onehot: Tensor<5> = Tensor::from_data(TensorData::new(onehot, [T, B, n, n, a_n]), &device);
    let x = Tensor::cat(vec![hi, onehot], 4).reshape([T, B * n * n, hd + a_n]);
    let x = a.infer_norm.forward_masked(a.infer1.forward(x), rows_mask(n * n), false);
    let x = host(a.infer2.forward(leaky_relu(x, 0.01))); // [T, B, i, j, 2L]
    let kl = |step: usize, i: usize, j: usize| -> f64 {
        (0..l)
            .map(|k| {
                let p = (step * n * n + i * n + j) * l + k;
                let q = (step * n * n + i * n + j) * 2 * l;
                let (m1, v1) = (mu[p] as f64, var[p] as f64);
                let (m2, v2) = (x[q + k] as f64, (x[q + l + k] as f64).exp().max(d.var_floor as f64));
                0.5 * (v2 / v1).ln() + (v1 + (m1 - m2).powi(2)) / (2.0 * v2) - 0.5
            })
            .sum()
    };
    let sum = |teammates_only: bool, masked: bool| -> f64 {
        let mut s = 0.0;
        for step in 0..T * B {
            let w = if masked { MASK[step] as f64 } else { 1.0 };
            for i in 0..n {
                for j in (0..n).filter(|&j| !teammates_only || j != i) {
                    s += w * kl(step, i, j);
                }
            }
        }
        s
    };
    let trained: f64 = MASK.iter().map(|&m| m as f64).sum();
    let paper = sum(true, true) / (trained * (n * (n - 1)) as f64);
    let released = sum(false, false) / ((T * B) as f64 * (n * n) as f64);

    let mi = |mi_pairs: MiPairs, mask_losses: bool| {
        let a = maic(MaicSettings { mi_pairs, mask_losses, ..d.clone() });
        term(&a.unroll(inputs.clone(), Some(&ctx)).1, "maic_mi")
    };
    close(mi(MiPairs::Teammates, true), paper, "the paper's MI over trained steps");
    close(mi(MiPairs::All, false), released, "the released MI");
    assert!((paper - released).abs() > 1e-3 * paper, "the two reductions differ on this batch: {paper} vs {released}");
}

/// MAIC's entropy term with keys that ignore the latent (W_k = 0): every agent's scores are
/// equal, so the attention is uniform. Over the teammates (the attention the messages use) that
/// is log2(n - 1) bits per agent; the released recomputation (unscaled, the agent itself among
/// the candidates) gives log2(n).
#[test]
fn maic_entropy_reads_the_attention_used_unless_told_to_recompute_it_as_released() {
    assert_eq!(MaicSettings::default().entropy_attention, EntropyAttention::Used);
    let (inputs, ctx, _) = data();
    let n = DIMS.n_agents as f64;
    let entropy = |entropy_attention: EntropyAttention, mask_losses: bool| {
        let mut a = maic(MaicSettings { entropy_attention, mask_losses, ..MaicSettings::default() });
        let w = a.key.weight.val();
        a.key.weight = Param::from_tensor(w.zeros_like());
        term(&a.unroll(inputs.clone(), Some(&ctx)).1, "maic_entropy")
    };
    for mask_losses in [true, false] {
        close(entropy(EntropyAttention::Used, mask_losses), (n - 1.0).log2(), "over the teammates");
        close(entropy(EntropyAttention::Released, mask_losses), n.log2(), "over all agents");
    }
}
