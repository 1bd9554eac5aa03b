"""Any PettingZoo parallel environment (PettingZoo 1.27 API) as an lmac environment.

Name: ``pz:<target>[,<key>=<value>]...``

- ``<target>`` is a dotted Python path: a module with a ``parallel_env(**kwargs)`` function
  (every PettingZoo environment module has one: ``mpe2.simple_spread_v3``,
  ``pettingzoo.butterfly.knights_archers_zombies_v11``), or any callable returning a
  ``ParallelEnv`` (``mypkg.envs.make_team_env``).
- ``<key>=<value>`` pairs are keyword arguments of that function (``max_cycles=100``,
  ``N=5``; values are parsed as bool ``true/false``, ``none``, int, float, else string),
  except the adapter's own options:
  ``team_reward=sum`` (default: the sum of the agents' rewards) or ``team_reward=mean`` (that sum
  divided by the number of agents, dead ones included).

The name is also the schema's place: ``pz:mpe2.simple_spread_v3`` is
``env-server/schemas/pz/mpe2.simple_spread_v3.toml``, written by
``lmac envs --generate pz:mpe2.simple_spread_v3`` (this module's ``generate``) and then edited.

How one PettingZoo env becomes a row of lmac's batch:
- agents in the fixed order of ``possible_agents``;
- observations flattened (``gymnasium.spaces.flatten``; for a ``Dict`` with an ``observation``
  key, that entry; an ``action_mask`` entry is never part of the observation) to float32 and
  zero-padded to the largest agent's size;
- actions: ``Discrete(n, start)`` (index a means start + a) or ``MultiDiscrete`` (index a is the
  joint index, row-major); an agent with fewer actions than the largest has the extra ones
  unavailable. Continuous action spaces are refused;
- available actions from an ``action_mask`` in the observation dict, else in the agent's
  ``info``, else all of the agent's actions;
- an agent that is not in ``env.agents`` (terminated early, or not yet spawned) is a dead slot:
  zero observation, only action 0 available (and ignored), reward 0;
- the episode ends when ``env.agents`` is empty (or every agent that acted is done): truncated
  if any agent was truncated without being terminated (the time limit: the learner bootstraps
  from the observations written on that row), else terminated;
- the state is ``env.state()`` flattened when the env has one, else the concatenated (padded)
  observations of all slots;
- copy k of a batch is reset with seed k of ``SeedSequence(seed)`` the first time, then
  without a seed (its own generator continues);
- an episode counts as won when an agent's final ``info`` has a true ``is_success`` or ``won``
  (PettingZoo has no common notion of winning, so otherwise no episode is won).

``python -m lmac_env.pz generate pz:... [--out FILE]`` writes a schema; ``python -m lmac_env.pz
check pz:...`` compares a schema with the environment.
"""
from __future__ import annotations

import argparse
import functools
import importlib
import math
import pathlib
import sys
from typing import Any, Callable

import numpy as np

from .core import Batch, Schema, VecEnv, schema_path
from .sizes import SizeMismatch

FAMILY = "pz"
OPTIONS = {"team_reward": ("sum", "mean")}
NOOP = 0  # the one action a dead slot has available


# -- names ------------------------------------------------------------------------------------

def _value(text: str) -> Any:
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    if low == "none":
        return None
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


def parse_variant(variant: str) -> tuple[str, dict, dict]:
    """``mpe2.simple_spread_v3,N=4,team_reward=mean`` -> (target, env kwargs, adapter options)."""
    target, *pairs = variant.split(",")
    if not target or not all(p.isidentifier() for p in target.split(".")):
        raise ValueError(f"pz:{variant}: {target!r} is not a dotted Python path "
                         "(pz:<module or callable>[,key=value]..., e.g. pz:mpe2.simple_spread_v3)")
    kwargs: dict = {}
    options = {k: v[0] for k, v in OPTIONS.items()}
    seen = set()
    for p in pairs:
        key, sep, value = p.partition("=")
        if not sep or not key.isidentifier():
            raise ValueError(f"pz:{variant}: {p!r} is not KEY=VALUE")
        if key in seen:
            raise ValueError(f"pz:{variant}: {key} is given twice")
        seen.add(key)
        if key in OPTIONS:
            if value not in OPTIONS[key]:
                raise ValueError(f"pz:{variant}: {key}={value}: must be one of {', '.join(OPTIONS[key])}")
            options[key] = value
        else:
            kwargs[key] = _value(value)
    return target, kwargs, options


