"""`lmac-sweep --config sweep.toml [--resume] [--address ADDR]`.

A sweep file (TOML):

    [sweep]
    name = "lbf-lr"                  # the experiment's directory under `storage`
    storage = "sweeps"               # results and Tune checkpoints (shared storage on a cluster)
    mode = "train"                   # "train" (one trial per setting x seed) or "experiment"
    search = "grid"                  # "grid" or "random" (lists become random choices)
    num_samples = 1                  # random: configurations drawn; grid: repeats of the grid
    seeds = [0, 1]                   # a grid axis in both searches
    cpus_per_trial = 2
    max_failures = 2                 # restarts of a failed trial, each from its last checkpoint
    env = "lbf:8x8-2p-2f-s1-coop"    # also algo, steps, preset, protocol, config (lmac train's flags)
    steps = "200k"

    [run]                            # fixed settings: --set run.envs=8 ...
    envs = 8
    [learn]
    [method]

    [search]                         # searched settings: a list is a grid axis, a table a distribution
    learn.lr = [0.0005, 0.001]
    learn.batch_size = { choice = [16, 32] }
    learn.gamma = { uniform = [0.95, 0.995] }

Every trial is `lmac train ... --set key=value ... --seeds k --out <runs>/<trial id>/attempt<n>`;
see docs/guide/sweeps.md.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import math
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import time

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

SWEEP_KEYS = {
    "name", "storage", "runs_dir", "mode", "search", "num_samples", "seeds", "cpus_per_trial",
    "max_failures", "max_concurrent_trials", "keep_checkpoints", "random_seed", "lmac", "metric",
    "metric_mode", "env", "algo", "steps", "preset", "protocol", "config", "num_cpus",
}
TRAIN_FLAGS = ("env", "algo", "steps", "preset", "protocol", "config")
DISTRIBUTIONS = {"choice", "uniform", "loguniform", "randint", "lograndint", "grid"}
SECTIONS = ("run", "learn", "method")


class SweepError(Exception):
    """A sweep file or command-line mistake: printed without a traceback."""


# ----------------------------------------------------------------------------------------------
# The sweep file


def _flatten(table: dict, prefix: str, where: str, search: bool = False) -> dict:
    """`{learn: {lr: [..]}}` -> `{"learn.lr": [..]}`; in [search] a table below `section.key` is a
    distribution (a leaf)."""
    out = {}
    for k, v in table.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and not (len(v) == 1 and next(iter(v)) in DISTRIBUTIONS):
            if search and ("." in key or any(d in v for d in DISTRIBUTIONS)):
                raise SweepError(f"{where} {key}: a distribution is a table with one key of {sorted(DISTRIBUTIONS)}, got {sorted(v)}")
            out.update(_flatten(v, key + ".", where, search))
        else:
            out[key] = v
    return out


def load_sweep(path: str | os.PathLike, cwd: str | os.PathLike | None = None) -> dict:
    """Read and check a sweep file; relative paths are resolved against `cwd` (default: the
    current directory), as `lmac train` does. Errors name the file and the key."""
    path = pathlib.Path(path)
    cwd = pathlib.Path(cwd or os.getcwd())
    try:
        raw = tomllib.loads(path.read_text())
    except OSError as e:
        raise SweepError(f"{path}: {e.strerror}") from None
    except tomllib.TOMLDecodeError as e:
        raise SweepError(f"{path}: not valid TOML: {e}") from None
    unknown = set(raw) - {"sweep", "search", "experiment", *SECTIONS}
    if unknown:
        raise SweepError(f"{path}: unknown section(s) {sorted(unknown)}; known: sweep, search, run, learn, method, experiment")
    sw = dict(raw.get("sweep", {}))
    bad = set(sw) - SWEEP_KEYS
    if bad:
        raise SweepError(f"{path}: [sweep] unknown key(s) {sorted(bad)}; known: {sorted(SWEEP_KEYS)}")
    s: dict = {
        "file": str(path.resolve()),
        "name": str(sw.get("name", path.stem)),
        "mode": sw.get("mode", "train"),
        "search": sw.get("search", "grid"),
        "num_samples": int(sw.get("num_samples", 1)),
        "seeds": list(sw.get("seeds", [0])),
        "cpus_per_trial": float(sw.get("cpus_per_trial", 2)),
        "max_failures": int(sw.get("max_failures", 2)),
        "max_concurrent_trials": int(sw.get("max_concurrent_trials", 0)),
        "keep_checkpoints": int(sw.get("keep_checkpoints", 2)),
        "random_seed": sw.get("random_seed"),
        "metric": str(sw.get("metric", "test_return_mean")),
        "metric_mode": str(sw.get("metric_mode", "max")),
        "num_cpus": sw.get("num_cpus"),
        "lmac": sw.get("lmac"),
    }
    if s["mode"] not in ("train", "experiment"):
        raise SweepError(f"{path}: [sweep] mode = {s['mode']!r}: must be \"train\" or \"experiment\"")
    if s["search"] not in ("grid", "random"):
        raise SweepError(f"{path}: [sweep] search = {s['search']!r}: must be \"grid\" or \"random\"")
    if not s["seeds"] or not all(isinstance(x, int) and x >= 0 for x in s["seeds"]):
        raise SweepError(f"{path}: [sweep] seeds must be a non-empty list of non-negative integers")
    if s["num_samples"] < 1 or s["cpus_per_trial"] <= 0 or s["max_failures"] < 0 or s["keep_checkpoints"] < 1:
        raise SweepError(f"{path}: [sweep] num_samples >= 1, cpus_per_trial > 0, max_failures >= 0, keep_checkpoints >= 1")
    if s["metric_mode"] not in ("max", "min"):
        raise SweepError(f"{path}: [sweep] metric_mode must be \"max\" or \"min\"")
    storage = str(sw.get("storage", "sweeps"))
    s["storage"] = storage if "://" in storage else str((cwd / storage).resolve())
    # Where the lmac run directories go: under the experiment on a filesystem storage, else the
    # trial's local working directory (only the Tune checkpoints then reach the storage).
    runs = sw.get("runs_dir")
    if runs:
        s["runs_dir"] = str((cwd / str(runs)).resolve())
    elif "://" not in storage:
        s["runs_dir"] = str(pathlib.Path(s["storage"]) / s["name"] / "lmac-runs")
    else:
        s["runs_dir"] = ""
    flags = {}
    for k in TRAIN_FLAGS:
        if k in sw:
            v = str(sw[k])
            if k in ("config", "protocol") and v and not v.startswith("/"):
                # protocol may be files joined by '+'
                v = "+".join(str((cwd / f).resolve()) for f in v.split("+"))
            flags[k] = v
    s["flags"] = flags
    fixed = {}
    for sec in SECTIONS:
        if sec in raw:
            if not isinstance(raw[sec], dict):
                raise SweepError(f"{path}: [{sec}] must be a table")
            fixed.update(_flatten(raw[sec], sec + ".", path.name))
    s["fixed"] = fixed
    space = _flatten(raw.get("search", {}), "", f"{path}: [search]", search=True)
    for key, v in space.items():
        if key.split(".")[0] not in SECTIONS or "." not in key:
            raise SweepError(f"{path}: [search] {key}: searched keys are run.*, learn.* or method.* settings")
        if isinstance(v, list):
            if not v:
                raise SweepError(f"{path}: [search] {key}: an empty list")
        elif isinstance(v, dict):
            (kind, args), = v.items()
            if not isinstance(args, list) or (kind in ("uniform", "loguniform", "randint", "lograndint") and len(args) != 2):
                raise SweepError(f"{path}: [search] {key}: {{ {kind} = [...] }} needs a list" + (" [low, high]" if kind != "choice" else ""))
        else:
            raise SweepError(f"{path}: [search] {key}: give a list (grid axis) or a table such as {{ loguniform = [1e-4, 1e-3] }}")
        if key in fixed:
            raise SweepError(f"{path}: {key} is both fixed ([{key.split('.')[0]}]) and searched ([search])")
    s["space"] = space
    exp = raw.get("experiment", {})
    if exp and s["mode"] != "experiment":
        raise SweepError(f"{path}: an [experiment] section needs [sweep] mode = \"experiment\"")
    s["experiment"] = dict(exp)
    return s


def param_space(s: dict) -> dict:
    """The Tune search space: one entry per searched setting, plus the seed in train mode."""
    from ray import tune

    space = {}
    for key, v in s["space"].items():
        if isinstance(v, list):
            space[key] = tune.grid_search(v) if s["search"] == "grid" else tune.choice(v)
        else:
            (kind, args), = v.items()
            if kind == "grid":
                space[key] = tune.grid_search(args)
            elif kind == "choice":
                space[key] = tune.choice(args)
            elif kind == "uniform":
                space[key] = tune.uniform(*args)
            elif kind == "loguniform":
                space[key] = tune.loguniform(*args)
            elif kind == "randint":
                space[key] = tune.randint(*args)
            elif kind == "lograndint":
                space[key] = tune.lograndint(*args)
    if s["mode"] == "train":
        space["seed"] = tune.grid_search(s["seeds"])
    return space


def toml_value(v) -> str:
    """A Python value as the TOML literal `lmac --set key=value` parses."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if hasattr(v, "item"):  # numpy scalars from Tune's samplers
        return toml_value(v.item())
    raise SweepError(f"cannot write {v!r} as a TOML value")


