"""Environment families by name prefix. `make("lbf:8x8-2p-2f-s1-coop", 32, seed=0)`.

A name is `FAMILY:VARIANT`; its schema is `schemas/FAMILY/VARIANT.toml`. The family's module
(any module with `make(variant: str, num_envs: int, seed: int) -> VecEnv`) is found, in order:

1. the built-in families below (`pz` is any PettingZoo parallel environment, see `lmac_env.pz`);
2. an installed package's entry point in the group `lmac_env.families` whose name is the family
   (`[project.entry-points."lmac_env.families"] myenv = "mypkg.lmac_env"`);
3. the family itself as a dotted module path: `mypkg.myenvs:easy` imports `mypkg.myenvs` (from
   the env servers' Python: LMAC_PYTHON, else the repository's .venv, with PYTHONPATH kept) and
   reads `schemas/mypkg.myenvs/easy.toml`.

So a new environment needs a schema and a `VecEnv`, never an edit here.
"""
from __future__ import annotations

import importlib
import importlib.metadata
import types

from .core import VecEnv


class UnknownFamily(ValueError):
    """No built-in, entry point or importable module makes this family (a typo, or the module's
    folder not on the env servers' path)."""

ENTRY_POINT_GROUP = "lmac_env.families"

# family prefix -> module with `make(variant: str, num_envs: int, seed: int) -> VecEnv`
FAMILIES = {
    "lbf": "lmac_env.lbf",
    "smaclite": "lmac_env.smaclite",
    "smac": "lmac_env.smac",
    "grf": "lmac_env.grf",
    "pz": "lmac_env.pz",
    "rware": "lmac_env.rware",
}


def _entry_point(family: str):
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        if ep.name == family:
            return ep
    return None


def family_module(family: str, env_name: str):
    """The module that makes `family`'s environments (see the module doc for the order)."""
    if family in FAMILIES:
        return importlib.import_module(FAMILIES[family])
    ep = _entry_point(family)
    if ep is not None:
        obj = ep.load()  # a module with make(), or make itself
        return obj if hasattr(obj, "make") else types.SimpleNamespace(make=obj, __name__=ep.value)
    if family and all(part.isidentifier() for part in family.split(".")):
        try:
            return importlib.import_module(family)
        except ModuleNotFoundError as e:
            if e.name is None or not family.startswith(e.name):
                raise  # the module exists but one of its own imports is missing
    raise UnknownFamily(f"unknown environment family {family!r} in {env_name!r}: not built in "
                     f"({', '.join(sorted(FAMILIES))}), no {ENTRY_POINT_GROUP!r} entry point of that name, "
                     "and no importable module of that dotted path")


def make(env_name: str, num_envs: int, seed: int = 0) -> VecEnv:
    family, _, variant = env_name.partition(":")
    module = family_module(family, env_name)
    make_fn = getattr(module, "make", None)
    if not callable(make_fn):
        raise ValueError(f"{env_name}: module {module.__name__} has no make(variant, num_envs, seed)")
    return make_fn(variant, num_envs, seed)
