//! The suite every method of `learn::methods::REGISTRY` passes (a new method gets it by its
//! registry line): output shapes and named extra losses, padded steps that change nothing,
//! a checkpoint round trip, acting step by step equal to the training unroll, and gradients
//! reaching every parameter.

use burn::module::{Module, ModuleVisitor, Param, ParamId};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};
use lmac_run::episode::{Episode, EpisodeDims};
use lmac_run::learn::methods::{lmac::EncoderKind, AgentConfig, MethodContext, REGISTRY};
use lmac_run::learn::{Batch, Controller, InputLayout, LearnConfig, LearnRng, Learner, RowParts};

const DIMS: EpisodeDims = EpisodeDims { n_agents: 3, obs_width: 9, state_dim: 6, n_actions: 4 };
const MSG_COLS: usize = 4;

/// Every registered method, plus the variants worth checking on their own.
fn cases() -> Vec<(String, LearnConfig, AgentConfig)> {
    let ctx = MethodContext { msg_cols: MSG_COLS, alpha: 0.1, critical_dims: vec![1, 3, 4], state_dim: DIMS.state_dim };
    let mut out = Vec::new();
    let mut tables = vec![(String::new(), toml::Table::new())];
    for (name, extra) in [
        ("window", "encoder = \"window\"\nwindow = 3\nheads = 2\nattention_dim = 8"),
        ("td-raw", "td_to_encoder = true\nraw_messages = true"),
        ("smac-weights", "c_beta = 0.1\ncomm_beta = 1e-4\nentropy_beta = 0.0\nmsg_dim = 2"),
        ("released", "message_input = \"receiver\"\nbatch_norm = \"batch\"\nmi_action = \"greedy\""),
        ("frozen-selector", "selector = \"frozen\"\nown_weight = 2.0\nattention_dim = 8"),
        ("hidden-input", "input = \"hidden\"\nclasses = 3\nembed_dim = 2"),
        // MASIA: the momentum copy refreshed after every update (so the round trip checks it is
        // saved), and one step of latent prediction with a narrower latent.
        ("momentum-ema", "momentum_interval = 1\nmomentum_tau = 0.5"),
        ("one-step-ahead", "pred_len = 1\nlatent_dim = 3\nmomentum_interval = 1"),
    ] {
        tables.push((name.to_string(), toml::from_str(extra).unwrap()));
    }
    for spec in REGISTRY {
        for (variant, table) in &tables {
            let agent = match (spec.configure)(table, &ctx) {
                Ok(a) => a,
                Err(_) if !variant.is_empty() => continue, // a variant of another method
                Err(e) => panic!("{}: {e}", spec.name),
            };
            let mut learn = LearnConfig { batch_size: 4, buffer_size: 16, seed: 5, qplex_num_kernel: 2, ..LearnConfig::default() };
            if let Some(m) = spec.mixer {
                learn.mixer = m;
            }
            learn.agent_sees_state = spec.agent_sees_state;
            out.push((format!("{} {variant}", spec.name), learn, agent));
        }
    }
    assert!(out.iter().any(|c| matches!(&c.2, AgentConfig::Lmac(l) if l.settings.encoder == EncoderKind::Window)));
    // The communication baselines, default and variants; NDQ once more with the target network
    // unrolled on a second thread (its inference loss then waits for the target's greedy actions).
    for want in [
        "ndq ",
        "ndq smac-weights",
        "maic ",
        "maic released",
        "t2mac ",
        "t2mac frozen-selector",
        "cola ",
        "cola hidden-input",
        "masia ",
        "masia momentum-ema",
        "masia one-step-ahead",
    ] {
        assert!(out.iter().any(|c| c.0 == want), "no case {want:?}");
    }
    let mut parallel = out.iter().find(|c| c.0 == "ndq ").cloned().expect("ndq case");
    parallel.0 = "ndq parallel-target".into();
    parallel.1.parallel_target = true;
    out.push(parallel);
    out
}

fn episode(rng: &mut LearnRng, len: usize) -> Episode {
    let mut ep = Episode::synthetic(&DIMS, len, rng, false);
    ep.terminated = len % 2 == 0;
    ep.truncated = !ep.terminated;
    ep
}

fn filled(learn: &LearnConfig, agent: &AgentConfig) -> Learner {
    let mut l = Learner::with_agent(DIMS, learn.clone(), agent.clone(), Device::default()).unwrap();
    let mut rng = LearnRng::seed_from(9);
    for i in 0..8 {
        l.add_episode(episode(&mut rng, 3 + i % 4)).unwrap();
    }
    l
}

