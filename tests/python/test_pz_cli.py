"""`lmac envs --generate pz:...` and `lmac envs --check` through the real binary (the Rust CLI
calls `python -m lmac_env.pz` as it starts env servers). Uses the newest of
target/{release,debug}/lmac; skipped when neither is built."""
import os
import pathlib
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
HERE = pathlib.Path(__file__).resolve().parent


def lmac_binary():
    found = [p for p in (ROOT / "target/release/lmac", ROOT / "target/debug/lmac") if p.is_file()]
    if not found:
        pytest.skip("no lmac binary built (cargo build --release --bin lmac)")
    return max(found, key=lambda p: p.stat().st_mtime)


def run(args, schema_dir=None, cwd=None):
    env = dict(os.environ, LMAC_ROOT=str(ROOT),
               PYTHONPATH=str(HERE) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("LMAC_SCHEMA_DIR", None)
    if schema_dir is not None:
        env["LMAC_SCHEMA_DIR"] = str(schema_dir)
    return subprocess.run([str(lmac_binary()), *args], capture_output=True, text=True, env=env, timeout=120,
                          cwd=cwd)


def test_generate_then_check_then_refuse_a_wrong_schema(tmp_path):
    r = run(["envs", "--generate", "pz:pz_toy,max_cycles=7"], tmp_path)
    assert r.returncode == 0, r.stderr
    path = tmp_path / "pz" / "pz_toy,max_cycles=7.toml"
    assert path.is_file() and "3 agents, obs 6, state 18, actions 6, episode limit 7" in r.stdout
    r = run(["envs", "--generate", "pz:pz_toy,max_cycles=7"], tmp_path)
    assert r.returncode != 0 and "--force" in r.stderr, "an existing schema is not overwritten"
    r = run(["envs", "--check"], tmp_path)
    assert r.returncode != 0 and f"{path}: task, reward, actions[0]" in r.stderr, "placeholders left"
    path.write_text(path.read_text().replace("EDIT: ", ""))
    r = run(["envs", "--check"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "pz:pz_toy,max_cycles=7" in r.stdout
    path.write_text(path.read_text().replace("n_actions = 6", "n_actions = 7")
                    .replace('actions = ["', 'actions = ["extra", "'))
    r = run(["envs", "--check"], tmp_path)
    assert r.returncode != 0
    assert "n_actions = 7 but the largest action space has 6 actions" in r.stderr, r.stderr
    r = run(["envs", "--generate", "lbf:whatever"], tmp_path)
    assert r.returncode != 0 and "unknown LBF variant 'whatever'" in r.stderr, r.stderr


def test_a_pipeline_run_on_a_generated_schema_outside_the_repository(tmp_path):
    """Run from a project folder with its own env-server/schemas (found from the current
    directory, no LMAC_SCHEMA_DIR): the env servers, started from the repository, read the schema
    the Rust side found and validated."""
    (tmp_path / "env-server" / "schemas").mkdir(parents=True)
    r = run(["envs", "--generate", "pz:pz_toy,max_cycles=7"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "env-server" / "schemas" / "pz" / "pz_toy,max_cycles=7.toml").is_file()
    r = run(["run", "--env", "pz:pz_toy,max_cycles=7", "--envs", "2", "--steps", "400", "--verify"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "0 invariant violations" in r.stdout, r.stdout
