//! The unrolls batch over time what does not depend on the recurrence.
//! Each is checked here against a plain per-step reference written out in this file: the
//! Q-values, the method's logged terms and the gradient of every parameter of one loss, to 1e-5.
//! The LMAC case trains with dropout, so the reference also pins the dropout draw order.

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::activation::{relu, sigmoid, softmax};
use burn::tensor::{Device, Tensor, TensorData};
use lmac_learn::agent::RnnAgent;
use lmac_learn::episode::EpisodeDims;
use lmac_learn::methods::lmac::module::{Encoder, GruGateEncoder, WindowEncoder};
use lmac_learn::methods::lmac::{EncoderKind, LmacAgent, LmacConfig, LmacSettings};
use lmac_learn::methods::{dropout, AgentConfig, AgentNet, AuxTerm, TrainContext};
use lmac_learn::{InputLayout, LearnConfig, LearnRng};

const TOL: f32 = 1e-5;
const DIMS: EpisodeDims = EpisodeDims { n_agents: 3, obs_width: 8, state_dim: 6, n_actions: 5 };

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec::<f32>().unwrap()
}

fn assert_close(what: &str, a: &[f32], b: &[f32]) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!((x - y).abs() <= TOL * x.abs().max(1.0), "{what}: element {i}: {x} vs reference {y}");
    }
}

/// Every parameter's gradient (flattened, in visiting order; zeros when it got none).
fn param_grads<M: Module>(m: &M, grads: &GradientsParams) -> Vec<(String, Vec<f32>)> {
    struct V<'a>(&'a GradientsParams, Vec<(String, Vec<f32>)>);
    impl ModuleVisitor for V<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            let g = match self.0.get::<D>(p.id) {
                Some(g) => values(g),
                None => vec![0.0; p.val().dims().iter().product()],
            };
            self.1.push((format!("parameter {} {:?}", self.1.len(), p.val().dims()), g));
        }
    }
    let mut v = V(grads, Vec::new());
    m.visit(&mut v);
    v.1
}

/// A loss that weighs every Q-value differently (so no gradient cancels), plus the extra losses.
fn loss(q: Tensor<3>, aux: &[AuxTerm]) -> Tensor<1> {
    let [t, n, a] = q.dims();
    let w: Vec<f32> = (0..t * n * a).map(|i| ((i * 7) % 11) as f32 / 11.0 - 0.4).collect();
    let w: Tensor<3> = Tensor::from_data(TensorData::new(w, [t, n, a]), &q.device());
    let mut l = (q * w).sum();
    for term in aux {
        if let Some(x) = &term.loss {
            l = l + x.clone();
        }
    }
    l
}

fn inputs(t: usize, rows: usize, width: usize, seed: u64, device: &Device) -> Vec<Tensor<2>> {
    let mut rng = LearnRng::seed_from(seed);
    (0..t)
        .map(|_| {
            let v: Vec<f32> = (0..rows * width).map(|_| rng.uniform() * 2.0 - 1.0).collect();
            Tensor::from_data(TensorData::new(v, [rows, width]), device)
        })
        .collect()
}

/// Plain RNN agent reference: the acting step, once per time step.
fn rnn_reference(agent: &RnnAgent, inputs: Vec<Tensor<2>>) -> Tensor<3> {
    let n = inputs[0].dims()[0];
    let mut h: Tensor<2> = Tensor::zeros([n, agent.hidden_dim], &inputs[0].device());
    let mut qs = Vec::new();
    for x in inputs {
        let (q, h2) = agent.step(x, h);
        h = h2;
        qs.push(q);
    }
    Tensor::stack(qs, 0)
}

#[test]
fn the_rnn_unroll_equals_the_per_step_reference_in_values_and_gradients() {
    let device = Device::default().autodiff();
    let agent = RnnAgent::new(&mut LearnRng::seed_from(3), 12, 16, 5, &device);
    for t in [1, 7] {
        let xs = inputs(t, 6, 12, 11, &device);
        let q = agent.unroll(xs.clone());
        let r = rnn_reference(&agent, xs);
        assert_close(&format!("T={t}: Q"), &values(q.clone()), &values(r.clone()));
        let g = GradientsParams::from_grads(loss(q, &[]).backward(), &agent);
        let gr = GradientsParams::from_grads(loss(r, &[]).backward(), &agent);
        for ((name, a), (_, b)) in param_grads(&agent, &g).iter().zip(&param_grads(&agent, &gr)) {
            assert_close(&format!("T={t}: gradient of {name}"), a, b);
        }
    }
}