def _factory(target: str) -> Callable[..., Any]:
    """The callable a target names: a module's ``parallel_env`` or the attribute itself."""
    try:
        mod = importlib.import_module(target)
    except ModuleNotFoundError as e:
        # Only "the target is not a module" falls through to module.attribute; a module that
        # exists but fails to import (a missing dependency) is reported as it is.
        if e.name is None or not target.startswith(e.name):
            raise
        mod = None
    if mod is not None:
        fn = getattr(mod, "parallel_env", None)
        if not callable(fn):
            raise ValueError(f"pz:{target}: module {target} has no parallel_env function")
        return fn
    module, _, attr = target.rpartition(".")
    try:
        mod = importlib.import_module(module) if module else None
    except ModuleNotFoundError as e:
        if e.name is None or not module.startswith(e.name):
            raise
        mod = None
    fn = getattr(mod, attr, None) if mod is not None else None
    if not callable(fn):
        raise ValueError(
            f"pz:{target}: cannot import {target} (neither a module with parallel_env nor a callable) "
            f"in {sys.executable}; install the environment's package into the Python the env servers "
            "use (LMAC_PYTHON, else the repository's .venv) or put its folder on PYTHONPATH")
    return fn


def make_parallel(target: str, kwargs: dict):
    env = _factory(target)(**kwargs)
    for attr in ("possible_agents", "reset", "step", "observation_space", "action_space"):
        if not hasattr(env, attr):
            hint = " (an AEC env? pz: takes parallel envs)" if hasattr(env, "agent_iter") else ""
            raise ValueError(f"pz:{target}: {type(env).__name__} has no {attr}: not a PettingZoo ParallelEnv{hint}")
    return env


# -- spaces -----------------------------------------------------------------------------------

class _Obs:
    """One agent's observation space: how to flatten it."""

    def __init__(self, agent: str, space):
        from gymnasium import spaces
        self.key = None
        self.drop_mask = False
        if isinstance(space, spaces.Dict) and "observation" in space.spaces:
            self.key = "observation"
            space = space["observation"]
        elif isinstance(space, spaces.Dict) and "action_mask" in space.spaces:
            # Every other entry is observation; the mask becomes the available actions.
            self.drop_mask = True
            space = spaces.Dict({k: v for k, v in space.spaces.items() if k != "action_mask"})
        if isinstance(space, spaces.Sequence) or isinstance(space, spaces.Graph) or isinstance(space, spaces.Text):
            raise ValueError(f"agent {agent}: observation space {space} has no fixed size")
        self.space = space
        self.box = isinstance(space, spaces.Box)
        self.dim = int(spaces.flatdim(space))
        self.shape = tuple(space.shape) if self.box else (self.dim,)

    def flat(self, obs) -> np.ndarray:
        o = obs[self.key] if self.key is not None else obs
        if self.drop_mask:
            o = {k: v for k, v in o.items() if k != "action_mask"}
        if self.box:
            return np.asarray(o, np.float32).reshape(-1)
        from gymnasium import spaces
        return np.asarray(spaces.flatten(self.space, o), np.float32)


class _Act:
    """One agent's discrete action space: lmac's action index -> the env's action."""

    def __init__(self, agent: str, space):
        from gymnasium import spaces
        self.agent = agent
        self.space = space
        if isinstance(space, spaces.Discrete):
            self.n = int(space.n)
            self.start = int(space.start)
            self.nvec = None
        elif isinstance(space, spaces.MultiDiscrete) and space.nvec.ndim == 1:
            self.nvec = tuple(int(v) for v in space.nvec)
            self.start = np.asarray(space.start, np.int64)
            self.n = int(math.prod(self.nvec))
        else:
            raise ValueError(f"agent {agent}: action space {space} is not Discrete or 1-D MultiDiscrete; "
                             "lmac's learners choose discrete actions")

    def decode(self, a: int):
        a = int(a)
        if not 0 <= a < self.n:
            raise ValueError(f"agent {self.agent}: action {a} is outside its {self.n} actions "
                             "(an unavailable padding action was chosen)")
        if self.nvec is None:
            return self.start + a
        return np.asarray(np.unravel_index(a, self.nvec), np.int64) + self.start

    def mask(self, m) -> np.ndarray:
        """A PettingZoo action mask (flat, or one per component of a MultiDiscrete) as a flat mask."""
        if self.nvec is not None and isinstance(m, (tuple, list)) and len(m) == len(self.nvec):
            flat = np.ones((), bool)
            for part in m:
                flat = np.multiply.outer(flat, np.asarray(part, bool))
            return flat.reshape(-1)
        m = np.asarray(m).reshape(-1)
        if m.shape[0] != self.n:
            raise ValueError(f"agent {self.agent}: action mask of {m.shape[0]} entries for {self.n} actions")
        return m != 0