#[test]
fn every_method_unrolls_to_q_values_and_names_its_extra_terms() {
    for (name, learn, agent) in cases() {
        let mut l = filled(&learn, &agent);
        let stats = l.train_step().unwrap_or_else(|e| panic!("{name}: {e}"));
        let names: Vec<&str> = stats.method.iter().map(|m| m.0).collect();
        assert_eq!(names, agent.stat_names(), "{name}: logged terms");
        assert!(stats.loss.is_finite() && stats.method.iter().all(|m| m.1.is_finite()), "{name}: {stats:?}");
        let net = l.acting_net();
        let inputs: Vec<Tensor<2>> = (0..5).map(|_| Tensor::zeros([2 * DIMS.n_agents, l.layout().width()], l.device())).collect();
        let (q, aux) = net.agent.unroll(inputs, None);
        assert_eq!(q.dims(), [5, 2 * DIMS.n_agents, DIMS.n_actions], "{name}");
        assert!(aux.is_empty(), "{name}: no extra terms outside training");
    }
}

#[test]
fn padded_steps_change_neither_the_loss_nor_any_logged_term() {
    for (name, learn, agent) in cases() {
        let l = filled(&learn, &agent);
        let mut rng = LearnRng::seed_from(4);
        let eps: Vec<Episode> = [2, 5, 3, 4].iter().map(|&n| episode(&mut rng, n)).collect();
        let refs: Vec<&Episode> = eps.iter().collect();
        let batch = Batch::from_episodes(&refs, &DIMS, &InputLayout::new(DIMS, &l.config().clone()));
        let mut noisy = batch.clone();
        // Garbage in every padded step (after each episode's end, next step included).
        let (b, n, iw, sd) = (batch.b, batch.n_agents, batch.input_dim, batch.state_dim);
        for t in 0..batch.t {
            for (bi, ep) in eps.iter().enumerate() {
                if t < ep.len + ep.next.is_some() as usize {
                    continue;
                }
                for v in &mut noisy.inputs[(t * b + bi) * n * iw..(t * b + bi + 1) * n * iw] {
                    *v = 7.5;
                }
                for v in &mut noisy.state[(t * b + bi) * sd..(t * b + bi + 1) * sd] {
                    *v = -3.0;
                }
            }
        }
        let (l1, s1) = l.td_loss(&batch).unwrap();
        let (l2, s2) = l.td_loss(&noisy).unwrap();
        let (l1, l2) = (l1.into_scalar::<f32>(), l2.into_scalar::<f32>());
        assert!((l1 - l2).abs() <= 1e-5 * l1.abs().max(1.0), "{name}: loss {l1} vs {l2}");
        for (a, c) in s1.method.iter().zip(&s2.method) {
            assert!((a.1 - c.1).abs() <= 1e-5 * a.1.abs().max(1.0), "{name}: {} {} vs {}", a.0, a.1, c.1);
        }
    }
}

fn acting_q(l: &Learner, seed: u64) -> Vec<f32> {
    let mut ctl = Controller::new(l, 2);
    let mut rng = LearnRng::seed_from(seed);
    let mut out = Vec::new();
    let rows = 2 * DIMS.n_agents;
    let mut last = vec![-1; rows];
    let state: Vec<f32> = (0..2 * DIMS.state_dim).map(|_| rng.uniform()).collect();
    for t in 0..4 {
        let obs: Vec<f32> = (0..rows * DIMS.obs_width).map(|_| rng.uniform()).collect();
        out.extend_from_slice(ctl.q_values(&obs, Some(&state), &last, &[t == 0, t == 0]));
        last = (0..rows).map(|i| ((i + t) % DIMS.n_actions) as i32).collect();
    }
    out
}

