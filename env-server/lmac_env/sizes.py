"""The schema's sizes against what an environment really writes, for every family.

The shared-memory layout is computed from the schema, so an env whose observation has 71 values
under a schema saying ``obs_dim = 70`` would otherwise die inside numpy with a broadcast error
from the user's own module and no schema file named. Here the env writes its first reset and
its first steps into a *probe* batch instead (the same shapes as the slot, sized by the schema):

- a write that does not fit (too many values, an index past the end) is caught where it happens
  and reported with the schema field it overflows and the env's own number;
- every value starts as a sentinel (NaN, 255), so what the env did not write shows up too: rows
  of agents it does not have, columns past the end of its observation, a ``step`` that left
  reward, terminated or truncated unwritten (the slot would keep the previous step's values).

`SizeChecked` wraps an env for its first calls (the env server: first reset and first step,
then the probe's rows are copied into the slot, so the env sees exactly the calls it would
have); ``python -m lmac_env.sizes check NAME...`` (what ``lmac envs --check`` runs) builds
each env and steps it a few times with random available actions; ``measure(name)`` asks the
family module's ``sizes(variant)`` for the sizes of an env (``lmac envs --generate`` for any
family whose module has one; ``pz:`` has its own, from the spaces).
"""
from __future__ import annotations

import argparse
import re
import sys

import numpy as np

from .core import Batch, EnvUnavailable, Schema, VecEnv, schema_path
from .registry import UnknownFamily, make

# The schema field each axis of a batch array is sized by (axis 0 is the env).
AXES = {"obs": ("num_envs", "n_agents", "obs_dim"), "state": ("num_envs", "state_dim"),
        "avail": ("num_envs", "n_agents", "n_actions"), "reward": ("num_envs",),
        "terminated": ("num_envs",), "truncated": ("num_envs",)}
# What the env's number counts, per (array, schema field).
WHAT = {("obs", "n_agents"): "the env writes observations of {n} agents",
        ("obs", "obs_dim"): "the env's observation has {n} values",
        ("state", "state_dim"): "the env's state has {n} values",
        ("avail", "n_agents"): "the env writes available actions of {n} agents",
        ("avail", "n_actions"): "the env's available-action rows have {n} entries"}
UNWRITTEN_F = np.float32(np.nan)
UNWRITTEN_U8 = np.uint8(255)
_OUT_OF_BOUNDS = re.compile(r"index (\d+) is out of bounds for axis (\d+) with size (\d+)")


class SizeMismatch(ValueError):
    """A schema that does not fit its env; the message is one line naming file, field, numbers."""


class _Overflow(Exception):
    """Raised inside a probe write: the env wrote `n` (or at least `n`) along `field`'s axis."""

    def __init__(self, array: str, field: str, n: int, at_least: bool):
        super().__init__(array, field, n, at_least)
        self.array, self.field, self.n, self.at_least = array, field, n, at_least


def _expand(key, ndim: int) -> tuple:
    key = key if isinstance(key, tuple) else (key,)
    if not any(k is Ellipsis for k in key):
        return key + (slice(None),) * (ndim - sum(k is not None for k in key))
    i = next(j for j, k in enumerate(key) if k is Ellipsis)
    used = sum(k is not None and k is not Ellipsis for k in key)
    return key[:i] + (slice(None),) * (ndim - used) + key[i + 1:]