class Layout:
    """What the spaces of one PettingZoo env give lmac: dims, per-agent readers, the state."""

    def __init__(self, name: str, env):
        self.name = name
        self.agents = list(env.possible_agents)
        if not self.agents:
            raise ValueError(f"{name}: the environment has no possible_agents")
        try:
            self.obs = [_Obs(a, env.observation_space(a)) for a in self.agents]
            self.act = [_Act(a, env.action_space(a)) for a in self.agents]
        except ValueError as e:
            raise ValueError(f"{name}: {e}") from None
        self.n_agents = len(self.agents)
        self.obs_dim = max(o.dim for o in self.obs)
        self.n_actions = max(a.n for a in self.act)
        self.state_space = None
        self.state_dim = None  # known after a reset when the env has state() but no state_space
        self.has_state = True
        space = getattr(env, "state_space", None)
        if space is not None:
            from gymnasium import spaces
            self.state_space = space
            self.state_dim = int(spaces.flatdim(space))

    def probe_state(self, env) -> None:
        """After a reset: does the env have state(), and how big is it?"""
        try:
            s = env.state()
        except (NotImplementedError, AttributeError):
            self.has_state = False
            self.state_dim = self.n_agents * self.obs_dim
            return
        n = int(np.asarray(s).size)
        if self.state_dim is not None and self.state_dim != n:
            raise ValueError(f"{self.name}: state() returned {n} values but state_space says {self.state_dim}")
        self.state_dim = n

    def describe_obs(self) -> str:
        return ", ".join(f"{a}: {o.dim}" for a, o in zip(self.agents, self.obs))

    def describe_actions(self) -> str:
        return ", ".join(f"{a}: {x.n}" for a, x in zip(self.agents, self.act))

    def check(self, schema: Schema) -> None:
        """Refuse a schema whose dims disagree with the environment, naming both numbers."""
        problems = []
        if schema.name != self.name:
            problems.append(f"name = {schema.name!r} but the environment is {self.name!r}")
        pairs = [
            ("n_agents", self.n_agents, f"possible_agents has {self.n_agents} ({', '.join(self.agents)})"),
            ("obs_dim", self.obs_dim, f"the largest flattened observation has {self.obs_dim} values "
                                      f"({self.describe_obs()})"),
            ("n_actions", self.n_actions, f"the largest action space has {self.n_actions} actions "
                                          f"({self.describe_actions()})"),
            ("state_dim", self.state_dim,
             f"the environment's state has {self.state_dim} values" if self.has_state else
             f"the concatenated observations have {self.state_dim} values ({self.n_agents} x {self.obs_dim}; "
             "the environment has no state())"),
        ]
        for field, ours, why in pairs:
            got = getattr(schema, field)
            if ours is not None and got != ours:
                problems.append(f"{field} = {got} but {why}")
        if problems:
            raise SizeMismatch(f"{schema.path}: the schema does not fit {self.name}: " + "; ".join(problems)
                             + f". Regenerate it (lmac envs --generate {self.name} --force) or fix the file.")


def _max_cycles(env) -> int | None:
    for obj in (env, getattr(env, "unwrapped", None), getattr(env, "aec_env", None)):
        v = getattr(obj, "max_cycles", None) if obj is not None else None
        if isinstance(v, int) and v > 0:
            return v
    return None


# -- the batched env --------------------------------------------------------------------------

