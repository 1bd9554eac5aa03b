"""`lmac campaign run --ray local`: a campaign's cells as Ray tasks on a local Ray cluster of this
machine (env-server/lmac_sweep/campaign.py), writing the same results tree as a local run.

Ray runs in a network namespace with only loopback, its session files in a temporary RAY_TMPDIR
and its token in a temporary HOME, as in test_sweep.py.
"""

import json
import os
import pathlib
import shutil
import subprocess
import tempfile

from test_sweep import LMAC, ROOT, _loopback_only

CAMPAIGN = """
[campaign]
title = "ray"
out = "tree"
set = ["run.envs=4", "run.servers=1", "run.test_interval=1000", "run.test_episodes=2", "run.log_interval=500", "run.final_eval_episodes=2"]

[[stage]]
name = "s"
tasks = ["lbf:8x8-2p-2f-s1-coop"]
algos = ["qmix", "vdn"]
seeds = [0]
steps = 1500
"""


def test_a_campaign_runs_its_cells_as_ray_tasks_into_the_same_tree(tmp_path):
    assert LMAC.exists(), f"{LMAC} is missing: build it (scripts/setup.sh)"
    (tmp_path / "c.toml").write_text(CAMPAIGN)
    (tmp_path / "home").mkdir()
    ray_tmp = tempfile.mkdtemp(prefix="lmcp-", dir="/tmp")
    env = dict(os.environ, HOME=str(tmp_path / "home"), RAY_TMPDIR=ray_tmp, LMAC_ROOT=str(ROOT))
    for k in ("RAY_ADDRESS", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH"):
        env.pop(k, None)
    try:
        cmd = _loopback_only() + [str(LMAC), "campaign", "run", "c.toml", "--ray", "local", "--cpus-per-cell", "1"]
        p = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240)
        out = p.stdout + p.stderr
        assert p.returncode == 0, out[-4000:]
        assert "Started a local Ray instance" in out and "2 cells submitted to a cluster of" in out, out[-3000:]
        assert out.count(": done on ") == 2, out[-3000:]
        assert "2 cells: 2 finished" in out, out[-3000:]
        # The tree a local run writes: an experiment per stage and task, a run per cell.
        for algo in ("qmix", "vdn"):
            run = tmp_path / "tree" / "s" / "lbf_8x8-2p-2f-s1-coop" / "runs" / algo / "seed0"
            assert (run / "config.toml").exists() and (run / "marl_eval.json").exists(), algo
            assert (tmp_path / "tree" / "logs" / f"s__lbf_8x8-2p-2f-s1-coop__{algo}__seed0.log").exists()
        status = subprocess.run([str(LMAC), "campaign", "status", "c.toml", "--json"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
        cells = json.loads(status.stdout)["cells"]
        assert [c["status"]["state"] for c in cells] == ["finished", "finished"], cells
        # Nothing left: a rerun hands Ray nothing.
        again = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
        assert again.returncode == 0 and "nothing left to train" in again.stderr, again.stderr[-2000:]
    finally:
        shutil.rmtree(ray_tmp, ignore_errors=True)