class _Probe(np.ndarray):
    """A batch array that knows, for each of its axes, which axis of the whole batch array it is
    (and where it starts on it), so a write that does not fit can be named by schema field."""

    def __array_finalize__(self, obj):
        self._name = getattr(obj, "_name", None)
        self._full = getattr(obj, "_full", None)  # the whole batch array's shape
        self._axes = None  # per axis: (axis of the whole array, start, step), or None if unknown

    def __getitem__(self, key):
        child = super().__getitem__(key)
        if isinstance(child, _Probe):
            child._axes = self._child_axes(key, child.ndim)
        return child

    def _child_axes(self, key, child_ndim):
        """The axes a basic index (ints, slices, None, Ellipsis, one 1-D index array) keeps."""
        if self._axes is None:
            return None
        try:
            key = _expand(key, self.ndim)
        except TypeError:
            return None
        axes, d = [], 0
        for k in key:
            if k is None:
                axes.append(None)
                continue
            if d >= self.ndim:
                return None
            src = self._axes[d]
            if isinstance(k, slice):
                start, _, step = k.indices(self.shape[d])
                axes.append(None if src is None else (src[0], src[1] + start * src[2], src[2] * step))
            elif isinstance(k, (np.ndarray, list)) and np.ndim(k) == 1:
                axes.append(None)  # which entries of the axis: not followed
            elif not isinstance(k, (int, np.integer)):
                return None
            d += 1
        return axes if len(axes) == child_ndim else None

    def __setitem__(self, key, value):
        try:
            super().__setitem__(key, value)
        except IndexError as e:
            over = self._index_overflow(str(e))
            if over is None:
                raise
            raise over from None
        except ValueError:
            over = self._broadcast_overflow(key, value)
            if over is None:
                raise
            raise over from None

    def _field(self, src, size):
        """The schema field of a view axis that reaches the end of its batch axis (a write past
        a shorter slice the env chose itself is the env's own mistake, not the schema's)."""
        if src is None or src[0] == 0 or src[2] != 1 or src[1] + size != self._full[src[0]]:
            return None
        return AXES[self._name][src[0]]

    def _index_overflow(self, text):
        m = _OUT_OF_BOUNDS.search(text)
        if m is None or self._axes is None:
            return None
        index, axis = int(m.group(1)), int(m.group(2))
        src = self._axes[axis] if axis < len(self._axes) else None
        field = self._field(src, self.shape[axis])
        if field is None:
            return None
        return _Overflow(self._name, field, src[1] + index + 1, True)

    def _broadcast_overflow(self, key, value):
        target = self[key]
        if not isinstance(target, _Probe) or target._axes is None:
            return None
        vshape = np.shape(value)
        for j in range(1, target.ndim + 1):
            t, v = target.shape[-j], (vshape[-j] if j <= len(vshape) else 1)
            if v != t and v != 1:
                src = target._axes[-j]
                field = target._field(src, t)
                if field is None:
                    return None
                return _Overflow(self._name, field, src[1] + v, False)
        return None


def probe_batch(schema: Schema, num_envs: int) -> Batch:
    """A batch of the schema's shapes whose arrays are probes filled with sentinels."""
    fields = {}
    for name, arr in vars(Batch.allocate(schema, num_envs)).items():
        p = arr.view(_Probe)
        p._name = name
        p._full = arr.shape
        p._axes = [(a, 0, 1) for a in range(arr.ndim)]
        p[...] = UNWRITTEN_F if arr.dtype == np.float32 else UNWRITTEN_U8
        fields[name] = p
    return Batch(**fields)


def _unwritten(arr: np.ndarray) -> np.ndarray:
    return np.isnan(arr) if arr.dtype == np.float32 else arr == UNWRITTEN_U8