def lmac_binary(s: dict) -> str:
    """`[sweep] lmac`, else $LMAC_BIN, else this checkout's target/release/lmac, else `lmac` on PATH.
    Resolved on the node that runs the trial."""
    for cand in (s.get("lmac"), os.environ.get("LMAC_BIN")):
        if cand:
            return str(cand)
    here = pathlib.Path(__file__).resolve().parents[2] / "target" / "release" / "lmac"
    if here.exists():
        return str(here)
    found = shutil.which("lmac")
    if found:
        return found
    raise RuntimeError("cannot find the lmac binary: set [sweep] lmac, $LMAC_BIN, or build target/release/lmac")


def train_command(s: dict, config: dict, out: str) -> list[str]:
    cmd = [lmac_binary(s), "train"]
    for k, v in s["flags"].items():
        cmd += [f"--{k}", v]
    for k, v in {**s["fixed"], **{k: v for k, v in config.items() if k != "seed"}}.items():
        cmd += ["--set", f"{k}={toml_value(v)}"]
    cmd += ["--seeds", str(config["seed"]), "--out", out]
    return cmd


def experiment_command(s: dict, config: dict, out: str) -> list[str]:
    cmd = [lmac_binary(s), "experiment"]
    for k, v in s["flags"].items():
        if k in ("algo", "protocol", "config"):
            raise RuntimeError(f"[sweep] {k} is a `lmac train` flag; an experiment takes [experiment] algos = ...")
        cmd += [f"--{k}", v]
    for k, v in s["experiment"].items():
        flag = "--" + k.replace("_", "-")
        if v is True:
            cmd.append(flag)
        elif v is False:
            continue
        elif isinstance(v, list) and k != "variant":
            cmd += [flag, ",".join(str(x) for x in v)]
        elif isinstance(v, list):
            for x in v:
                cmd += [flag, str(x)]
        else:
            cmd += [flag, str(v)]
    for k, v in {**s["fixed"], **config}.items():
        cmd += ["--set", f"{k}={toml_value(v)}"]
    cmd += ["--seeds", ",".join(str(x) for x in s["seeds"]), "--out", out]
    return cmd


