"""Wall time of one sweep through Ray Tune against the same trials run one after another.

The guide's figure for `lmac-sweep` (docs/guide/sweeps.md): 4 trials (seeds 0, 1 x learn.lr 0.0005, 0.001; QMIX on LBF
8x8) run (a) with plain `lmac train`, one after another, (b) through `lmac-sweep` with
cpus_per_trial = 2 (the default: one trial at a time on 2 cores) and (c) with cpus_per_trial = 1
(two at a time). Ray runs in a network namespace with only loopback, as in the tests. Run it on a
quiet machine: the figure is a ratio of wall times measured in the same run.

    .venv/bin/python scripts/sweep_walltime.py --steps 200k --out docs/figures/sweep_lbf8x8.json
"""

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SEEDS = [0, 1]
LRS = [0.0005, 0.001]


def sweep_toml(storage: Path, name: str, steps: str, cpus: int, envs: int) -> str:
    return f"""[sweep]
name = "{name}"
storage = "{storage}"
seeds = {SEEDS}
search = "grid"
cpus_per_trial = {cpus}
max_failures = 0
env = "lbf:8x8-2p-2f-s1-coop"
algo = "qmix"
steps = "{steps}"

[run]
envs = {envs}

[search]
learn.lr = {LRS}
"""


def final_row(metrics: Path) -> dict:
    """The last training row (the final evaluation's row carries no env-steps rate)."""
    rows = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    rows = [row for row in rows if row.get("env_steps_per_s") is not None]
    if not rows:
        raise SystemExit(f"sweep_walltime: {metrics} has no training rows")
    return rows[-1]


def run_sequential(lmac: str, work: Path, steps: str, envs: int) -> dict:
    trials = []
    start = time.monotonic()
    for lr in LRS:
        for seed in SEEDS:
            out = work / f"lr{lr}_seed{seed}"
            t0 = time.monotonic()
            cmd = [lmac, "train", "--env", "lbf:8x8-2p-2f-s1-coop", "--algo", "qmix", "--steps", steps,
                   "--set", f"run.envs={envs}", "--set", f"learn.lr={lr}", "--seeds", str(seed), "--out", str(out)]
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            metrics = next(out.rglob("metrics.jsonl"))
            row = final_row(metrics)
            trials.append({"lr": lr, "seed": seed, "wall_s": round(time.monotonic() - t0, 2),
                           "t_env": row.get("t_env"), "env_steps_per_s": row.get("env_steps_per_s"),
                           "test_return_mean": row.get("test_return_mean")})
    return {"wall_s": round(time.monotonic() - start, 2), "trials": trials}


def run_sweep(work: Path, steps: str, cpus: int, envs: int) -> dict:
    storage = work / "sweeps"
    name = f"cpus{cpus}"
    config = work / f"{name}.toml"
    config.write_text(sweep_toml(storage, name, steps, cpus, envs))
    home = work / f"home_{name}"
    home.mkdir()
    # Ray's socket paths must stay under 107 bytes: its session files go in a short folder.
    ray_tmp = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    env = dict(os.environ, HOME=str(home), RAY_TMPDIR=ray_tmp)
    sweep = shutil.which("lmac-sweep", path=str(ROOT / ".venv" / "bin"))
    ip = shutil.which("ip") or "/usr/sbin/ip"
    inner = f"{ip} link set lo up && exec {sweep} --config {config}"
    prefix = ["unshare", "--net"] + ([] if os.geteuid() == 0 else ["--map-root-user"])
    t0 = time.monotonic()
    done = subprocess.run(prefix + ["sh", "-c", inner], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wall = round(time.monotonic() - t0, 2)
    shutil.rmtree(ray_tmp, ignore_errors=True)
    if done.returncode != 0:
        sys.stderr.write(done.stdout[-4000:])
        raise SystemExit(f"sweep_walltime: lmac-sweep ({name}) exited {done.returncode}")
    summary = json.loads((storage / name / "lmac_sweep.json").read_text())
    keep = ("trial_id", "config", "status", "t_env", "lmac_attempt", "test_return_mean")
    trials = [{key: trial.get(key) for key in keep} for trial in summary["trials"]]
    return {"cpus_per_trial": cpus, "wall_s": wall, "trials": trials}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", default="200k", help="env steps per trial (default 200k)")
    parser.add_argument("--envs", type=int, default=8, help="run.envs of every trial (default 8)")
    parser.add_argument("--out", type=Path, required=True, help="where the JSON goes")
    parser.add_argument("--lmac", default=str(ROOT / "target" / "release" / "lmac"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="lmac-sweep-walltime-") as tmp:
        work = Path(tmp)
        result = {
            "what": "4 trials (seeds 0,1 x learn.lr 0.0005,0.001), QMIX on lbf:8x8-2p-2f-s1-coop",
            "command": " ".join([".venv/bin/python", "scripts/sweep_walltime.py", "--steps", args.steps,
                                 "--envs", str(args.envs), "--out", str(args.out)]),
            "steps_per_trial": args.steps,
            "envs": args.envs,
            "cpus": os.cpu_count(),
            "machine": platform.processor() or platform.machine(),
            "load_before": os.getloadavg(),
        }
        print("[sweep_walltime] one after another with lmac train", flush=True)
        result["sequential"] = run_sequential(args.lmac, work / "sequential", args.steps, args.envs)
        print(f"[sweep_walltime]   {result['sequential']['wall_s']} s", flush=True)
        for cpus in (2, 1):
            print(f"[sweep_walltime] lmac-sweep, cpus_per_trial = {cpus}", flush=True)
            result[f"ray_cpus{cpus}"] = run_sweep(work, args.steps, cpus, args.envs)
            ratio = result[f"ray_cpus{cpus}"]["wall_s"] / result["sequential"]["wall_s"]
            result[f"ray_cpus{cpus}"]["ratio_to_sequential"] = round(ratio, 3)
            print(f"[sweep_walltime]   {result[f'ray_cpus{cpus}']['wall_s']} s ({ratio:.2f}x sequential)", flush=True)
        result["load_after"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"[sweep_walltime] wrote {args.out}")


if __name__ == "__main__":
    main()