// ---- LMAC: the module's forward written step by step, as the acting step computes it.

fn ref_embed(a: &LmacAgent, u: Tensor<2>, rng: Option<&mut LearnRng>) -> Tensor<2> {
    let x = relu(a.embed2.forward(a.norm.forward(relu(a.embed1.forward(u)))));
    match rng {
        Some(r) => dropout(x, a.cfg.settings.dropout, r),
        None => x,
    }
}

/// The gate on the carried state c = h + x.
fn ref_gate(g: &GruGateEncoder, x: Tensor<2>, c: Tensor<2>) -> Tensor<2> {
    let r = c;
    let score = sigmoid((g.query.forward(x) * g.key.forward(r.clone())).sum_dim(1));
    g.value.forward(r) * score
}

/// Attention of step t's embedding to entries t, t-1, .. t-W+1 (those before the first step
/// masked), one entry at a time.
fn ref_window(w: &WindowEncoder, xs: &[Tensor<2>], t: usize) -> Tensor<2> {
    let n = xs[t].dims()[0];
    let a = w.query.weight.dims()[1];
    let (h, dh) = (w.heads, a / w.heads);
    let q = w.query.forward(xs[t].clone()).reshape([n, h, dh]);
    let zero: Tensor<2> = Tensor::zeros(xs[t].dims(), &xs[t].device());
    let mut scores = Vec::new();
    let mut vals = Vec::new();
    for o in 0..w.window {
        if o <= t {
            let k = w.key.forward(xs[t - o].clone()).reshape([n, h, dh]);
            scores.push((k * q.clone()).sum_dim(2).reshape([n, h]).div_scalar((dh as f32).sqrt()));
            vals.push(w.value.forward(xs[t - o].clone()).reshape([n, h, dh]));
        } else {
            scores.push(Tensor::full([n, h], -1e9, &xs[t].device()));
            vals.push(w.value.forward(zero.clone()).reshape([n, h, dh]));
        }
    }
    let att = softmax(Tensor::stack::<3>(scores, 0), 0); // [W, n, h]
    let mut out: Tensor<3> = Tensor::zeros([n, h, dh], &xs[t].device());
    for (o, v) in vals.into_iter().enumerate() {
        out = out + att.clone().narrow(0, o, 1).reshape([n, h, 1]) * v;
    }
    w.out.forward(out.reshape([n, a]))
}

fn ref_latent(a: &LmacAgent, inputs: &[Tensor<2>], mut rng: Option<&mut LearnRng>) -> Vec<Tensor<2>> {
    let xs: Vec<Tensor<2>> = inputs.iter().map(|u| ref_embed(a, u.clone(), rng.as_deref_mut())).collect();
    match &a.encoder {
        Encoder::GruGate(g) => {
            let mut h: Tensor<2> = Tensor::zeros(xs[0].dims(), &xs[0].device());
            xs.iter()
                .map(|x| {
                    // the released code carries h + x to the next step
                    h = g.gru.forward(x.clone(), h.clone()) + x.clone();
                    ref_gate(g, x.clone(), h.clone())
                })
                .collect()
        }
        Encoder::Window(w) => (0..xs.len()).map(|t| ref_window(w, &xs, t)).collect(),
    }
}

fn ref_unroll(a: &LmacAgent, inputs: Vec<Tensor<2>>, train: Option<&TrainContext>) -> (Tensor<3>, Vec<AuxTerm>) {
    let mut rng = train.map(|c| LearnRng::seed_from(c.seed ^ 0xD80F_0000_0000_0001));
    let zs = ref_latent(a, &inputs, rng.as_mut());
    let n = inputs[0].dims()[0];
    let (m, obs) = (a.cfg.msg_cols, a.obs_dim);
    let mut h: Tensor<2> = Tensor::zeros([n, a.agent.hidden_dim], &inputs[0].device());
    let mut qs = Vec::new();
    for (u, z) in inputs.into_iter().zip(&zs) {
        let own = if a.cfg.settings.raw_messages {
            u
        } else {
            Tensor::cat(vec![u.clone().narrow(1, 0, obs), u.clone().narrow(1, obs + m, a.in_width - obs - m)], 1)
        };
        let z = if a.cfg.settings.td_to_encoder { z.clone() } else { z.clone().detach() };
        let (q, h2) = a.agent.step(Tensor::cat(vec![own, z], 1), h);
        h = h2;
        qs.push(q);
    }
    let aux = match train {
        Some(ctx) => a.losses(Tensor::stack(zs, 0), ctx),
        None => Vec::new(),
    };
    (Tensor::stack(qs, 0), aux)
}