# ----------------------------------------------------------------------------------------------
# One trial (runs in a Ray worker)


try:
    _PRCTL = ctypes.CDLL(None, use_errno=True).prctl  # looked up before any fork
except (OSError, AttributeError):
    _PRCTL = None


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the Ray worker dies (lmac then checkpoints and stops
    its own children)."""
    if _PRCTL is not None:
        _PRCTL(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG


class _Tail:
    """Complete lines appended to a file since the last read (reopened each time: lmac rewrites
    metrics.jsonl when it resumes)."""

    def __init__(self, path: pathlib.Path, offset: int = 0):
        self.path, self.offset = path, offset

    def lines(self) -> list[str]:
        try:
            with open(self.path, "rb") as f:
                f.seek(self.offset)
                data = f.read()
        except FileNotFoundError:
            return []
        end = data.rfind(b"\n")
        if end < 0:
            return []
        self.offset += end + 1
        return [l for l in data[: end + 1].decode("utf-8", "replace").splitlines() if l.strip()]


def _ck_counters(ck: pathlib.Path) -> dict:
    return json.loads((ck / "state.json").read_text())["counters"]


def _snapshot(run_dir: pathlib.Path, line: dict, rows: list[str], dest: pathlib.Path) -> bool:
    """Copy the run's checkpoint (the one `line` announces), its config and the metrics rows it
    keeps into `dest/run`. False when lmac has already replaced that checkpoint with a newer one
    (the newer one's own line follows)."""
    src = run_dir / "checkpoint"
    try:
        before = {p.name: (p.stat().st_mtime_ns, p.stat().st_size) for p in src.iterdir()}
        shutil.copytree(src, dest / "run" / "checkpoint")
        after = {p.name: (p.stat().st_mtime_ns, p.stat().st_size) for p in src.iterdir()}
        c = _ck_counters(dest / "run" / "checkpoint")
    except (OSError, KeyError, ValueError):
        shutil.rmtree(dest / "run", ignore_errors=True)
        return False
    if before != after or c["t_env"] != line["t_env"] or c["updates"] != line.get("updates", c["updates"]):
        shutil.rmtree(dest / "run", ignore_errors=True)
        return False
    shutil.copy2(run_dir / "config.toml", dest / "run" / "config.toml")
    if (run_dir / "metrics.csv").exists():
        shutil.copy2(run_dir / "metrics.csv", dest / "run" / "metrics.csv")  # lmac trims it on resume
    t = line["t_env"]
    kept = [r for r in rows if json.loads(r).get("t_env", 0) <= t]  # exactly what a resume keeps
    (dest / "run" / "metrics.jsonl").write_text("".join(r + "\n" for r in kept))
    (dest / "lmac_sweep.json").write_text(json.dumps({"t_env": t, "updates": c["updates"], "run_dir": str(run_dir)}))
    return True


def _numeric(row: dict) -> dict:
    return {k: v for k, v in row.items() if isinstance(v, (int, float)) and not isinstance(v, bool) and v is not None}


def _runs_root(s: dict) -> pathlib.Path:
    from ray import tune

    ctx = tune.get_context()
    if s["runs_dir"]:
        return pathlib.Path(s["runs_dir"]) / ctx.get_trial_id()
    return pathlib.Path(ctx.get_trial_dir()) / "lmac-runs"


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)  # lmac writes a last checkpoint and stops its children
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _failed(cmd: list[str], rc: int, log: pathlib.Path) -> RuntimeError:
    try:
        tail = log.read_text(errors="replace").splitlines()[-15:]
    except OSError:
        tail = []
    return RuntimeError(f"{' '.join(cmd[:2])} exited with {rc} (log {log}):\n" + "\n".join(tail))


