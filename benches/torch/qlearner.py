#!/usr/bin/env python3
"""PyTorch (CPU) anchor for `lmac bench learner --against torch`: one pymarl QLearner update
(double-Q TD(0), masked MSE, grad-norm clip 10, Adam) for the VDN, QMIX and QPLEX mixers, with the
same network structure as lmac's Rust learner. The batch is synthetic and fixed; only the update
is timed.

  python qlearner.py --mixer qmix --updates 20            # one JSON line: per-update ms, median
  python qlearner.py --mixer qplex --updates 5 --profile  # + operator table on stderr
  python qlearner.py --mixer vdn --serve                  # stdin: "run K" / "quit"; JSON replies
"""
import argparse
import copy
import json
import statistics
import sys
import time

import torch
import torch.nn as nn
import torch.nn.functional as F


class RNNAgent(nn.Module):
    """pymarl RNNAgent, shared by all agents."""

    def __init__(self, inp, hidden, actions):
        super().__init__()
        self.hidden = hidden
        self.fc1 = nn.Linear(inp, hidden)
        self.rnn = nn.GRUCell(hidden, hidden)
        self.fc2 = nn.Linear(hidden, actions)

    def unroll(self, inputs):
        # Step by step as pymarl's mac.forward loop does (one fc1/GRU/fc2 call per step), so the
        # operator count is the one a pymarl user pays, not that of a fused nn.GRU.
        b, t, n, _ = inputs.shape
        h = inputs.new_zeros(b * n, self.hidden)
        out = []
        for ti in range(t):
            h = self.rnn(F.relu(self.fc1(inputs[:, ti].reshape(b * n, -1))), h)
            out.append(self.fc2(h).view(b, n, -1))
        return torch.stack(out, dim=1)  # [B, T, n, A]


def hypernet(inp, embed, out):
    return nn.Sequential(nn.Linear(inp, embed), nn.ReLU(), nn.Linear(embed, out))


class VDN(nn.Module):
    def forward(self, qs, states, **_):
        return qs.sum(dim=2, keepdim=True)


class QMixer(nn.Module):
    def __init__(self, n, s, embed, hyper_embed):
        super().__init__()
        self.n, self.s, self.e = n, s, embed
        self.hyper_w1 = hypernet(s, hyper_embed, embed * n)
        self.hyper_b1 = nn.Linear(s, embed)
        self.hyper_w_final = hypernet(s, hyper_embed, embed)
        self.V = nn.Sequential(nn.Linear(s, embed), nn.ReLU(), nn.Linear(embed, 1))

    def forward(self, qs, states, **_):
        b = qs.size(0)
        st = states.reshape(-1, self.s)
        q = qs.reshape(-1, 1, self.n)
        # abs() keeps Q_tot monotonic in every agent's Q.
        w1 = self.hyper_w1(st).abs().view(-1, self.n, self.e)
        hidden = F.elu(torch.bmm(q, w1) + self.hyper_b1(st).view(-1, 1, self.e))
        w_final = self.hyper_w_final(st).abs().view(-1, self.e, 1)
        y = torch.bmm(hidden, w_final) + self.V(st).view(-1, 1, 1)
        return y.view(b, -1, 1)


def mlp3(inp, embed, out):
    return nn.Sequential(nn.Linear(inp, embed), nn.ReLU(), nn.Linear(embed, embed), nn.ReLU(), nn.Linear(embed, out))


class QPLEXMixer(nn.Module):
    """DMAQ general mixer with the DMAQ_SI_Weight advantage weights (no qatten)."""

    def __init__(self, n, s, actions, hyper_embed, kernels, adv_embed=64):
        super().__init__()
        self.n, self.s, self.a = n, s, actions
        self.hyper_w_final = hypernet(s, hyper_embed, n)
        self.V = hypernet(s, hyper_embed, n)
        # K separate Sequentials in ModuleLists, as the reference code has them (K small matmul
        # chains rather than one batched one).
        self.key = nn.ModuleList(mlp3(s, adv_embed, 1) for _ in range(kernels))
        self.agents = nn.ModuleList(mlp3(s, adv_embed, n) for _ in range(kernels))
        self.action = nn.ModuleList(mlp3(s + n * actions, adv_embed, n) for _ in range(kernels))

    def forward(self, qs, states, actions_onehot, max_q):
        b = qs.size(0)
        st = states.reshape(-1, self.s)
        w = self.hyper_w_final(st).abs() + 1e-10
        v = self.V(st)
        q = w * qs.reshape(-1, self.n) + v
        qmax = w * max_q.reshape(-1, self.n) + v
        # The advantage is a constant to the lambda weights: only lambda learns from this term.
        adv = (q - qmax).detach()
        data = torch.cat([st, actions_onehot.reshape(-1, self.n * self.a)], dim=1)
        heads = [(k(st).abs() + 1e-10) * torch.sigmoid(ag(st)) * torch.sigmoid(ac(data))
                 for k, ag, ac in zip(self.key, self.agents, self.action)]
        lam = torch.stack(heads, dim=1).sum(dim=1)
        q_tot = q.sum(dim=1) + (adv * (lam - 1.0)).sum(dim=1)
        return q_tot.view(b, -1, 1)