fn lmac_agent(settings: LmacSettings, device: &Device) -> LmacAgent {
    let learn = LearnConfig::default();
    let layout = InputLayout::new(DIMS, &learn);
    let cfg = LmacConfig { settings, msg_cols: 3, alpha: 0.05, critical_dims: vec![0, 2, 5] };
    match AgentNet::new(&mut LearnRng::seed_from(4), &AgentConfig::Lmac(cfg), &layout, &learn, device) {
        AgentNet::Lmac(a) => a,
        other => panic!("not an LMAC agent: {other:?}"),
    }
}

#[test]
fn the_lmac_unroll_equals_the_per_step_reference_in_values_terms_and_gradients() {
    let device = Device::default().autodiff();
    let width = InputLayout::new(DIMS, &LearnConfig::default()).width();
    let b = 2;
    let rows = b * DIMS.n_agents;
    for (encoder, td_to_encoder, raw_messages) in [
        (EncoderKind::GruGate, false, false),
        (EncoderKind::GruGate, true, true),
        (EncoderKind::Window, false, false),
        (EncoderKind::Window, true, false),
    ] {
        let settings = LmacSettings {
            encoder,
            td_to_encoder,
            raw_messages,
            window: 3,
            heads: 2,
            attention_dim: 8,
            dropout: 0.3,
            ..LmacSettings::default()
        };
        let a = lmac_agent(settings, &device);
        // Shorter than, as long as and longer than the window.
        for t in [2, 3, 6] {
            let case = format!("{encoder:?} td_to_encoder={td_to_encoder} T={t}");
            let xs = inputs(t, rows, width, 21 + t as u64, &device);
            let mut rng = LearnRng::seed_from(t as u64);
            let state: Vec<f32> = (0..t * b * DIMS.state_dim).map(|_| rng.uniform() - 0.5).collect();
            let mask: Vec<f32> = (0..t * b).map(|i| if i + 1 == t * b { 0.0 } else { 1.0 }).collect();
            let ctx = TrainContext {
                state: Tensor::from_data(TensorData::new(state, [t * b, DIMS.state_dim]), &device),
                mask: Tensor::from_data(TensorData::new(mask.clone(), [t * b]), &device),
                mask_sum: mask.iter().sum::<f32>().max(1.0),
                b,
                batch_episodes: b,
                n_agents: DIMS.n_agents,
                seed: 7,
                actions: None,
                reward: None,
            };
            // Deterministic (acting, target network) and in training (dropout, extra losses).
            for train in [None, Some(&ctx)] {
                let what = format!("{case} train={}", train.is_some());
                let (q, aux) = a.unroll(xs.clone(), train);
                let (rq, raux) = ref_unroll(&a, xs.clone(), train);
                assert_close(&format!("{what}: Q"), &values(q.clone()), &values(rq.clone()));
                let names: Vec<&str> = aux.iter().map(|x| x.name).collect();
                assert_eq!(names, raux.iter().map(|x| x.name).collect::<Vec<_>>(), "{what}");
                assert_close(
                    &format!("{what}: logged terms"),
                    &aux.iter().map(|x| x.value).collect::<Vec<_>>(),
                    &raux.iter().map(|x| x.value).collect::<Vec<_>>(),
                );
                let g = GradientsParams::from_grads(loss(q, &aux).backward(), &a);
                let gr = GradientsParams::from_grads(loss(rq, &raux).backward(), &a);
                let (g, gr) = (param_grads(&a, &g), param_grads(&a, &gr));
                assert!(g.iter().any(|(_, v)| v.iter().any(|&x| x != 0.0)), "{what}: some gradient");
                for ((name, x), (_, y)) in g.iter().zip(&gr) {
                    assert_close(&format!("{what}: gradient of {name}"), x, y);
                }
            }
            // The per-step latents as the tests and tools read them.
            let z: Vec<f32> = a.latent(&xs, None).into_iter().flat_map(values).collect();
            let rz: Vec<f32> = ref_latent(&a, &xs, None).into_iter().flat_map(values).collect();
            assert_close(&format!("{case}: latent"), &z, &rz);
        }
    }
}