def run_trial(config: dict, sweep: dict) -> None:
    """The Tune trainable: one `lmac train` run (or one `lmac experiment`)."""
    if sweep["mode"] == "experiment":
        return _run_experiment(config, sweep)
    from ray import tune

    root = _runs_root(sweep)
    root.mkdir(parents=True, exist_ok=True)
    attempt = 1 + sum(1 for p in root.iterdir() if p.name.startswith("attempt"))
    work = root / f"attempt{attempt}"
    work.mkdir()
    ckpt = tune.get_checkpoint()
    resumed_from = None
    if ckpt is not None:
        # Tune's checkpoint is the trial's state: restore it into a fresh run directory.
        run_dir = work / "run"
        with ckpt.as_directory() as d:
            shutil.copytree(pathlib.Path(d) / "run", run_dir)
        resumed_from = _ck_counters(run_dir / "checkpoint")["t_env"]
        rows = (run_dir / "metrics.jsonl").read_text().splitlines()
        tail = _Tail(run_dir / "metrics.jsonl", (run_dir / "metrics.jsonl").stat().st_size)
        cmd = [lmac_binary(sweep), "train", "--resume", str(run_dir)]
    else:
        run_dir, tail, rows = None, None, []
        cmd = train_command(sweep, config, str(work))
    (work / "command.json").write_text(json.dumps(cmd))
    log = work / "lmac.log"
    latest: dict = {"lmac_attempt": attempt}
    if resumed_from is not None:
        latest["resumed_from_t_env"] = resumed_from
    with open(log, "ab") as logf:
        proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                cwd=str(work), preexec_fn=_die_with_parent)
    try:
        while True:
            rc = proc.poll()
            if run_dir is None:
                found = sorted(work.glob("*/*/*/seed*/config.toml"))
                if found:
                    run_dir = found[0].parent
                    tail = _Tail(run_dir / "metrics.jsonl")
            for text in tail.lines() if tail else []:
                try:
                    row = json.loads(text)
                except ValueError:
                    continue
                rows.append(text)
                if "checkpoint" in row:
                    with tempfile.TemporaryDirectory(prefix="lmac-ck-") as d:
                        if _snapshot(run_dir, row, rows, pathlib.Path(d)):
                            latest.update(t_env=row["t_env"], checkpoint_t_env=row["t_env"])
                            tune.report(dict(latest), checkpoint=tune.Checkpoint.from_directory(d))
                else:
                    latest.update(_numeric(row))
                    tune.report(dict(latest))
            if rc is not None:
                break
            time.sleep(0.5)
    finally:
        _stop(proc)
    if proc.returncode != 0:
        raise _failed(cmd, proc.returncode, log)
    # Finished (not stopped early by a signal): the checkpoint holds every step of the run.
    if run_dir is not None and (run_dir / "checkpoint" / "state.json").exists():
        steps = tomllib.loads((run_dir / "config.toml").read_text())["run"]["steps"]
        if _ck_counters(run_dir / "checkpoint")["t_env"] >= steps:
            tune.report({**latest, "lmac_finished": 1})