def make_batch(a, gen):
    """Fixed synthetic batch in pymarl's layout ([B, T, ...], T entries = T-1 transitions)."""
    b, t, n, na = a.batch, a.steps, a.agents, a.actions
    actions = torch.randint(0, na, (b, t, n, 1), generator=gen)
    avail = (torch.rand(b, t, n, na, generator=gen) > 0.3).float()
    avail.scatter_(3, actions, 1.0)  # the taken action was available
    terminated = torch.zeros(b, t, 1)
    terminated[:, t - 2] = (torch.rand(b, 1, generator=gen) > 0.5).float()  # some episodes end
    return {
        "inputs": torch.rand(b, t, n, a.input, generator=gen),
        "actions": actions,
        # pymarl's buffer stores the one-hot (OneHot preprocess), so it is not built per update.
        "actions_onehot": F.one_hot(actions.squeeze(3), na).float(),
        "avail": avail,
        "reward": torch.rand(b, t, 1, generator=gen),
        "terminated": terminated,
        "filled": torch.ones(b, t, 1),
        "state": torch.rand(b, t, a.state, generator=gen),
    }


class QLearner:
    def __init__(self, a):
        self.agent = RNNAgent(a.input, a.hidden, a.actions)
        self.mixer = {"vdn": lambda: VDN(),
                      "qmix": lambda: QMixer(a.agents, a.state, a.embed, a.hypernet_embed),
                      "qplex": lambda: QPLEXMixer(a.agents, a.state, a.actions, a.hypernet_embed,
                                                  a.qplex_kernels)}[a.mixer]()
        self.qplex = a.mixer == "qplex"
        self.target_agent = copy.deepcopy(self.agent)
        self.target_mixer = copy.deepcopy(self.mixer)
        self.params = list(self.agent.parameters()) + list(self.mixer.parameters())
        # Default Adam as pymarl uses it (on CPU torch picks the per-parameter loop, not foreach).
        self.optim = torch.optim.Adam(self.params, lr=5e-4, eps=1e-8)
        self.gamma = 0.99

    def train(self, bt):
        actions = bt["actions"][:, :-1]
        reward, terminated = bt["reward"][:, :-1], bt["terminated"][:, :-1]
        mask = bt["filled"][:, :-1].clone()
        mask[:, 1:] = mask[:, 1:] * (1 - terminated[:, :-1])
        avail = bt["avail"]

        mac_out = self.agent.unroll(bt["inputs"])
        chosen = torch.gather(mac_out[:, :-1], 3, actions).squeeze(3)
        with torch.no_grad():
            target_out = self.target_agent.unroll(bt["inputs"])[:, 1:]
        target_out[avail[:, 1:] == 0] = -9999999

        # Double Q: the online network picks the action at t+1, the target network values it.
        greedy = mac_out.clone().detach()
        greedy[avail == 0] = -9999999
        next_act = greedy[:, 1:].max(dim=3, keepdim=True)[1]
        target_q = torch.gather(target_out, 3, next_act).squeeze(3)

        if self.qplex:
            q_tot = self.mixer(chosen, bt["state"][:, :-1], actions_onehot=bt["actions_onehot"][:, :-1],
                               max_q=greedy[:, :-1].max(dim=3)[0])
            next_onehot = torch.zeros_like(target_out).scatter_(3, next_act, 1)
            with torch.no_grad():
                target_tot = self.target_mixer(target_q, bt["state"][:, 1:], actions_onehot=next_onehot,
                                               max_q=target_out.max(dim=3)[0])
        else:
            q_tot = self.mixer(chosen, bt["state"][:, :-1])
            with torch.no_grad():
                target_tot = self.target_mixer(target_q, bt["state"][:, 1:])

        targets = reward + self.gamma * (1 - terminated) * target_tot
        td = (q_tot - targets.detach()) * mask
        loss = (td ** 2).sum() / mask.sum()
        self.optim.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.params, 10.0)
        self.optim.step()
        return loss.detach()


