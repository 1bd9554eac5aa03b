"""lmac environment servers.

An environment family plugs in by shipping a schema file under ``env-server/schemas/<family>/``
and a :class:`lmac_env.core.VecEnv` subclass registered in :mod:`lmac_env.registry`.
"""


def parallel_env(name: str, **kwargs):
    """The lmac environment ``name`` as a PettingZoo ParallelEnv (see :mod:`lmac_env.parallel`;
    imported on first use, so the env servers do not need PettingZoo)."""
    from .parallel import parallel_env as make_parallel
    return make_parallel(name, **kwargs)