def _run_experiment(config: dict, sweep: dict) -> None:
    """`lmac experiment` in a stable directory: a restarted trial reruns the same command, which
    continues where it stopped (the design is reused, finished seeds skipped, the rest resumed)."""
    from ray import tune

    out = _runs_root(sweep) / "experiment"
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = experiment_command(sweep, config, str(out))
    log = out.parent / "lmac.log"
    with open(log, "ab") as logf:
        proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                cwd=str(out.parent), preexec_fn=_die_with_parent)
    try:
        proc.wait()
    finally:
        _stop(proc)
    if proc.returncode != 0:
        raise _failed(cmd, proc.returncode, log)
    comp = json.loads((out / "comparison.json").read_text())
    metrics = {"steps": comp.get("steps", 0), "lmac_finished": 1}
    for row in comp.get("rows", []):
        for k, v in _numeric(row).items():
            metrics[f"{row['label']}/{k}"] = v
    tune.report(metrics)


# ----------------------------------------------------------------------------------------------
# The driver


def _start_ray(address: str | None, s: dict) -> None:
    import ray

    try:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            kw = {"include_dashboard": False, "log_to_driver": False}
            if s["num_cpus"]:
                kw["num_cpus"] = int(s["num_cpus"])
            ray.init(**kw)
    except Exception as e:  # noqa: BLE001 - Ray raises many kinds; all mean the same here
        where = f"the Ray cluster at {address}" if address else "a local Ray"
        raise SweepError(f"could not start or reach {where}: {type(e).__name__}: {e}") from None


def _summary(results, s: dict, exp_path: str) -> dict:
    trials = []
    for r in results:
        m = r.metrics or {}
        trials.append({
            "trial_id": m.get("trial_id") or "_".join(pathlib.Path(r.path).name.split("_")[2:4]),
            "config": r.config,
            # Tune calls a trial stopped by Ctrl-C "terminated" too: lmac_finished tells them apart.
            "status": "ERROR" if r.error else ("TERMINATED" if m.get("lmac_finished") else "UNFINISHED"),
            "error": str(r.error).splitlines()[0] if r.error else None,
            "t_env": m.get("t_env"),
            "checkpoint_t_env": m.get("checkpoint_t_env"),
            "lmac_attempt": m.get("lmac_attempt"),
            "resumed_from_t_env": m.get("resumed_from_t_env"),
            s["metric"]: m.get(s["metric"]),
            "checkpoint": r.checkpoint.path if r.checkpoint else None,
            "trial_dir": r.path,
            "runs": str(pathlib.Path(s["runs_dir"]) / "_".join(pathlib.Path(r.path).name.split("_")[2:4])) if s["runs_dir"] else None,
        })
    return {"name": s["name"], "mode": s["mode"], "experiment": exp_path, "metric": s["metric"], "trials": trials}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="lmac-sweep", description="Sweeps of lmac train (or lmac experiment) as Ray Tune trials.")
    ap.add_argument("--config", required=True, help="the sweep file (TOML)")
    ap.add_argument("--resume", action="store_true", help="continue the interrupted sweep of this file (Tuner.restore)")
    ap.add_argument("--address", help="an existing Ray cluster (e.g. auto or HOST:6379); default: start a local Ray")
    ap.add_argument("--dry-run", action="store_true", help="print the search space and the first trial's command, run nothing")
    a = ap.parse_args(argv)
    try:
        return _main(a)
    except SweepError as e:
        print(f"lmac-sweep: {e}", file=sys.stderr)
        return 2


