"""lmac-sweep (env-server/lmac_sweep): Ray Tune trials that run `lmac train`.

Both tests start a real local Ray through the `lmac-sweep` command line, inside a network
namespace that has only the loopback interface (`unshare --net`; `--map-root-user` when not root),
so nothing Ray opens can be reached from outside; Ray's session files go to a temporary
RAY_TMPDIR and its auth token to a temporary HOME. Without unshare or `ip`, the tests fail and
say so (they are not skipped).
"""

import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = pathlib.Path(__file__).resolve().parents[2]
LMAC = ROOT / "target" / "release" / "lmac"
CLI_TIMEOUT = 150  # seconds for one sweep on a loaded 2-core machine

SWEEP = """
[sweep]
name = "{name}"
storage = "store"
seeds = {seeds}
cpus_per_trial = 1
max_failures = 2
env = "lbf:8x8-2p-2f-s1-coop"
steps = {steps}

[run]
envs = 4
servers = 1
checkpoint_interval = {checkpoint_interval}
log_interval = 500
test_interval = {test_interval}
test_episodes = 4

[search]
learn.lr = {lrs}
"""


def _loopback_only() -> list:
    """A command prefix that runs its command in a new network namespace with only `lo` (up)."""
    unshare, ip = shutil.which("unshare"), shutil.which("ip") or ("/usr/sbin/ip" if os.path.exists("/usr/sbin/ip") else None)
    if not unshare or not ip:
        pytest.fail(f"keeping Ray on loopback needs `unshare` and `ip` (util-linux, iproute2); found unshare={unshare} ip={ip}")
    prefix = [unshare, "--net"] + ([] if os.geteuid() == 0 else ["--map-root-user"])
    probe = subprocess.run(prefix + ["sh", "-c", f"{ip} link set lo up && {ip} -o link show"], capture_output=True, text=True, timeout=30)
    if probe.returncode != 0:
        pytest.fail(f"cannot create a network namespace for Ray (unshare --net): {probe.stderr.strip()}")
    names = [l.split(":")[1].strip() for l in probe.stdout.splitlines() if l.strip()]
    assert names == ["lo"], f"the namespace should hold only loopback, has {names}"
    return prefix + ["sh", "-c", f'{ip} link set lo up && exec "$@"', "sh"]