#[test]
fn a_checkpoint_round_trip_keeps_the_q_values_and_the_next_update() {
    for (name, learn, agent) in cases() {
        let mut l = filled(&learn, &agent);
        l.train_step().unwrap();
        let dir = std::env::temp_dir().join(format!("lmac-suite-{}-{}", std::process::id(), name.replace(' ', "_")));
        l.save_checkpoint(&dir, true).unwrap();
        let mut r = Learner::load_checkpoint(&dir, Device::default()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(r.agent_config(), &agent, "{name}");
        assert_eq!(acting_q(&l, 1), acting_q(&r, 1), "{name}: Q after loading");
        let (a, b) = (l.train_step().unwrap(), r.train_step().unwrap());
        assert_eq!(a.loss, b.loss, "{name}: the next update");
        let _ = std::fs::remove_dir_all(&dir);
    }
}

#[test]
fn acting_step_by_step_equals_the_unrolled_forward() {
    for (name, learn, agent) in cases() {
        let l = filled(&learn, &agent);
        let layout = *l.layout();
        let (rows, iw, t_len) = (2 * DIMS.n_agents, layout.width(), 6);
        let mut rng = LearnRng::seed_from(21);
        let state: Vec<f32> = (0..2 * DIMS.state_dim).map(|_| rng.uniform()).collect();
        let mut ctl = Controller::new(&l, 2);
        let mut stepped = Vec::new();
        let mut inputs = Vec::new();
        let mut last = vec![-1; rows];
        for t in 0..t_len {
            let obs: Vec<f32> = (0..rows * DIMS.obs_width).map(|_| rng.uniform() * 2.0 - 1.0).collect();
            stepped.extend_from_slice(ctl.q_values(&obs, Some(&state), &last, &[t == 0, t == 0]));
            let mut x = vec![0.0; rows * iw];
            for r in 0..rows {
                let (e, ag) = (r / DIMS.n_agents, r % DIMS.n_agents);
                let st = layout.state.then(|| &state[e * DIMS.state_dim..(e + 1) * DIMS.state_dim]);
                let o = &obs[r * DIMS.obs_width..(r + 1) * DIMS.obs_width];
                layout.write(&mut x[r * iw..(r + 1) * iw], RowParts::step(o, st, last[r], ag));
            }
            inputs.push(Tensor::<2>::from_data(TensorData::new(x, [rows, iw]), l.device()));
            last = (0..rows).map(|i| ((i * 3 + t) % DIMS.n_actions) as i32).collect();
        }
        let (q, _) = l.acting_net().agent.unroll(inputs, None);
        let unrolled = q.into_data().try_into_vec::<f32>().unwrap();
        assert_eq!(unrolled.len(), stepped.len());
        for (i, (a, b)) in stepped.iter().zip(&unrolled).enumerate() {
            assert!((a - b).abs() <= 1e-5, "{name}: element {i}: acting {a} vs unrolled {b}");
        }
    }
}

/// Trainable parameters of `module` without a gradient, or with an all-zero one.
pub fn params_without_gradient<M: Module>(module: &M, grads: &GradientsParams) -> usize {
    struct V<'a> {
        grads: &'a GradientsParams,
        missing: usize,
        trainable: usize,
    }
    impl ModuleVisitor for V<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            let id: ParamId = p.id;
            if !p.val().is_require_grad() {
                return; // a buffer, not trained by gradients (batch-norm running statistics)
            }
            self.trainable += 1;
            match self.grads.get::<D>(id) {
                Some(g) if g.clone().abs().sum().into_scalar::<f32>() > 0.0 => {}
                _ => self.missing += 1,
            }
        }
    }
    let mut v = V { grads, missing: 0, trainable: 0 };
    module.visit(&mut v);
    assert!(v.trainable > 0, "no trainable parameter found");
    v.missing
}

#[test]
fn one_update_sends_a_gradient_to_every_parameter() {
    for (name, learn, agent) in cases() {
        let mut l = filled(&learn, &agent);
        let batch = l.sample_batch();
        let (loss, _) = l.td_loss(&batch).unwrap();
        let grads = loss.backward();
        let net = l.online_net();
        let grads = GradientsParams::from_grads(grads, net);
        assert_eq!(params_without_gradient(net, &grads), 0, "{name}: parameters without a gradient");
    }
}

#[test]
fn the_gradient_check_skips_what_is_not_trained_but_counts_a_trainable_parameter_left_without_one() {
    // COLA keeps its teacher (8 weights and biases) and its center out of the optimizer and
    // passes the check above; with its consensus loss weighted 0, the student's 8 weights and
    // biases (trainable, reached by no other loss) get all-zero gradients and are counted.
    let (_, learn, mut agent) = cases().into_iter().find(|c| c.0 == "cola ").expect("cola case");
    let AgentConfig::Cola(c) = &mut agent else { panic!("not a COLA config") };
    c.settings.consensus_weight = 0.0;
    let mut l = filled(&learn, &agent);
    let batch = l.sample_batch();
    let (loss, _) = l.td_loss(&batch).unwrap();
    let grads = GradientsParams::from_grads(loss.backward(), l.online_net());
    assert_eq!(params_without_gradient(l.online_net(), &grads), 8);
}

#[test]
fn the_communication_baselines_resolve_through_the_run_config_without_a_protocol() {
    use lmac_run::train::TrainConfig;
    for (algo, good, bad, field) in [
        ("ndq", "method.cut=90", "method.cut=120", "method.cut"),
        ("maic", "method.prune=0.5", "method.prune=-1", "method.prune"),
        ("masia", "method.pred_len=1", "method.momentum_tau=2.0", "method.momentum_tau"),
        ("cola", "method.classes=8", "method.teacher_temp=0.0", "method.teacher_temp"),
    ] {
        let set = |extra: &str| vec![format!("run.algo={algo:?}"), extra.to_string()];
        let cfg = TrainConfig::resolve(None, &set(good)).unwrap_or_else(|e| panic!("{algo}: {e:#}"));
        assert_eq!(cfg.protocol().unwrap().to_string(), "none", "{algo} makes its own messages: the runner writes none");
        let err = format!("{:#}", TrainConfig::resolve(None, &set(bad)).unwrap_err());
        assert!(err.contains(field), "{algo}: {err}");
    }
}