def _main(a) -> int:
    s = load_sweep(a.config)
    if a.dry_run:
        print(json.dumps({k: s[k] for k in ("name", "mode", "search", "seeds", "fixed", "space", "storage", "runs_dir")}, indent=2, default=str))
        first = {k: (v[0] if isinstance(v, list) else v) for k, v in s["space"].items()}
        if s["mode"] == "train":
            print(" ".join(train_command(s, {**first, "seed": s["seeds"][0]}, "<runs>/<trial>/attempt1")))
        else:
            print(" ".join(experiment_command(s, first, "<runs>/<trial>/experiment")))
        return 0
    from ray import tune
    from ray.tune.search.basic_variant import BasicVariantGenerator

    exp_path = s["storage"].rstrip("/") + "/" + s["name"]
    if a.resume:
        if not tune.Tuner.can_restore(exp_path):
            raise SweepError(f"--resume: no sweep to continue at {exp_path}")
    elif "://" not in exp_path and (pathlib.Path(exp_path) / "tuner.pkl").exists():
        raise SweepError(f"{exp_path} already holds a sweep named {s['name']!r}: continue it with --resume, or change [sweep] name")
    _start_ray(a.address, s)
    trainable = tune.with_resources(tune.with_parameters(run_trial, sweep=s), {"cpu": s["cpus_per_trial"]})
    if a.resume:
        tuner = tune.Tuner.restore(exp_path, trainable, resume_unfinished=True, resume_errored=True)
    else:
        tuner = tune.Tuner(
            trainable,
            param_space=param_space(s),
            tune_config=tune.TuneConfig(
                num_samples=s["num_samples"],
                max_concurrent_trials=s["max_concurrent_trials"] or None,
                search_alg=BasicVariantGenerator(random_state=s["random_seed"]),
            ),
            run_config=tune.RunConfig(
                name=s["name"],
                storage_path=s["storage"],
                failure_config=tune.FailureConfig(max_failures=s["max_failures"]),
                checkpoint_config=tune.CheckpointConfig(num_to_keep=s["keep_checkpoints"]),
                verbose=1,
            ),
        )
    results = tuner.fit()
    summary = _summary(results, s, exp_path)
    text = json.dumps(summary, indent=2, default=str)
    if "://" not in exp_path:
        (pathlib.Path(exp_path) / "lmac_sweep.json").write_text(text + "\n")
    print(f"lmac-sweep: {len(summary['trials'])} trial(s) in {exp_path}")
    for t in summary["trials"]:
        cfg = " ".join(f"{k}={v}" for k, v in sorted(t["config"].items()))
        print(f"  {t['status']:<10} {cfg}  t_env={t['t_env']}  {s['metric']}={t[s['metric']]}"
              + (f"  ({t['error']})" if t["error"] else ""))
    errors = sum(1 for t in summary["trials"] if t["status"] == "ERROR")
    unfinished = sum(1 for t in summary["trials"] if t["status"] not in ("ERROR", "TERMINATED"))
    if errors or unfinished:
        print(f"lmac-sweep: {errors} trial(s) failed, {unfinished} unfinished; continue with: "
              f"lmac-sweep --config {a.config} --resume" + (f" --address {a.address}" if a.address else ""), file=sys.stderr)
    return 1 if errors else (130 if unfinished else 0)
