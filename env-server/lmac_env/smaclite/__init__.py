"""SMAC-Comm without StarCraft II: a vectorized numpy re-implementation of the four SMAC-Comm
maps (bane_vs_hM, 1o_10b_vs_1r, 2o_20b_vs_2r, 5z_vs_1ul). Not the game; see README.md for the
sources of every number and every simplification. `make("bane_vs_hM", 32, seed=0)`."""
from .env import SmacliteVecEnv, make
from .maps import MAPS

__all__ = ["SmacliteVecEnv", "make", "MAPS"]
