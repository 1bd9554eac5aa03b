"""The Multi-Robot Warehouse family (`rware:tiny-2ag`, `rware:small-4ag`, lmac_env/rware.py): sizes
against the real rware 2.0.0, seeds, rware's done at its step limit as a truncation, and a run
through the real pipeline. Skipped where rware is not installed."""
import numpy as np
import pytest

pytest.importorskip("rware", reason="rware is not installed (pip install rware==2.0.0)")

from lmac_env.core import Batch  # noqa: E402
from lmac_env.registry import make  # noqa: E402
from lmac_env.sizes import check  # noqa: E402
from test_pz_cli import run  # noqa: E402


@pytest.mark.parametrize("name", ["rware:tiny-2ag", "rware:small-4ag"])
def test_the_schemas_fit_rware(name):
    s = check(name)
    assert s.obs_dim == 71 and s.n_actions == 5 and s.state_dim == 71 * s.n_agents


def test_seeded_and_the_step_limit_is_a_truncation():
    runs = []
    for _ in range(2):
        env = make("rware:tiny-2ag", 2, seed=7)
        out = Batch.allocate(env.schema, 2)
        env.reset(np.arange(2), out)
        rng = np.random.default_rng(0)
        seen = []
        for t in range(env.schema.episode_limit):
            env.step(rng.integers(0, 5, (2, 2)), out)
            seen.append(out.obs.copy())
            last = t == env.schema.episode_limit - 1
            assert out.terminated.tolist() == [0, 0] and out.truncated.tolist() == [int(last)] * 2
        runs.append(np.stack(seen))
    assert np.array_equal(runs[0], runs[1])


def test_through_the_pipeline():
    r = run(["run", "--env", "rware:tiny-2ag", "--envs", "4", "--steps", "4000", "--verify"])
    assert r.returncode == 0, r.stderr[-3000:]
    assert "0 invariant violations" in r.stdout, r.stdout


def test_generate_measures_the_shipped_sizes(tmp_path):
    r = run(["envs", "--generate", "rware:tiny-2ag"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "rware:tiny-2ag: 2 agents, obs 71, state 142, actions 5, episode limit 500, message columns 73" in r.stdout