class PettingZooVecEnv(VecEnv):
    """B copies of one PettingZoo parallel env, stepped one after another (see the module doc)."""

    def __init__(self, variant: str, num_envs: int, seed: int, schema: Schema | None = None):
        self.name = f"{FAMILY}:{variant}"
        target, kwargs, options = parse_variant(variant)
        self.mean_reward = options["team_reward"] == "mean"
        self.num_envs = num_envs
        self.envs = [make_parallel(target, kwargs) for _ in range(num_envs)]
        self.layout = Layout(self.name, self.envs[0])
        self.agents = self.layout.agents
        self._index = {a: i for i, a in enumerate(self.agents)}
        self._seeds = np.random.SeedSequence(seed).generate_state(num_envs)
        self._seeded = np.zeros(num_envs, bool)
        # The state's presence and size: one seeded reset of copy 0 (it is reset again with the
        # same seed before its first episode, so this changes nothing).
        self.envs[0].reset(seed=int(self._seeds[0]))
        self.layout.probe_state(self.envs[0])
        if schema is None:
            path = schema_path(self.name)
            if not path.is_file():
                raise ValueError(f"{self.name}: no schema file {path}; write one with "
                                 f"`lmac envs --generate {self.name}` and describe its dims")
            schema = Schema.load(path)
        self.layout.check(schema)
        self.schema = schema
        n = self.layout.n_agents
        self.alive = np.zeros((num_envs, n), bool)  # slots shown on the last row written (not dead)
        self.won = np.zeros(num_envs, bool)

    # -- rows ----------------------------------------------------------------------------------
    def _write(self, e: int, obs: dict, infos: dict, out: Batch, show: set) -> None:
        lay = self.layout
        env = self.envs[e]
        row_obs, row_avail = out.obs[e], out.avail[e]
        for i, a in enumerate(lay.agents):
            self.alive[e, i] = a in show and a in obs
            if not self.alive[e, i]:
                row_obs[i] = 0.0
                row_avail[i] = 0
                row_avail[i, NOOP] = 1
                continue
            o = obs[a]
            x = lay.obs[i].flat(o)
            row_obs[i, :x.shape[0]] = x
            row_obs[i, x.shape[0]:] = 0.0
            mask = None
            if isinstance(o, dict) and "action_mask" in o:
                mask = o["action_mask"]
            elif isinstance(infos.get(a), dict) and "action_mask" in infos[a]:
                mask = infos[a]["action_mask"]
            act = lay.act[i]
            row_avail[i] = 0
            if mask is None:
                row_avail[i, :act.n] = 1
            else:
                row_avail[i, :act.n] = act.mask(mask)
                if not row_avail[i].any():
                    row_avail[i, NOOP] = 1  # nothing allowed: the learner still needs one choice
        if lay.has_state:
            out.state[e] = np.asarray(env.state(), np.float32).reshape(-1)
        else:
            out.state[e] = row_obs.reshape(-1)

    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        for e in env_ids:
            e = int(e)
            env = self.envs[e]
            if not self._seeded[e]:
                obs, infos = env.reset(seed=int(self._seeds[e]))
                self._seeded[e] = True
            else:
                obs, infos = env.reset()
            self.won[e] = False
            self._write(e, obs, infos or {}, out, set(env.agents))

    def step(self, actions: np.ndarray, out: Batch, active: np.ndarray | None = None) -> None:
        lay = self.layout
        scale = 1.0 / lay.n_agents if self.mean_reward else 1.0
        for e, env in enumerate(self.envs):
            if active is not None and not active[e]:
                continue
            before = list(env.agents)
            index = self._index
            acts = {a: lay.act[index[a]].decode(actions[e, index[a]]) for a in before}
            obs, rewards, terms, truncs, infos = env.step(acts)
            infos = infos or {}
            out.reward[e] = scale * float(sum(float(rewards.get(a, 0.0)) for a in lay.agents))
            ended = not env.agents or all(terms.get(a) or truncs.get(a) for a in before)
            truncated = ended and any(truncs.get(a) and not terms.get(a) for a in before)
            out.terminated[e] = 1 if ended and not truncated else 0
            out.truncated[e] = 1 if truncated else 0
            if ended:
                self.won[e] = any(isinstance(infos.get(a), dict) and
                                  bool(infos[a].get("is_success", infos[a].get("won", False)))
                                  for a in before)
                # After a time limit the learner bootstraps from this row: show the agents that
                # were cut off (not the terminated ones) with their last observations.
                show = {a for a in before if truncs.get(a) and not terms.get(a)} if truncated else set()
            else:  # (an env that keeps a done agent in env.agents does not revive it)
                show = {a for a in env.agents if not (terms.get(a) or truncs.get(a))}
            self._write(e, obs, infos, out, show)

    def close(self) -> None:
        for env in self.envs:
            try:
                env.close()
            except Exception:  # noqa: BLE001 - closing a broken env must not hide the real error
                pass