class Sweep:
    """One `lmac-sweep` run in a sandbox: temporary HOME and RAY_TMPDIR, loopback only."""

    def __init__(self, tmp_path: pathlib.Path, text: str):
        assert LMAC.exists(), f"{LMAC} is missing: build it (scripts/setup.sh)"
        self.dir = tmp_path
        (tmp_path / "sweep.toml").write_text(text)
        (tmp_path / "home").mkdir()
        # Short: Ray's unix socket paths live under it (108-byte limit).
        self.ray_tmp = tempfile.mkdtemp(prefix="lmsw-", dir="/tmp")
        pp = str(ROOT / "env-server") + (":" + os.environ["PYTHONPATH"] if os.environ.get("PYTHONPATH") else "")
        self.env = dict(os.environ, HOME=str(tmp_path / "home"), RAY_TMPDIR=self.ray_tmp, PYTHONPATH=pp, LMAC_BIN=str(LMAC))
        for k in ("RAY_ADDRESS", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH"):
            self.env.pop(k, None)
        self.cmd = _loopback_only() + [sys.executable, "-m", "lmac_sweep", "--config", "sweep.toml"]
        self.proc = None

    def start(self, *extra: str):
        self.logname = "sweep" + "".join(extra).replace("-", "_") + ".log"
        self.log = open(self.dir / self.logname, "wb")
        self.t0 = time.monotonic()
        # `unshare` and `sh` exec: self.proc is the lmac-sweep process itself.
        self.proc = subprocess.Popen(self.cmd + list(extra), cwd=self.dir, env=self.env, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
        return self

    def output(self) -> str:
        return (self.dir / self.logname).read_text(errors="replace")

    def wait(self) -> int:
        try:
            rc = self.proc.wait(max(1.0, CLI_TIMEOUT - (time.monotonic() - self.t0)))
        except subprocess.TimeoutExpired:
            self.close()
            pytest.fail(f"lmac-sweep did not finish in {CLI_TIMEOUT} s; its output ends:\n{self.output()[-4000:]}")
        self.seconds = time.monotonic() - self.t0
        if "could not start or reach" in self.output():
            pytest.fail(f"Ray did not start:\n{self.output()[-3000:]}")
        return rc

    def close(self):
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        shutil.rmtree(self.ray_tmp, ignore_errors=True)

    def summary(self, name: str) -> dict:
        return json.loads((self.dir / "store" / name / "lmac_sweep.json").read_text())


@pytest.fixture
def sweep_in(tmp_path):
    made = []

    def make(text):
        s = Sweep(tmp_path, text)
        made.append(s)
        return s

    yield make
    for s in made:
        s.close()


def _results(trial_dir: str) -> list:
    return [json.loads(l) for l in open(os.path.join(trial_dir, "result.json")) if l.strip()]


def _run_dirs(runs: str, attempt: int) -> list:
    return sorted(p.parent for p in pathlib.Path(runs, f"attempt{attempt}").glob("**/config.toml"))


def test_a_two_trial_sweep_streams_metrics_and_checkpoints(sweep_in):
    s = sweep_in(SWEEP.format(name="two", seeds="[0]", steps=3000, checkpoint_interval=1000, test_interval=1500, lrs="[0.0005, 0.001]"))
    rc = s.start().wait()
    out = s.output()
    assert rc == 0, out[-4000:]
    assert "Started a local Ray instance" in out
    assert any(pathlib.Path(s.ray_tmp).glob("*/session_*")), "Ray's session files should be in the temporary RAY_TMPDIR"
    assert (s.dir / "home" / ".ray" / "auth_token").exists(), "Ray's auth token should be in the temporary HOME"
    summary = s.summary("two")
    trials = summary["trials"]
    assert len(trials) == 2
    assert sorted(t["config"]["learn.lr"] for t in trials) == [0.0005, 0.001]
    for t in trials:
        assert t["status"] == "TERMINATED", t
        assert t["t_env"] >= 3000 and t["checkpoint_t_env"] == t["t_env"] and t["lmac_attempt"] == 1, t
        # Tune holds the run's last checkpoint (lmac's checkpoint/ with its config and metrics).
        ck = pathlib.Path(t["checkpoint"], "run")
        assert json.loads((ck / "checkpoint" / "state.json").read_text())["counters"]["t_env"] == t["t_env"]
        assert (ck / "config.toml").exists()
        # Every metrics row came back as a Tune result, in order (checkpoint reports share the
        # t_env of the row they follow or precede, so the steps are read without repeats).
        rows = _results(t["trial_dir"])
        all_steps = [r["t_env"] for r in rows]
        steps = sorted(set(all_steps))
        assert all_steps == sorted(all_steps) and steps[0] == 0 and steps[-1] >= 3000 and len(steps) >= 7, all_steps
        assert any("test_return_mean" in r for r in rows)
        (run,) = _run_dirs(t["runs"], 1)
        cfg = tomllib.loads((run / "config.toml").read_text())
        assert cfg["learn"]["lr"] == t["config"]["learn.lr"] and cfg["run"]["envs"] == 4 and cfg["run"]["steps"] == 3000
    print(f"two-trial sweep: {s.seconds:.1f} s")


def _trainer_pids(under: str) -> list:
    """The `lmac child trainer` processes whose run directory is under `under`."""
    pids = []
    for p in pathlib.Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            args = (p / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        text = [a.decode(errors="replace") for a in args]
        if not ("child" in text and "trainer" in text and "--job" in text[:-1]):
            continue
        # The run directory is in the trainer's job file (supervisor::TrainerJobFile).
        try:
            work = json.loads(pathlib.Path(text[text.index("--job") + 1]).read_text())["job"]["work"]
        except (OSError, ValueError, KeyError):
            continue
        run_dir = next((v["dir"] for v in work.values() if "dir" in v), "") if isinstance(work, dict) else ""
        if run_dir.startswith(under):
            pids.append(int(p.name))
    return pids


def _first_checkpointed_trial(s: Sweep, name: str, attempt: int = 1):
    """Wait for a trial whose checkpoint Tune holds while its trainer runs: (trial id, that
    checkpoint's t_env, the trainer's pid)."""
    store = s.dir / "store" / name
    deadline = time.monotonic() + 100
    while time.monotonic() < deadline and s.proc.poll() is None:
        for ck in sorted(store.glob("run_trial_*/checkpoint_*/lmac_sweep.json")):
            trial_id = "_".join(ck.parent.parent.name.split("_")[2:4])
            pids = _trainer_pids(str(store / "lmac-runs" / trial_id / f"attempt{attempt}"))
            if not pids:
                continue
            try:
                # Tune copies a reported checkpoint into the store file by file: a file seen
                # mid-copy is empty or cut short, and that checkpoint is not held yet.
                return trial_id, json.loads(ck.read_text())["t_env"], pids[0]
            except (OSError, ValueError):
                continue
        time.sleep(0.2)
    pytest.fail("no trial reached a checkpoint while its trainer ran:\n" + s.output()[-4000:])


def test_a_killed_trainer_resumes_from_its_checkpoint(sweep_in):
    steps = 24000
    s = sweep_in(SWEEP.format(name="kill", seeds="[0, 1]", steps=steps, checkpoint_interval=3000, test_interval=6000, lrs="[0.0005]"))
    s.start()
    victim, killed_after, pid = _first_checkpointed_trial(s, "kill")
    os.kill(pid, signal.SIGKILL)
    rc = s.wait()
    out = s.output()
    assert rc == 0, out[-4000:]
    trials = {t["trial_id"]: t for t in s.summary("kill")["trials"]}
    assert len(trials) == 2
    for tid, t in trials.items():
        assert t["status"] == "TERMINATED" and t["t_env"] >= steps, t
        if tid != victim:
            assert t["lmac_attempt"] == 1, t
    t = trials[victim]
    # Restarted once by FailureConfig, from the checkpoint Tune held (not from scratch).
    assert t["lmac_attempt"] == 2, t
    resumed = t["resumed_from_t_env"]
    assert resumed is not None and resumed >= killed_after >= 3000, (resumed, killed_after)
    first = _run_dirs(t["runs"], 1)[0]
    assert "trainer" in (first.parents[3] / "lmac.log").read_text(errors="replace")
    (run2,) = _run_dirs(t["runs"], 2)
    log2 = (run2.parent / "lmac.log").read_text(errors="replace")
    assert f"resuming from" in log2 and f"at t_env {resumed}" in log2, log2[-2000:]
    # lmac's own metrics continue from the checkpoint without a step backwards...
    rows = [json.loads(l) for l in (run2 / "metrics.jsonl").read_text().splitlines() if l.strip()]
    t_env = [r["t_env"] for r in rows if "checkpoint" not in r]
    assert t_env == sorted(t_env) and t_env[-1] >= steps, t_env
    assert any(r.get("checkpoint") and r["t_env"] == resumed for r in rows)
    # ... and so do the results Tune got from the second attempt.
    second = [r for r in _results(t["trial_dir"]) if r.get("lmac_attempt") == 2]
    assert second and all(r["t_env"] > resumed for r in second), [r["t_env"] for r in second]
    assert all(r["resumed_from_t_env"] == resumed for r in second)
    print(f"kill-and-resume sweep: {s.seconds:.1f} s; killed {victim}'s trainer after checkpoint t_env {killed_after}, resumed at {resumed}")


def test_an_interrupted_sweep_continues_with_resume(sweep_in):
    steps = 18000
    s = sweep_in(SWEEP.format(name="resume", seeds="[0]", steps=steps, checkpoint_interval=3000, test_interval=6000, lrs="[0.0005, 0.001]"))
    s.start()
    _first_checkpointed_trial(s, "resume")
    time.sleep(2)  # the driver registers the checkpoint a moment after the trial wrote it
    s.proc.send_signal(signal.SIGINT)  # Ctrl-C: Tune saves the experiment state and stops
    rc = s.wait()
    first = s.seconds
    assert rc == 130, f"an interrupted sweep exits with 130, got {rc}:\n" + s.output()[-3000:]
    assert "--resume" in s.output()
    before = {t["trial_id"]: t for t in s.summary("resume")["trials"]}
    assert all(t["status"] == "UNFINISHED" for t in before.values()), before
    # The checkpoints Tune holds for the unfinished trials.
    held = {tid: json.loads(pathlib.Path(t["checkpoint"], "lmac_sweep.json").read_text())["t_env"]
            for tid, t in before.items() if t["checkpoint"]}
    assert held, "no trial had a checkpoint registered with Tune when the sweep was interrupted:\n" + s.output()[-3000:]
    rc = s.start("--resume").wait()
    out = s.output()
    assert rc == 0, out[-4000:]
    trials = {t["trial_id"]: t for t in s.summary("resume")["trials"]}
    assert trials.keys() == before.keys() and len(trials) == 2
    for t in trials.values():
        assert t["status"] == "TERMINATED" and t["t_env"] >= steps, t
    for tid, at in held.items():
        # Continued from the checkpoint Tune held when the sweep stopped, in a new attempt.
        t = trials[tid]
        assert t["lmac_attempt"] == 2 and t["resumed_from_t_env"] == at >= 3000, t
        second = [r for r in _results(t["trial_dir"]) if r.get("lmac_attempt") == 2]
        assert second and all(r["t_env"] > at for r in second)
    print(f"interrupted sweep: {first:.1f} s, then --resume: {s.seconds:.1f} s; resumed at t_env {held}")


def test_a_sweep_file_becomes_lmac_commands(tmp_path):
    """No Ray: the sweep file's settings, search space and seeds as `lmac` arguments."""
    from lmac_sweep import sweep as sw

    (tmp_path / "s.toml").write_text("""
[sweep]
seeds = [3, 4]
search = "random"
num_samples = 5
env = "lbf:8x8-2p-2f-s1-coop"
steps = "50k"
lmac = "/x/lmac"
[run]
envs = 8
[method]
encoder = "window"
[search]
learn.lr = { loguniform = [1e-4, 1e-3] }
learn.batch_size = [16, 32]
""")
    s = sw.load_sweep(tmp_path / "s.toml", cwd=tmp_path)
    assert s["name"] == "s" and s["storage"] == str(tmp_path / "sweeps") and s["runs_dir"] == str(tmp_path / "sweeps" / "s" / "lmac-runs")
    cmd = sw.train_command(s, {"learn.lr": 0.0003, "learn.batch_size": 16, "seed": 4}, "/out")
    assert cmd == ["/x/lmac", "train", "--env", "lbf:8x8-2p-2f-s1-coop", "--steps", "50k",
                   "--set", "run.envs=8", "--set", 'method.encoder="window"', "--set", "learn.lr=0.0003",
                   "--set", "learn.batch_size=16", "--seeds", "4", "--out", "/out"]
    space = sw.param_space(s)
    assert set(space) == {"learn.lr", "learn.batch_size", "seed"}
    assert space["seed"] == {"grid_search": [3, 4]}  # seeds stay a grid axis in a random search
    assert sw.toml_value(True) == "true" and sw.toml_value([1, "a"]) == '[1, "a"]' and sw.toml_value(1e-4) == "0.0001"
    for text, says in [
        ("[sweep]\nbogus = 1\n", "unknown key(s) ['bogus']"),
        ("[search]\nlr = [1]\n", "[search] lr: searched keys are run.*, learn.* or method.*"),
        ("[learn]\nlr = 1\n[search]\nlearn.lr = [1, 2]\n", "learn.lr is both fixed"),
        ("[search]\nlearn.lr = { normal = [0, 1] }\n", "learn.lr"),
        ("[sweep]\nmode = \"tune\"\n", "mode"),
    ]:
        (tmp_path / "bad.toml").write_text(text)
        with pytest.raises(sw.SweepError) as e:
            sw.load_sweep(tmp_path / "bad.toml", cwd=tmp_path)
        assert "bad.toml" in str(e.value) and says in str(e.value), str(e.value)
