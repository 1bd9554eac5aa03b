"""The Python half of the shm-schema contract: schema loading, the batch a step writes into,
and the interface every vectorized environment implements.

The schema files are the same TOML files the Rust crates read (``shm-schema``); this module
only reads the fields the environments need. Validation with precise errors lives in Rust
(``lmac envs --check``) and runs before any server starts.
"""
from __future__ import annotations

import abc
import dataclasses
import os
import pathlib
import tomllib

import numpy as np

SCHEMA_DIR = pathlib.Path(__file__).resolve().parent.parent / "schemas"


@dataclasses.dataclass(frozen=True)
class Schema:
    name: str
    n_agents: int
    obs_dim: int
    state_dim: int
    n_actions: int
    episode_limit: int
    message_columns: int
    alpha: float
    path: pathlib.Path
    raw: dict

    @staticmethod
    def load(path: str | pathlib.Path) -> "Schema":
        path = pathlib.Path(path)
        with open(path, "rb") as f:
            raw = tomllib.load(f)
        try:
            return Schema(
                name=raw["name"], n_agents=int(raw["n_agents"]), obs_dim=int(raw["obs_dim"]),
                state_dim=int(raw["state_dim"]), n_actions=int(raw["n_actions"]),
                episode_limit=int(raw["episode_limit"]),
                message_columns=int(raw.get("message_columns", 0)), alpha=float(raw["alpha"]),
                path=path, raw=raw)
        except KeyError as e:
            raise ValueError(f"{path}: missing field {e.args[0]!r}") from None


def schema_dir() -> pathlib.Path:
    """$LMAC_SCHEMA_DIR, else env-server/schemas. `lmac` sets LMAC_SCHEMA_DIR for the env servers
    it starts to the directory its Rust side reads, so both sides read the same files."""
    d = os.environ.get("LMAC_SCHEMA_DIR")
    return pathlib.Path(d) if d else SCHEMA_DIR


def schema_path(env_name: str) -> pathlib.Path:
    """`lbf:8x8-2p-2f-s1-coop` -> env-server/schemas/lbf/8x8-2p-2f-s1-coop.toml"""
    family, sep, variant = env_name.partition(":")
    if not sep or not family or not variant:
        raise ValueError(f"environment name {env_name!r} must look like FAMILY:VARIANT")
    return schema_dir() / family / f"{variant}.toml"


class EnvUnavailable(RuntimeError):
    """The environment cannot run on this machine (a game or package is missing); the message
    says what. `lmac envs --check` reports such an env as not checked instead of failing."""


@dataclasses.dataclass
class Batch:
    """Where one batched step is written. In the pipeline every field is a numpy view of the
    shared-memory slot (no copy); in the raw benchmark they are ordinary arrays.

    obs        float32 (B, n_agents, obs_dim)   (a strided view: message columns follow each row)
    state      float32 (B, state_dim)
    avail      uint8   (B, n_agents, n_actions) 1 = action available
    reward     float32 (B,)   team reward of the step that led here
    terminated uint8   (B,)   the environment ended the episode (win, loss, all food eaten)
    truncated  uint8   (B,)   the episode hit a time limit
    """
    obs: np.ndarray
    state: np.ndarray
    avail: np.ndarray
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray

    @staticmethod
    def allocate(schema: Schema, num_envs: int) -> "Batch":
        return Batch(
            obs=np.zeros((num_envs, schema.n_agents, schema.obs_dim), np.float32),
            state=np.zeros((num_envs, schema.state_dim), np.float32),
            avail=np.zeros((num_envs, schema.n_agents, schema.n_actions), np.uint8),
            reward=np.zeros(num_envs, np.float32),
            terminated=np.zeros(num_envs, np.uint8),
            truncated=np.zeros(num_envs, np.uint8))


def split_done(done, steps, limit, terminal=None):
    """(terminated, truncated) from a gym-style ``done`` that also fires at the env's own step
    limit (rware, old gym envs): an end at the limit is a truncation, the learner bootstraps
    from the observation after it; an end before it is a termination. Works on scalars and on
    arrays (one entry per env).

    steps     steps taken in the episode, this one included
    limit     the env's own step limit
    terminal  optional: what the env says about a real end (won, lost, all goals reached) where
              it knows; then a ``done`` with it is a termination even on the limit's step, and
              one without it a truncation even before (a time limit of another kind).
    """
    done = np.asarray(done, bool)
    real = np.asarray(steps) < limit if terminal is None else np.asarray(terminal, bool)
    terminated, truncated = done & real, done & ~real
    if terminated.ndim == 0:
        return bool(terminated), bool(truncated)
    return terminated, truncated


class VecEnv(abc.ABC):
    """B environments of one kind, stepped together.

    Contract:
    - ``reset(env_ids, out)`` starts new episodes in the listed envs and writes their first
      obs/state/avail into those rows of ``out`` (other rows untouched).
    - ``step(actions, out, active=None)`` applies int actions of shape (B, n_agents) to the envs
      and writes every row of obs/state/avail/reward/terminated of the envs it steps; it may set
      ``truncated`` for an env's own time limit. ``active`` (bool (B,), None = all) lists the
      envs to step: an inactive env's episode has ended (its last row carried the observation
      after a time limit) and the server resets it right after this call, so it must not be
      advanced where that could fail (a real game); a vectorized simulator may step it anyway,
      its rows are overwritten by the reset. The server loop (lmac_env.server) counts episode
      steps, truncates at the schema's episode_limit and calls ``reset`` for finished envs.
    - Deterministic for a given ``seed`` passed to the constructor.
    """
    schema: Schema
    num_envs: int

    @abc.abstractmethod
    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        """Start new episodes in ``env_ids`` (see the contract above)."""

    @abc.abstractmethod
    def step(self, actions: np.ndarray, out: Batch, active: np.ndarray | None = None) -> None:
        """Step the ``active`` envs (all when None) with ``actions`` (see the contract above)."""

    def close(self) -> None:
        pass
