"""End to end at the paper's schedule, how the learner uses the second core:
`lmac train` on smaclite:1o_10b_vs_1r at `--preset paper` with the authors' design, in these
settings measured back to back, alternating, `--rounds` times (`--settings` picks some):

- `paper`: the preset as it is: each update's batch in two halves on two threads
  (learn.data_parallel), burn's flex backend free to run its large matmuls on rayon's two threads;
- `target-on-second-core`: learn.data_parallel=false: the target network unrolled on a second
  thread during the online pass (the preset before data_parallel);
- `one-thread-gemm`: `target-on-second-core` with RAYON_NUM_THREADS=1 (matmuls on one thread);
- `serial-target`: learn.data_parallel=false, learn.parallel_target=false;
- `one-core`: all three off: the learner on one core.

The rate is env steps per second between the first metrics row past `--from` steps and the
last row (start-up, the first 32 episodes without updates and the buffer filling excluded).

    python scripts/cores_ab.py target/release/lmac docs/figures/cores_ab_lmac_1o10b.json --algo lmac --steps 40k --rounds 1
"""
import argparse
import csv
import json
import os
import pathlib
import statistics
import subprocess
import tempfile

SERIAL = ["--set", "learn.data_parallel=false"]
SETTINGS = {
    "paper": ({}, []),
    "target-on-second-core": ({}, SERIAL),
    "one-thread-gemm": ({"RAYON_NUM_THREADS": "1"}, SERIAL),
    "serial-target": ({}, SERIAL + ["--set", "learn.parallel_target=false"]),
    "one-core": ({"RAYON_NUM_THREADS": "1"}, SERIAL + ["--set", "learn.parallel_target=false"]),
}


def steps(text: str) -> int:
    text = text.lower()
    mult = {"k": 1_000, "m": 1_000_000}.get(text[-1], 1)
    return int(float(text.rstrip("km")) * mult)


def rate(metrics: pathlib.Path, start: int) -> tuple[float, int]:
    rows = [r for r in csv.DictReader(open(metrics)) if r["wall_s"]]
    first = next(r for r in rows if int(r["t_env"]) >= start)
    last = rows[-1]
    dt = float(last["wall_s"]) - float(first["wall_s"])
    updates = int(last["updates"]) - int(first["updates"])
    return (int(last["t_env"]) - int(first["t_env"])) / dt, round(1000 * dt / max(updates, 1), 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("lmac")
    ap.add_argument("out")
    ap.add_argument("--algo", default="lmac")
    ap.add_argument("--steps", default="40k")
    ap.add_argument("--from", dest="start", default="10k")
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--settings", default=",".join(SETTINGS), help="comma-separated subset of: " + ", ".join(SETTINGS))
    a = ap.parse_args()
    chosen = a.settings.split(",")
    unknown = [c for c in chosen if c not in SETTINGS]
    if unknown:
        ap.error(f"--settings: unknown {unknown}; known: {', '.join(SETTINGS)}")
    results = {name: [] for name in chosen}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.rounds):
            for name in chosen:
                env, extra = SETTINGS[name]
                out = pathlib.Path(tmp) / f"{name}-{r}"
                cmd = [a.lmac, "train", "--env", "smaclite:1o_10b_vs_1r", "--algo", a.algo, "--preset", "paper",
                       "--steps", a.steps, "--seeds", "0", "--out", str(out),
                       "--set", "run.final_eval_episodes=0", "--set", "run.checkpoint_interval=1000000", *extra]
                if a.algo == "lmac":
                    cmd += ["--protocol", "paper"]
                subprocess.run(cmd, env={**os.environ, **env}, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                metrics = next(out.glob("**/metrics.csv"))
                sps, ms = rate(metrics, steps(a.start))
                results[name].append({"env_steps_per_s": round(sps, 1), "ms_per_update": ms})
                print(f"round {r} {name}: {sps:.1f} env steps/s, {ms} ms per update (wall time / updates)", flush=True)
    summary = {name: statistics.median(x["env_steps_per_s"] for x in v) for name, v in results.items()}
    doc = {
        "command": f"python scripts/cores_ab.py LMAC {a.out} --algo {a.algo} --steps {a.steps} --from {a.start} --rounds {a.rounds} --settings {a.settings}",
        "env": "smaclite:1o_10b_vs_1r", "algo": a.algo, "preset": "paper", "steps": a.steps,
        "settings": {k: {"env": SETTINGS[k][0], "args": SETTINGS[k][1]} for k in chosen},
        "runs": results,
        "median_env_steps_per_s": summary,
    }
    base = "one-core" if "one-core" in summary else chosen[-1]
    doc[f"ratio_to_{base}"] = {k: round(v / summary[base], 3) for k, v in summary.items()}
    pathlib.Path(a.out).write_text(json.dumps(doc, indent=2))
    print(json.dumps(doc[f"ratio_to_{base}"]))


if __name__ == "__main__":
    main()