def timed(learner, batch, k, losses=None):
    ms = []
    for _ in range(k):
        t0 = time.perf_counter()
        loss = learner.train(batch)
        ms.append((time.perf_counter() - t0) * 1e3)
        if losses is not None:
            losses.append(loss.item())
    return ms


def emit(obj):
    print(json.dumps(obj, separators=(",", ":")), flush=True)


def serve(learner, batch, ready):
    emit(ready)
    for line in iter(sys.stdin.readline, ""):
        cmd = line.split()
        if cmd == ["quit"]:
            return
        if len(cmd) == 2 and cmd[0] == "run" and cmd[1].isdigit() and int(cmd[1]) > 0:
            emit({"ms": timed(learner, batch, int(cmd[1]))})
        else:
            emit({"error": f"expected 'run K' (K >= 1) or 'quit', got {line.strip()!r}"})


def profile(learner, batch, n):
    from torch.profiler import ProfilerActivity, profile as prof_ctx
    with prof_ctx(activities=[ProfilerActivity.CPU]) as prof:
        ms = timed(learner, batch, n)
    avgs = prof.key_averages()
    print(avgs.table(sort_by="self_cpu_time_total", row_limit=15), file=sys.stderr)
    # Every recorded operator (nested ones too, e.g. aten::linear -> aten::addmm) and the outermost
    # ones only (those not called from inside another operator), each per update.
    events = prof.events()
    outer = sum(1 for e in events if e.name.startswith("aten::")
                and (e.cpu_parent is None or not e.cpu_parent.name.startswith("aten::")))
    print(f"operator calls per update: {sum(e.count for e in avgs) / n:.0f} recorded, "
          f"{outer / n:.0f} outermost aten::", file=sys.stderr)
    return ms


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mixer", choices=["qmix", "vdn", "qplex"], default="qmix")
    p.add_argument("--batch", type=int, default=32, help="episodes per update (B)")
    p.add_argument("--steps", type=int, default=25, help="batch entries per episode (T; T-1 transitions)")
    p.add_argument("--agents", type=int, default=2)
    p.add_argument("--input", type=int, default=37, help="agent network input width")
    p.add_argument("--actions", type=int, default=6)
    p.add_argument("--state", type=int, default=300, help="global state width")
    p.add_argument("--hidden", type=int, default=64, help="agent GRU width")
    p.add_argument("--embed", type=int, default=32, help="QMIX mixing embedding")
    p.add_argument("--hypernet-embed", type=int, default=64, help="hidden width of 2-layer hypernetworks")
    p.add_argument("--qplex-kernels", type=int, default=10, help="QPLEX attention kernels")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--warmup", type=int, default=3, help="untimed updates first")
    mode = p.add_mutually_exclusive_group(required=True)
    mode.add_argument("--updates", type=int, help="timed updates; prints one JSON line")
    mode.add_argument("--serve", action="store_true",
                      help="after warmup print {\"ready\":true,...}; then per stdin line 'run K' "
                           "print {\"ms\":[...]}; 'quit' or EOF exits")
    p.add_argument("--profile", action="store_true", help="with --updates: torch.profiler table on stderr")
    p.add_argument("--check", action="store_true", help="with --updates: first and last loss on stderr")
    a = p.parse_args()
    if a.steps < 2 or min(a.batch, a.agents, a.input, a.actions, a.state, a.hidden) < 1:
        p.error("all dims must be at least 1 and --steps at least 2")
    if a.updates is not None and a.updates < 1:
        p.error("--updates must be at least 1")

    # Interop threads must be fixed before any parallel work starts.
    torch.set_num_interop_threads(1)
    torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)
    learner = QLearner(a)
    batch = make_batch(a, torch.Generator().manual_seed(a.seed + 1))
    timed(learner, batch, a.warmup)
    params = sum(x.numel() for x in learner.params if x.requires_grad)

    if a.serve:
        serve(learner, batch, {"ready": True, "version": torch.__version__, "params": params})
        return
    losses = [] if a.check else None
    ms = profile(learner, batch, a.updates) if a.profile else timed(learner, batch, a.updates, losses)
    if losses:
        print(f"loss: first {losses[0]:.6f} last {losses[-1]:.6f} over {len(losses)} updates", file=sys.stderr)
    shape = {k: getattr(a, k) for k in ("batch", "steps", "agents", "input", "actions", "state",
                                          "hidden", "embed", "hypernet_embed", "qplex_kernels")}
    emit({"impl": "torch", "version": torch.__version__, "mixer": a.mixer, "threads": a.threads,
          "shape": shape, "ms": ms, "median_ms": statistics.median(ms), "params": params})


if __name__ == "__main__":
    main()