def make(variant: str, num_envs: int, seed: int) -> VecEnv:
    return PettingZooVecEnv(variant, num_envs, seed)


# -- schema generation ------------------------------------------------------------------------

def _toml_str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ") + '"'


def _group(kind: str, count: int, meaning: str, shape: tuple | None = None) -> str:
    lines = [f"[[{kind}]]", f"count = {count}"]
    if shape is not None and len(shape) > 1:
        lines.append(f"shape = [{', '.join(str(d) for d in shape)}]")
    lines.append(f"meaning = {_toml_str(meaning)}")
    return "\n".join(lines)


def _index_words(shape: tuple) -> str:
    if len(shape) <= 1:
        return "value {k}"
    return "value at index [" + ", ".join(f"{{i{d}}}" for d in range(len(shape))) + "]"


def generate(name: str, episode_limit: int | None = None, alpha: float = 0.1) -> str:
    """A schema for ``name`` (``pz:...``) with dims from the spaces and EDIT placeholders."""
    family, _, variant = name.partition(":")
    if family != FAMILY or not variant:
        raise ValueError(f"{name}: only pz:<module>[,key=value]... environments are generated")
    target, kwargs, options = parse_variant(variant)
    env = make_parallel(target, kwargs)
    lay = Layout(name, env)
    env.reset(seed=0)
    lay.probe_state(env)
    limit = episode_limit or _max_cycles(env)
    try:
        env.close()
    except Exception:  # noqa: BLE001
        pass
    if not limit:
        raise ValueError(f"{name}: the environment has no max_cycles; give --episode-limit N")
    agents = lay.agents
    same_obs = len({(o.dim, o.shape) for o in lay.obs}) == 1
    same_act = len({repr(a.space) for a in lay.act}) == 1
    n = lay.n_agents
    fullcomm = (n - 1) * (lay.obs_dim + n)
    team = "mean" if options["team_reward"] == "mean" else "sum"
    agent_list = ", ".join(agents)
    out = [
        f"# Generated by `lmac envs --generate {name}` from the environment's spaces.",
        "# Replace every text that starts with EDIT: the LLM that designs protocols reads the task,",
        "# the reward, the actions and the meaning of every observation and state dimension.",
        "# `python -m lmac_env.pz check NAME` compares the file with the environment again.",
        f"name = {_toml_str(name)}",
        "task = " + _toml_str(f"EDIT: what the team of {n} agents ({agent_list}) must do in {target}."),
        f"n_agents = {n}",
        f"obs_dim = {lay.obs_dim}",
        f"state_dim = {lay.state_dim}",
        f"n_actions = {lay.n_actions}",
        f"episode_limit = {limit}",
        f"message_columns = {fullcomm}  # FullComm needs (n_agents - 1) x (obs_dim + n_agents)",
        f"alpha = {alpha}  # meta-information threshold: a squared error in the state's own units",
        "reward = " + _toml_str(
            f"EDIT: how the agents are rewarded. Team reward = {team} of the agents' rewards "
            f"({'divided by ' + str(n) + ', dead agents included' if team == 'mean' else 'dead agents add 0'}). "
            "The episode terminates when every agent is done and is truncated at the time limit."),
    ]
    names = []
    for k in range(lay.n_actions):
        who = [a for a, x in zip(agents, lay.act) if k < x.n]
        suffix = "" if len(who) == n else f" (only {', '.join(who)}; unavailable to the others)"
        dead = "; the only action of a dead agent" if k == NOOP else ""
        names.append(_toml_str(f"EDIT: action {k}{suffix}{dead}"))
    out.append("actions = [" + ", ".join(names) + "]")
    out.append("")
    if same_obs:
        o = lay.obs[0]
        out.append(_group("obs_dims", o.dim, f"EDIT: this agent's observation {_index_words(o.shape)}", o.shape))
    else:
        cuts = sorted({0, lay.obs_dim} | {o.dim for o in lay.obs})
        for lo, hi in zip(cuts, cuts[1:]):
            has = [a for a, o in zip(agents, lay.obs) if o.dim >= hi]
            pad = [a for a, o in zip(agents, lay.obs) if o.dim <= lo]
            text = f"EDIT: observation value {lo} + {{k}} of {', '.join(has)}"
            if pad:
                text += f"; always 0 (padding) for {', '.join(pad)}"
            out.append(_group("obs_dims", hi - lo, text))
            out.append("")
        # Agents whose spaces differ observe different things: each kind its own meanings, so
        # no prompt or log names one agent's value with another's meaning.
        kinds: dict[tuple, list[str]] = {}
        for a, o in zip(agents, lay.obs):
            kinds.setdefault((o.dim, tuple(o.shape)), []).append(a)
        for (dim, shape), who in kinds.items():
            ids = [agents.index(a) for a in who]
            out += ["[[agent_obs]]", "name = " + _toml_str(f"EDIT: what {', '.join(who)} are"),
                    f"agents = [{', '.join(str(i) for i in ids)}]"]
            out.append(_group("agent_obs.obs_dims", dim, f"EDIT: {', '.join(who)}'s observation {_index_words(shape)}", shape))
            if dim < lay.obs_dim:
                out.append(_group("agent_obs.obs_dims", lay.obs_dim - dim, "always 0 (padding to the widest agent's observation)"))
            out.append("")
    out.append("")
    if lay.has_state:
        shape = tuple(lay.state_space.shape) if lay.state_space is not None and lay.state_space.shape else (lay.state_dim,)
        if math.prod(shape) != lay.state_dim:
            shape = (lay.state_dim,)
        out.append(_group("state_dims", lay.state_dim, f"EDIT: global state {_index_words(shape)}", shape))
    else:
        for a in agents:
            out.append(_group("state_dims", lay.obs_dim,
                              f"observation value {{k}} of {a} (the environment has no state(); "
                              "the state is the agents' padded observations; 0 when dead)"))
            out.append("")
    return "\n".join(out).rstrip() + "\n"


