//! The LMAC module: the meta target and the reconstruction error as specified, a consistency
//! loss of zero when the cycle encoder inverts the decoder exactly, gradients that reach
//! exactly the parameters each option says, dropout only in training unless asked, the consistency loss's
//! reduction and reward standardisation.

use burn::module::{Module, Param};
use burn::nn::Linear;
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};
use lmac_learn::episode::EpisodeDims;
use lmac_learn::methods::lmac::{AuxLayout, LmacAgent, LmacConfig, LmacSettings};
use lmac_learn::methods::{AgentConfig, AgentNet, TrainContext};
use lmac_learn::{InputLayout, LearnConfig, LearnRng};

const DIMS: EpisodeDims = EpisodeDims { n_agents: 2, obs_width: 7, state_dim: 5, n_actions: 3 };

fn config(edit: impl FnOnce(&mut LmacSettings)) -> LmacConfig {
    let mut settings = LmacSettings { dropout: 0.0, ..LmacSettings::default() };
    edit(&mut settings);
    LmacConfig { settings, msg_cols: 3, alpha: 0.05, critical_dims: vec![0, 2, 4] }
}

fn agent(cfg: &LmacConfig, device: &Device) -> LmacAgent {
    let learn = LearnConfig::default();
    let layout = InputLayout::new(DIMS, &learn);
    match AgentNet::new(&mut LearnRng::seed_from(3), &AgentConfig::Lmac(cfg.clone()), &layout, &learn, device) {
        AgentNet::Lmac(a) => a,
        other => panic!("not an LMAC agent: {other:?}"),
    }
}

/// T steps of B episodes: inputs per step [B * n, in], the state and the mask per (t, b).
fn data(t: usize, b: usize, mask: &[f32], device: &Device) -> (Vec<Tensor<2>>, TrainContext, Vec<f32>) {
    let width = InputLayout::new(DIMS, &LearnConfig::default()).width();
    let mut rng = LearnRng::seed_from(17);
    let inputs = (0..t)
        .map(|_| {
            let v: Vec<f32> = (0..b * DIMS.n_agents * width).map(|_| rng.uniform() * 2.0 - 1.0).collect();
            Tensor::from_data(TensorData::new(v, [b * DIMS.n_agents, width]), device)
        })
        .collect();
    let state: Vec<f32> = (0..t * b * DIMS.state_dim).map(|_| rng.uniform() * 0.6 - 0.3).collect();
    let ctx = TrainContext {
        state: Tensor::from_data(TensorData::new(state.clone(), [t * b, DIMS.state_dim]), device),
        mask: Tensor::from_data(TensorData::new(mask.to_vec(), [t * b]), device),
        mask_sum: mask.iter().sum::<f32>().max(1.0),
        b,
        batch_episodes: b,
        n_agents: DIMS.n_agents,
        seed: 1,
        actions: None,
        reward: None,
    };
    (inputs, ctx, state)
}

fn term(terms: &[lmac_learn::methods::AuxTerm], name: &str) -> f32 {
    terms.iter().find(|t| t.name == name).unwrap_or_else(|| panic!("no {name}")).value
}

#[test]
fn the_meta_target_and_the_reconstruction_error_follow_the_definition() {
    let device = Device::default();
    let cfg = config(|_| {});
    let a = agent(&cfg, &device);
    let (t, b) = (4, 3);
    let mask = [1., 1., 1., 1., 1., 1., 1., 0., 1., 1., 0., 0.]; // [t, b]: padded steps at the end
    let (inputs, ctx, state) = data(t, b, &mask, &device);
    let z = Tensor::stack(a.latent(&inputs, None), 0);
    let (s_hat, _) = a.decode(z.clone());
    let s_hat = s_hat.into_data().try_into_vec::<f32>().unwrap();
    let terms = a.losses(z, &ctx);
    // On the host: rows (t, b, agent), critical dims 0, 2, 4.
    let (n, dc) = (DIMS.n_agents, 3);
    let (mut sq_sum, mut hits, mut count) = (0.0f64, 0usize, 0usize);
    for ti in 0..t {
        for bi in 0..b {
            if mask[ti * b + bi] == 0.0 {
                continue;
            }
            for ag in 0..n {
                for (k, &d) in cfg.critical_dims.iter().enumerate() {
                    let pred = s_hat[((ti * b + bi) * n + ag) * dc + k];
                    let err = (pred - state[(ti * b + bi) * DIMS.state_dim + d]).powi(2);
                    sq_sum += err as f64;
                    hits += (err <= cfg.alpha as f32) as usize;
                    count += 1;
                }
            }
        }
    }
    let (mse, recovered) = (sq_sum / count as f64, hits as f64 / count as f64);
    assert!((term(&terms, "lmac_recon_mse") as f64 - mse).abs() < 1e-5, "mse {} vs {mse}", term(&terms, "lmac_recon_mse"));
    assert!((term(&terms, "lmac_recovered") as f64 - recovered).abs() < 1e-5, "xi {} vs {recovered}", term(&terms, "lmac_recovered"));
    assert!(recovered > 0.0 && recovered < 1.0, "the case exercises both sides of alpha: {recovered}");
}

