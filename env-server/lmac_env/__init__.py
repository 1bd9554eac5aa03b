"""lmac environment servers.

An environment family plugs in by shipping a schema file under ``env-server/schemas/<family>/``
and a :class:`lmac_env.core.VecEnv` subclass registered in :mod:`lmac_env.registry`.
"""