def check(name: str, schema_file: str | pathlib.Path | None = None) -> Layout:
    """Compare a schema file with the environment (ValueError naming both numbers)."""
    path = pathlib.Path(schema_file) if schema_file else schema_path(name)
    _, _, variant = name.partition(":")
    env = PettingZooVecEnv(variant, 1, 0, schema=Schema.load(path))
    env.close()
    return env.layout


# -- command line -----------------------------------------------------------------------------

def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lmac_env.pz", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="write a schema for a pz: environment")
    g.add_argument("name", help="pz:<module>[,key=value]...")
    g.add_argument("--out", help="schema file to write (default: the schema directory's place for NAME; '-' prints)")
    g.add_argument("--force", action="store_true", help="overwrite an existing file")
    g.add_argument("--episode-limit", type=int, help="when the environment has no max_cycles")
    c = sub.add_parser("check", help="compare a pz: environment's schema with the environment")
    c.add_argument("name")
    c.add_argument("--schema", help="schema file (default: the schema directory's place for NAME)")
    args = p.parse_args(argv)
    try:
        if args.cmd == "generate":
            text = generate(args.name, args.episode_limit)
            if args.out == "-":
                sys.stdout.write(text)
                return 0
            out = pathlib.Path(args.out) if args.out else schema_path(args.name)
            if out.exists() and not args.force:
                print(f"{out} exists (it may hold your descriptions); --force overwrites it", file=sys.stderr)
                return 2
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(text)
            print(f"wrote {out}: edit the EDIT texts, then `lmac envs --check`")
            return 0
        lay = check(args.name, args.schema)
        print(f"{args.name}: the schema fits ({lay.n_agents} agents, obs {lay.obs_dim}, state {lay.state_dim}, "
              f"actions {lay.n_actions})")
        return 0
    except ValueError as e:
        print(f"lmac: {e}", file=sys.stderr)
        return 1
    except ImportError as e:  # the environment's own dependency is missing
        print(f"lmac: {args.name}: {e}; install it into the Python the env servers use ({sys.executable})",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