fn set(l: &mut Linear, w: Vec<f32>, d_in: usize, d_out: usize, device: &Device) {
    l.weight = Param::from_tensor(Tensor::from_data(TensorData::new(w, [d_in, d_out]), device));
    l.bias = Some(Param::from_tensor(Tensor::zeros([d_out], device)));
}

#[test]
fn the_consistency_loss_is_zero_when_the_cycle_encoder_inverts_the_decoder() {
    let device = Device::default();
    // Latent 3 = critical dims 3, hidden 6: the decoder computes s_hat = relu(z) - relu(-z) = z and
    // a constant reliability; the cycle encoder reads s_hat back the same way.
    let cfg = config(|s| {
        s.latent_dim = 3;
        s.decoder_hidden = 6;
        s.aux_layout = AuxLayout::Compact;
    });
    let mut a = agent(&cfg, &device);
    let (l, h) = (3, 6);
    let split = |rows: usize| -> Vec<f32> {
        // [rows, 6]: row i -> +1 at column i, -1 at column 3 + i (rows beyond 3 are zero)
        let mut w = vec![0.0; rows * h];
        for i in 0..l.min(rows) {
            w[i * h + i] = 1.0;
            w[i * h + l + i] = -1.0;
        }
        w
    };
    let join: Vec<f32> = (0..h)
        .flat_map(|r| {
            (0..l).map(move |c| {
                if r == c {
                    1.0
                } else if r == c + l {
                    -1.0
                } else {
                    0.0
                }
            })
        })
        .collect();
    let ident: Vec<f32> = (0..h * h).map(|k| if k / h == k % h { 1.0 } else { 0.0 }).collect();
    set(&mut a.dec1, split(l), l, h, &device);
    set(&mut a.dec2, ident, h, h, &device);
    set(&mut a.dec_state, join.clone(), h, l, &device);
    set(&mut a.dec_meta, vec![0.0; h * l], h, l, &device);
    set(&mut a.cycle1, split(2 * l), 2 * l, h, &device); // the reliability half has zero weights
    set(&mut a.cycle2, join, h, l, &device);
    let mut rng = LearnRng::seed_from(2);
    let z: Tensor<3> =
        Tensor::from_data(TensorData::new((0..2 * 4 * l).map(|_| rng.uniform() * 4.0 - 2.0).collect::<Vec<f32>>(), [2, 4, l]), &device);
    let (s_hat, xi) = a.decode(z.clone());
    let z_hat = a.cycle(s_hat, xi);
    let err: f32 = (z_hat - z.clone()).square().sum().into_scalar();
    assert!(err < 1e-10, "||z_hat - z||^2 = {err}");
    // The same through the loss: a module with these weights has L_cons = 0 on any batch.
    let (inputs, ctx, _) = data(2, 2, &[1.0; 4], &device);
    let z = Tensor::stack(a.latent(&inputs, None), 0);
    assert!(term(&a.losses(z, &ctx), "lmac_cons") < 1e-10);
}

/// How many parameters of `m` got a non-zero gradient, and how many it has.
fn reached<M: Module>(m: &M, grads: &GradientsParams) -> (usize, usize) {
    struct V<'a>(&'a GradientsParams, usize, usize);
    impl burn::module::ModuleVisitor for V<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            self.2 += 1;
            if self.0.get::<D>(p.id).is_some_and(|g| g.abs().sum().into_scalar::<f32>() > 0.0) {
                self.1 += 1;
            }
        }
    }
    let mut v = V(grads, 0, 0);
    m.visit(&mut v);
    (v.1, v.2)
}