class SizeChecked(VecEnv):
    """``env`` with its first ``calls`` resets and steps written into probe batches and checked
    against the schema (`SizeMismatch` naming file, field and both numbers), then copied into
    the real batch; later calls go straight through. Other attributes (``won``, ``alive``,
    ``agents``) are the env's."""

    def __init__(self, env: VecEnv, calls: int = 1):
        self.env = env
        self.schema = env.schema
        self.num_envs = env.num_envs
        self._resets = calls
        self._steps = calls

    def __getattr__(self, name):
        return getattr(self.__dict__.get("env"), name)

    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        if self._resets <= 0:
            return self.env.reset(env_ids, out)
        self._resets -= 1
        probe = probe_batch(self.schema, self.num_envs)
        self._call(lambda: self.env.reset(env_ids, probe), "reset")
        rows = np.asarray(env_ids, np.int64)
        self._verify(probe, rows, ("obs", "state", "avail"), "reset")
        self._copy(probe, out, rows, ("obs", "state", "avail"))

    def step(self, actions: np.ndarray, out: Batch, active: np.ndarray | None = None) -> None:
        if self._steps <= 0:
            return self.env.step(actions, out, active)
        self._steps -= 1
        probe = probe_batch(self.schema, self.num_envs)
        self._call(lambda: self.env.step(actions, probe, active), "step")
        rows = np.arange(self.num_envs) if active is None else np.nonzero(active)[0]
        names = ("obs", "state", "avail", "reward", "terminated", "truncated")
        self._verify(probe, rows, names, "step")
        self._copy(probe, out, rows, names)

    def close(self) -> None:
        self.env.close()

    def _fail(self, text: str):
        return SizeMismatch(f"{self.schema.path}: {text}")

    def _call(self, fn, what: str) -> None:
        try:
            fn()
        except _Overflow as o:
            ours = getattr(self.schema, o.field)
            n = f"at least {o.n}" if o.at_least else str(o.n)
            raise self._fail(f"{o.field} = {ours} but " + WHAT[(o.array, o.field)].format(n=n)
                             + f" (seen in {what})") from None

    def _verify(self, probe: Batch, rows: np.ndarray, names, what: str) -> None:
        """What the env left unwritten: a smaller env than the schema, or a broken contract."""
        for name in names:
            miss = _unwritten(getattr(probe, name)[rows])
            if not miss.any():
                continue
            axes = AXES[name]
            # Trailing agents or trailing columns never written in any row: the schema is larger.
            for axis in range(miss.ndim - 1, 0, -1):
                other = tuple(a for a in range(miss.ndim) if a != axis)
                written = ~miss.all(axis=other)
                n = int(np.nonzero(written)[0].max()) + 1 if written.any() else 0
                if n > 0 and not written[n:].any() and miss.take(range(n, miss.shape[axis]), axis).all() \
                        and not miss.take(range(n), axis).any():
                    field = axes[axis]
                    raise self._fail(f"{field} = {getattr(self.schema, field)} but "
                                     + WHAT[(name, field)].format(n=n) + f" (seen in {what})")
            at = tuple(int(i) for i in np.argwhere(miss)[0])
            at = (int(rows[at[0]]),) + at[1:]
            raise self._fail(f"{what} left {name}[{', '.join(map(str, at))}] unwritten (or NaN): a VecEnv "
                             f"writes every value of {name} for each env it {what}s (lmac_env/core.py)")

    @staticmethod
    def _copy(probe: Batch, out: Batch, rows: np.ndarray, names) -> None:
        for name in names:
            getattr(out, name)[rows] = np.asarray(getattr(probe, name))[rows]


def check_env(env: VecEnv, steps: int = 3, seed: int = 0) -> None:
    """Reset ``env`` and step it ``steps`` times with random available actions, every call
    checked against its schema (`SizeMismatch`)."""
    from .server import _random_actions  # the server's own uniform choice over available actions

    checked = SizeChecked(env, calls=steps + 1)
    out = Batch.allocate(env.schema, env.num_envs)
    checked.reset(np.arange(env.num_envs), out)
    rng = np.random.default_rng(seed)
    actions = np.zeros((env.num_envs, env.schema.n_agents), np.int32)
    for _ in range(steps):
        _random_actions(rng, out.avail, actions)
        checked.step(actions, out)
        done = np.nonzero((out.terminated != 0) | (out.truncated != 0))[0]
        if len(done):
            checked.reset(done, out)


def check(name: str, schema_file=None, num_envs: int = 2, steps: int = 3) -> Schema:
    """Build ``name``'s env (``num_envs`` copies: two, so the env axis is never mistaken for
    another) and check it against its schema file; the file the env loaded must be that file."""
    path = schema_path(name) if schema_file is None else schema_file
    want = Schema.load(path)
    env = make(name, num_envs, seed=0)
    try:
        got = env.schema
        for field in ("n_agents", "obs_dim", "state_dim", "n_actions", "episode_limit"):
            if getattr(got, field) != getattr(want, field):
                raise SizeMismatch(f"{path}: {field} = {getattr(want, field)} but the env loaded "
                                   f"{got.path} with {field} = {getattr(got, field)}; an env loads "
                                   "its own schema by its name (core.schema_path)")
        check_env(env, steps)
    finally:
        env.close()
    return want


SIZE_FIELDS = ("n_agents", "obs_dim", "state_dim", "n_actions")


def measure(name: str) -> dict:
    """The sizes of ``name``'s env, from its family module's ``sizes(variant)`` (a dict with
    n_agents, obs_dim, state_dim, n_actions and optionally episode_limit): a module that can
    build one env without a schema (its game, its spaces) says what it writes."""
    from .registry import family_module

    family, _, variant = name.partition(":")
    module = family_module(family, name)
    fn = getattr(module, "sizes", None)
    if not callable(fn):
        raise ValueError(f"{name}: module {module.__name__} has no sizes(variant) to measure an env with; "
                         "add one (see lmac_env/examples/meet.py) or write the schema by hand (shm-schema/SCHEMA.md)")
    got = dict(fn(variant))
    missing = [k for k in SIZE_FIELDS if not isinstance(got.get(k), int) or got[k] < 1]
    if missing:
        raise ValueError(f"{name}: {module.__name__}.sizes({variant!r}) gave no positive int for {', '.join(missing)}")
    return got


