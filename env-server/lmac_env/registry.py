"""Environment families by name prefix. `make("lbf:8x8-2p-2f-s1-coop", 32, seed=0)`."""
from __future__ import annotations

import importlib

from .core import VecEnv

# family prefix -> module with `make(variant: str, num_envs: int, seed: int) -> VecEnv`
FAMILIES = {
    "lbf": "lmac_env.lbf",
    "smaclite": "lmac_env.smaclite",
    "smac": "lmac_env.smac",
    "grf": "lmac_env.grf",
}


def make(env_name: str, num_envs: int, seed: int = 0) -> VecEnv:
    family, _, variant = env_name.partition(":")
    if family not in FAMILIES:
        raise ValueError(f"unknown environment family {family!r} in {env_name!r}; "
                         f"known: {', '.join(sorted(FAMILIES))}")
    module = importlib.import_module(FAMILIES[family])
    return module.make(variant, num_envs, seed)