#[test]
fn gradients_reach_exactly_the_parameters_each_option_says() {
    let device = Device::default().autodiff();
    let all = |m: (usize, usize)| m.0 == m.1;
    let none = |m: (usize, usize)| m.0 == 0;
    for td_to_encoder in [false, true] {
        let a = agent(&config(|s| s.td_to_encoder = td_to_encoder), &device);
        let (inputs, ctx, _) = data(3, 2, &[1.0; 6], &device);
        // The TD side: Q-values alone.
        let (q, _) = a.unroll(inputs.clone(), None);
        let g = GradientsParams::from_grads(q.sum().backward(), &a);
        assert!(all(reached(&a.agent, &g)), "TD reaches the agent network");
        for (what, r) in [("embedding", reached(&a.embed1, &g)), ("encoder", reached(&a.encoder, &g))] {
            assert_eq!(!none(r), td_to_encoder, "TD reaches the {what} iff td_to_encoder ({td_to_encoder}): {r:?}");
        }
        assert!(none(reached(&a.dec1, &g)) && none(reached(&a.cycle1, &g)), "TD never reaches the decoder or the cycle encoder");
        // The representation side: the weighted extra losses alone.
        let (_, terms) = a.unroll(inputs, Some(&ctx));
        let loss = terms.into_iter().filter_map(|t| t.loss).reduce(|x, y| x + y).unwrap();
        let g = GradientsParams::from_grads(loss.backward(), &a);
        assert!(none(reached(&a.agent, &g)), "the module's losses never reach the agent network");
        for (what, r) in [
            ("embedding", reached(&a.embed1, &g)),
            ("encoder", reached(&a.encoder, &g)),
            ("decoder", reached(&a.dec1, &g)),
            ("state head", reached(&a.dec_state, &g)),
            ("meta head", reached(&a.dec_meta, &g)),
            ("cycle encoder", reached(&a.cycle2, &g)),
        ] {
            assert!(all(r), "the module's losses reach the {what}: {r:?}");
        }
    }
    // Without the consistency loss, nothing trains the cycle encoder.
    let a = agent(&config(|s| s.lambda_cons = 0.0), &device);
    let (inputs, ctx, _) = data(3, 2, &[1.0; 6], &device);
    let (_, terms) = a.unroll(inputs, Some(&ctx));
    let loss = terms.into_iter().filter_map(|t| t.loss).reduce(|x, y| x + y).unwrap();
    let g = GradientsParams::from_grads(loss.backward(), &a);
    assert!(none(reached(&a.cycle1, &g)) && none(reached(&a.cycle2, &g)), "w/o consistency: the cycle encoder gets no gradient");
}

#[test]
fn dropout_acts_in_training_updates_only() {
    let device = Device::default();
    let a = agent(&config(|s| s.dropout = 0.5), &device);
    let (inputs, mut ctx, _) = data(3, 2, &[1.0; 6], &device);
    let plain = |a: &LmacAgent| Tensor::stack::<3>(a.latent(&inputs, None), 0).into_data().try_into_vec::<f32>().unwrap();
    assert_eq!(plain(&a), plain(&a), "without training the module is deterministic");
    let mse = |ctx: &TrainContext| term(&a.unroll(inputs.clone(), Some(ctx)).1, "lmac_recon_mse");
    let first = mse(&ctx);
    assert_eq!(first, mse(&ctx), "the same update seed draws the same units");
    ctx.seed = 2;
    assert_ne!(first, mse(&ctx), "another update draws other units");
}

/// `dropout_when_acting` (the released code's modules, never in eval mode): acting and the
/// target network draw units from their own seeds; without it both are the deterministic module.
#[test]
fn dropout_acts_when_acting_and_in_the_target_network_only_when_asked() {
    let device = Device::default();
    let values = |t: Tensor<2>| t.into_data().try_into_vec::<f32>().unwrap();
    let values3 = |t: Tensor<3>| t.into_data().try_into_vec::<f32>().unwrap();
    let (inputs, _, _) = data(3, 2, &[1.0; 6], &device);
    for when_acting in [false, true] {
        let a = agent(&config(|s| (s.dropout, s.dropout_when_acting) = (0.5, when_acting)), &device);
        let state = Tensor::<2>::zeros([inputs[0].dims()[0], a.state_width()], &device);
        let net = AgentNet::Lmac(a.clone());
        let acting = |seed: u64| values(net.step_drawing(inputs[0].clone(), state.clone(), &mut LearnRng::seed_from(seed)).0);
        let target = |seed: u64| values3(net.unroll_target(inputs.clone(), seed));
        let plain_step = values(a.step(inputs[0].clone(), state.clone()).0);
        let plain_unroll = values3(a.unroll(inputs.clone(), None).0);
        assert_eq!(acting(1), acting(1), "a seed fixes the acting draws");
        assert_eq!(target(1), target(1), "a seed fixes the target network's draws");
        if when_acting {
            assert_ne!(acting(1), acting(2), "acting draws other units from another seed");
            assert_ne!(acting(1), plain_step, "acting drops units out");
            assert_ne!(target(1), target(2), "the target network draws other units from another seed");
            assert_ne!(target(1), plain_unroll, "the target network drops units out");
        } else {
            assert_eq!(acting(1), plain_step, "acting is the deterministic module");
            assert_eq!(target(1), plain_unroll, "the target network is the deterministic module");
        }
    }
}