def generate(name: str, episode_limit: int | None = None, alpha: float = 0.1) -> str:
    """A schema for ``name`` with every size `measure` gives and EDIT placeholders for the texts
    (``lmac envs --check`` refuses them until they are written)."""
    m = measure(name)
    limit = episode_limit or m.get("episode_limit")
    if not limit:
        raise ValueError(f"{name}: the env gives no episode_limit; give --episode-limit N")
    n = m["n_agents"]
    actions = ", ".join(f'"EDIT: action {k}"' for k in range(m["n_actions"]))
    return f"""# Generated by `lmac envs --generate {name}` from the env's own sizes.
# Replace every text that starts with EDIT: the LLM that designs protocols reads the task,
# the reward, the actions and the meaning of every observation and state dimension (split a
# group into several, see shm-schema/SCHEMA.md). `lmac envs --check` compares the file with the env.
name = "{name}"
task = "EDIT: what the team of {n} agents must do."
n_agents = {n}
obs_dim = {m["obs_dim"]}
state_dim = {m["state_dim"]}
n_actions = {m["n_actions"]}
episode_limit = {limit}
message_columns = {(n - 1) * (m["obs_dim"] + n)}  # FullComm needs (n_agents - 1) x (obs_dim + n_agents)
alpha = {alpha}  # meta-information threshold: a squared error in the state's own units
reward = "EDIT: how the team is rewarded, when an episode terminates and when it is truncated."
actions = [{actions}]

[[obs_dims]]
count = {m["obs_dim"]}
meaning = "EDIT: this agent's observation value {{k}}"

[[state_dims]]
count = {m["state_dim"]}
meaning = "EDIT: state value {{k}}"
"""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lmac_env.sizes", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("check", help="build each env and check it against its schema")
    c.add_argument("names", nargs="+", help="FAMILY:VARIANT (the schema in the schema directory)")
    g = sub.add_parser("generate", help="write a schema from the sizes the env's module measures")
    g.add_argument("name")
    g.add_argument("--out", required=True, help="schema file to write ('-' prints)")
    g.add_argument("--force", action="store_true", help="overwrite an existing file")
    g.add_argument("--episode-limit", type=int, help="when the module gives none")
    args = p.parse_args(argv)
    if args.cmd == "generate":
        return _generate(args)
    bad = 0
    for name in args.names:
        try:
            s = check(name)
            print(f"ok {name}: {s.n_agents} agents, obs {s.obs_dim}, state {s.state_dim}, actions {s.n_actions}")
        except ImportError as e:  # the env's package is not installed here: nothing to compare with
            print(f"skip {name}: {e} (not installed in {sys.executable})")
        except EnvUnavailable as e:
            print(f"skip {name}: {str(e).splitlines()[0]}")
        except (SizeMismatch, OSError) as e:
            bad += 1
            print(f"lmac: {e}", file=sys.stderr)
        except UnknownFamily:
            # A typo in the family or a module not on the servers' path: the run would fail the
            # same way, so --check fails now, naming the schema that asks for it.
            bad += 1
            family = name.partition(":")[0]
            print(f"lmac: {schema_path(name)}: no module makes family {family!r} under {sys.executable}: "
                  f"put the folder holding {family.replace('.', '/')}.py on PYTHONPATH, install it, "
                  "or rename the schema's folder to the module's dotted path", file=sys.stderr)
        except ValueError as e:  # the env refused its schema itself (lbf, pz)
            bad += 1
            print(f"lmac: {e}", file=sys.stderr)
    return 1 if bad else 0


def _generate(args) -> int:
    import pathlib

    out = pathlib.Path(args.out)
    if args.out != "-" and out.exists() and not args.force:
        print(f"lmac: {out} exists (it may hold your descriptions); --force overwrites it", file=sys.stderr)
        return 2
    try:
        text = generate(args.name, args.episode_limit)
    except (ValueError, ImportError, EnvUnavailable) as e:
        print(f"lmac: {e}", file=sys.stderr)
        return 1
    if args.out == "-":
        sys.stdout.write(text)
        return 0
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(f"wrote {out}: replace the EDIT texts, then `lmac envs --check`")
    return 0


if __name__ == "__main__":
    sys.exit(main())