/// Whether dropout acts when acting is a test-time setting (`lmac evaluate --set`); the
/// module's other settings are not.
#[test]
fn dropout_when_acting_can_change_for_a_trained_network_and_nothing_else_can() {
    let device = Device::default();
    let trained = config(|s| s.dropout = 0.1);
    let mut net = AgentNet::Lmac(agent(&trained, &device));
    let on = config(|s| (s.dropout, s.dropout_when_acting) = (0.1, true));
    net.retune(&AgentConfig::Lmac(trained.clone()), &AgentConfig::Lmac(on)).unwrap();
    assert!(matches!(&net, AgentNet::Lmac(a) if a.drops_out_when_acting()));
    let other = config(|s| (s.dropout, s.window) = (0.1, 4));
    let err = net.retune(&AgentConfig::Lmac(trained), &AgentConfig::Lmac(other)).unwrap_err();
    assert!(err.contains("method.dropout_when_acting (lmac)") && err.contains("window"), "{err}");
}

#[test]
fn the_consistency_loss_averages_over_the_latent_unless_told_to_sum() {
    use lmac_learn::methods::lmac::LatentReduction;
    let device = Device::default();
    let (inputs, ctx, _) = data(3, 2, &[1., 1., 1., 1., 0., 1.], &device);
    let cons = |r: LatentReduction| {
        let a = agent(&config(|s| s.consistency_over_latent = r), &device);
        let z = Tensor::stack(a.latent(&inputs, None), 0);
        term(&a.losses(z, &ctx), "lmac_cons")
    };
    let (mean, sum) = (cons(LatentReduction::Mean), cons(LatentReduction::Sum));
    let latent = LmacSettings::default().latent_dim as f32;
    assert!(mean > 0.0, "an untrained cycle encoder does not invert the decoder");
    assert!((sum - latent * mean).abs() <= 1e-4 * sum, "sum {sum} = {latent} x mean {mean}");
}

/// Rewards in the TD targets: raw by default for every method; LMAC with
/// `method.standardise_rewards = true` (its released config) standardises them, QMIX never by
/// its own choice; `released` folds the padding's zero rewards into the statistics,
/// `valid-steps` only the real steps.
#[test]
fn lmac_standardises_rewards_over_valid_steps_when_asked_and_qmix_does_not() {
    use lmac_learn::episode::Episode;
    use lmac_learn::methods::{self, MethodContext};
    use lmac_learn::{Learner, RewardStandardisation};
    let dims = EpisodeDims { n_agents: 2, obs_width: 6, state_dim: 4, n_actions: 3 };
    let ctx = MethodContext { msg_cols: 2, alpha: 0.1, critical_dims: vec![0, 1], state_dim: 4 };
    let count_after_one_update = |algo: &str, standardise: RewardStandardisation| {
        let (algo, settings) = match algo.strip_suffix("+std") {
            Some(a) => (a, toml::toml! { standardise_rewards = true }),
            None => (algo, toml::Table::new()),
        };
        let spec = methods::method(algo).unwrap();
        let agent = (spec.configure)(&settings, &ctx).unwrap();
        let learn = LearnConfig { batch_size: 2, buffer_size: 2, reward_standardisation: standardise, ..LearnConfig::default() };
        let mut l = Learner::with_agent(dims, learn, agent, Device::default()).unwrap();
        let mut rng = LearnRng::seed_from(1);
        // lengths 3 and 5: the batch is padded to 5 steps, 8 of its 10 rows are real
        for len in [3, 5] {
            let mut ep = Episode::synthetic(&dims, len, &mut rng, true);
            ep.reward = (0..len).map(|i| i as f32 * 2.0 + 1.0).collect();
            l.add_episode(ep).unwrap();
        }
        l.train_step().unwrap();
        l.counters().reward_stats
    };
    let prior = lmac_learn::RewardStats::default();
    assert_eq!(count_after_one_update("qmix", RewardStandardisation::Method), prior, "QMIX keeps raw rewards");
    assert_eq!(count_after_one_update("lmac", RewardStandardisation::Method), prior, "LMAC keeps raw rewards by default");
    let valid = count_after_one_update("lmac+std", RewardStandardisation::Method);
    assert!((valid.count - prior.count - 8.0).abs() < 1e-9, "LMAC's released config folds in the 8 real steps: {valid:?}");
    // rewards 1,3,5 and 1,3,5,7,9: mean 34/8
    assert!((valid.mean - 34.0 / 8.0 * 8.0 / (8.0 + prior.count)).abs() < 1e-6, "{valid:?}");
    let released = count_after_one_update("lmac", RewardStandardisation::Released);
    assert!((released.count - prior.count - 10.0).abs() < 1e-9, "released: the 2 padded steps too: {released:?}");
    let off = count_after_one_update("lmac", RewardStandardisation::Off);
    assert_eq!(off, prior, "off: raw rewards");
}
