"""Finding and reading training runs as marl-eval data.

A run (one seed) is found as:
- a seed directory: `config.toml` with `metrics.csv` (or `metrics.jsonl`) and/or `marl_eval.json`
  (`lmac train`: runs/<env>/<algo>/<time>/seed<k>/; `lmac experiment`: <exp>/runs/<label>/seed<k>/);
- a flat copy: `<label>_seed<k>.csv` with `<label>_seed<k>.config.toml` beside it (as in docs/figures);
- an entry of a marl-eval JSON file given directly (e.g. an earlier report.json).
A directory argument is searched recursively for seed directories and flat copies.

Each run becomes marl-eval's per-seed structure, `{"step_<i>": {"step_count": t_env, "return":
[mean test return], "win_rate": [rate]}, ..., "absolute_metrics": {...}}`: read from the seed's
`marl_eval.json` when it has one, else built from the test rows of its metrics (rows with a
`test_return_mean`), without absolute_metrics.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

from .final import FINAL_TEST_PHASES as FINAL_TESTS, final_of  # noqa: E402  (the one rule)
# What runs written before 2026-12-04 kept inside absolute_metrics besides the metrics: which
# checkpoint the final evaluation used and its step (now in absolute_metrics_source).
OLD_ANNOTATIONS = ("checkpoint", "t_env")
FLAT = re.compile(r"^(?P<label>.+)_seed(?P<seed>\d+)\.csv$")
STEP = re.compile(r"^step_(\d+)$")


class ReportError(Exception):
    """An expected problem with the input (a message for the user, no traceback)."""


@dataclass
class Run:
    env: str  # "lbf:8x8-2p-2f-s1-coop"
    label: str  # the row it belongs to: the experiment's folder name, else run.algo
    seed: str  # marl-eval key, "seed_<k>"
    data: dict  # marl-eval per-seed data
    source: str  # where it was read (for messages)
    notes: list = field(default_factory=list)
    budget: int | None = None  # run.steps of its config, when known

    @property
    def family(self) -> str:
        return split_env(self.env)[0]

    @property
    def task(self) -> str:
        return split_env(self.env)[1]

    def curve(self, metric: str) -> tuple[list, list]:
        """(env steps, metric) of its test phases, in order."""
        steps = sorted((int(STEP.match(k).group(1)), v) for k, v in self.data.items() if STEP.match(k))
        xs, ys = [], []
        for _, v in steps:
            if metric in v:
                xs.append(v["step_count"])
                ys.append(sum(v[metric]) / len(v[metric]))
        return xs, ys

    def final(self, metric: str) -> tuple[float, str]:
        """The run's final score and where it comes from: "absolute" (absolute_metrics: the best
        checkpoint's final evaluation) or "last5" (the mean of its last 5 test phases)."""
        absolute = self.data.get("absolute_metrics", {}).get(metric)
        if absolute:
            return sum(absolute) / len(absolute), "absolute"
        _, ys = self.curve(metric)
        if not ys:
            raise ReportError(f"{self.source}: no {metric!r} in any test phase or absolute_metrics")
        return final_of(ys), "last5"

    def unfinished(self) -> bool:
        """Its last test phase is more than 2% short of its config's run.steps."""
        xs, _ = self.curve("return")
        return self.budget is not None and "absolute_metrics" not in self.data and (not xs or xs[-1] < 0.98 * self.budget)


def split_env(env: str) -> tuple[str, str]:
    """marl-eval's environment family and task: the env name split at its first ':'."""
    family, sep, task = env.partition(":")
    return (family, task) if sep else (env, env)


def _number(v, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ReportError(f"{where}: expected a finite number, found {v!r}")
    return v


def check_seed_data(data, where: str) -> dict:
    """Validate one seed's marl-eval data (`where` names the file and key path)."""
    if not isinstance(data, dict):
        raise ReportError(f"{where}: expected an object of step_<i> entries, found {type(data).__name__}")
    steps = 0
    for key, v in data.items():
        if STEP.match(key):
            steps += 1
            if not isinstance(v, dict):
                raise ReportError(f"{where}/{key}: expected an object, found {type(v).__name__}")
            if "step_count" not in v:
                raise ReportError(f"{where}/{key}: no step_count")
            _number(v["step_count"], f"{where}/{key}/step_count")
            metrics = v
        elif key == "absolute_metrics":
            if not isinstance(v, dict):
                raise ReportError(f"{where}/{key}: expected an object, found {type(v).__name__}")
            metrics = v
        else:
            continue  # marl-eval tolerates other keys; so do we
        for name, values in metrics.items():
            if name == "step_count":
                continue
            if key == "absolute_metrics" and name in OLD_ANNOTATIONS:
                continue
            if not isinstance(values, list) or not values:
                raise ReportError(f"{where}/{key}/{name}: expected a non-empty list of numbers, found {values!r}")
            for i, x in enumerate(values):
                _number(x, f"{where}/{key}/{name}[{i}]")
    if steps == 0 and "absolute_metrics" not in data:
        raise ReportError(f"{where}: no step_<i> entries and no absolute_metrics")
    return data


def _read_text(path: Path) -> str:
    """A file's text; an unreadable file is a ReportError naming it."""
    try:
        return path.read_text()
    except OSError as e:
        raise ReportError(f"{path}: cannot be read ({e.strerror})") from None


def read_marl_eval(path: Path) -> list[tuple[str, str, str, dict]]:
    """Every (env, algo, seed key, seed data) of a marl-eval JSON file."""
    try:
        raw = json.loads(_read_text(path))
    except json.JSONDecodeError as e:
        raise ReportError(f"{path}: not valid JSON ({e})") from None
    out = []
    levels = ("environment family", "task", "algorithm", "seed")

    def obj(v, where, level):
        if not isinstance(v, dict) or not v:
            raise ReportError(f"{path}: {where or 'the top level'}: expected a non-empty object keyed by {levels[level]}")
        return v

    for family, tasks in obj(raw, "", 0).items():
        for task, algos in obj(tasks, family, 1).items():
            for algo, seeds in obj(algos, f"{family}/{task}", 2).items():
                for seed, data in obj(seeds, f"{family}/{task}/{algo}", 3).items():
                    where = f"{path}: {family}/{task}/{algo}/{seed}"
                    env = family if task == family else f"{family}:{task}"
                    out.append((env, algo, seed, check_seed_data(data, where)))
    return out


def read_config(path: Path) -> tuple[str, str, int, int | None]:
    """(run.env, run.algo, learn.seed, run.steps or None) of a run's config.toml."""
    try:
        cfg = tomllib.loads(_read_text(path))
    except tomllib.TOMLDecodeError as e:
        raise ReportError(f"{path}: not valid TOML ({e})") from None
    try:
        env, algo, seed = cfg["run"]["env"], cfg["run"]["algo"], cfg["learn"]["seed"]
    except (KeyError, TypeError) as e:
        raise ReportError(f"{path}: missing {e} (a run's config needs run.env, run.algo and learn.seed)") from None
    if not isinstance(env, str) or not isinstance(algo, str) or not isinstance(seed, int):
        raise ReportError(f"{path}: run.env and run.algo must be strings and learn.seed an integer")
    steps = cfg["run"].get("steps")
    return env, algo, seed, steps if isinstance(steps, int) and not isinstance(steps, bool) else None


def _float(s: str, where: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise ReportError(f"{where}: {s!r} is not a number") from None
    if not math.isfinite(v):
        raise ReportError(f"{where}: {s!r} is not a finite number")
    return v


def _steps_from_rows(rows: list[tuple[float, float, float | None]], path: Path) -> dict:
    if not rows:
        raise ReportError(f"{path}: no test rows (no row has a test_return_mean): the run has not finished a test phase")
    data = {}
    for i, (t, ret, win) in enumerate(rows):
        step = {"step_count": int(t), "return": [ret]}
        if win is not None:
            step["win_rate"] = [win]
        data[f"step_{i}"] = step
    return data


def read_metrics_csv(path: Path) -> dict:
    """marl-eval per-seed data from the test rows of metrics.csv (no absolute_metrics)."""
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            fields = reader.fieldnames or []
            for need in ("t_env", "test_return_mean"):
                if need not in fields:
                    raise ReportError(f"{path}: no {need} column (columns: {', '.join(fields) or 'none'})")
            rows = []
            for r in reader:
                ret = (r.get("test_return_mean") or "").strip()
                if not ret:
                    continue
                where = f"{path}:{reader.line_num}"
                win = (r.get("test_win_rate") or "").strip()
                rows.append((_float(r["t_env"] or "", where + " t_env"), _float(ret, where + " test_return_mean"),
                             _float(win, where + " test_win_rate") if win else None))
    except OSError as e:
        raise ReportError(f"{path}: cannot be read ({e.strerror})") from None
    except (UnicodeDecodeError, csv.Error) as e:
        raise ReportError(f"{path}: not a readable CSV file ({e})") from None
    return _steps_from_rows(rows, path)


def read_metrics_jsonl(path: Path) -> dict:
    """The same from metrics.jsonl (checkpoint lines and a line cut off at the end are skipped)."""
    rows = []
    lines = _read_text(path).splitlines()
    for n, line in enumerate(lines, 1):
        try:
            r = json.loads(line)
        except json.JSONDecodeError:
            if n == len(lines):
                continue  # a line cut off by a crash
            raise ReportError(f"{path}:{n}: not valid JSON") from None
        if isinstance(r, dict) and r.get("test_return_mean") is not None:
            where = f"{path}:{n}"
            win = r.get("test_win_rate")
            rows.append((_number(r.get("t_env"), where + " t_env"), _number(r["test_return_mean"], where + " test_return_mean"),
                         None if win is None else _number(win, where + " test_win_rate")))
    return _steps_from_rows(rows, path)


def is_seed_dir(d: Path) -> bool:
    if (d / "marl_eval.json").is_file():
        return True
    return (d / "config.toml").is_file() and ((d / "metrics.csv").is_file() or (d / "metrics.jsonl").is_file())


def seed_dir_label(d: Path, algo: str) -> str:
    """The experiment's run folder (<exp>/runs/<label>/seed<k>) when the seed is in one, else the algo."""
    return d.parent.name if d.parent.parent.name == "runs" else algo


def read_seed_dir(d: Path, label: str | None) -> list[Run]:
    cfg = d / "config.toml"
    env = algo = seed = budget = None
    if cfg.is_file():
        env, algo, seed, budget = read_config(cfg)
    me = d / "marl_eval.json"
    if me.is_file():
        entries = read_marl_eval(me)
        if len(entries) != 1:
            raise ReportError(f"{me}: a seed directory's marl_eval.json should hold one run, found {len(entries)}")
        j_env, j_algo, j_seed, data = entries[0]
        notes = []
        if env is not None and j_env != env:
            notes.append(f"{me} is for {j_env} but config.toml says {env}; using config.toml")
        return [Run(env or j_env, label or seed_dir_label(d, algo or j_algo), j_seed if seed is None else f"seed_{seed}",
                    data, str(me), notes, budget)]
    if (d / "metrics.csv").is_file():
        data = read_metrics_csv(d / "metrics.csv")
        src = d / "metrics.csv"
    else:
        data = read_metrics_jsonl(d / "metrics.jsonl")
        src = d / "metrics.jsonl"
    return [Run(env, label or seed_dir_label(d, algo), f"seed_{seed}", data, str(src), budget=budget)]


def read_flat(csv_path: Path, label: str | None) -> list[Run]:
    m = FLAT.match(csv_path.name)
    env, _algo, seed, budget = read_config(csv_path.with_name(csv_path.name[: -len(".csv")] + ".config.toml"))
    return [Run(env, label or m.group("label"), f"seed_{seed}", read_metrics_csv(csv_path), str(csv_path), budget=budget)]


def _flat_pairs(d: Path, files: list[str]) -> list[Path]:
    names = set(files)
    return [d / f for f in sorted(files) if FLAT.match(f) and f[: -len(".csv")] + ".config.toml" in names]


def load(arg: str, skip_bad: bool = False, warn=print) -> list[Run]:
    """Every run of one RUNS argument: `PATH` or `LABEL=PATH` (every run under PATH gets LABEL)."""
    label = None
    path = Path(arg)
    if not path.exists() and "=" in arg:
        label, _, rest = arg.partition("=")
        path = Path(rest)
        if not label:
            raise ReportError(f"{arg}: empty label before '='")
    if not path.exists():
        raise ReportError(f"{path}: no such file or directory")

    def attempt(fn, *a) -> list[Run]:
        try:
            return fn(*a)
        except ReportError as e:
            if not skip_bad:
                raise
            warn(f"skipped: {e}")
            return []

    if path.is_file():
        if path.suffix == ".json":
            return [Run(env, label or algo, seed, data, str(path)) for env, algo, seed, data in read_marl_eval(path)]
        if path.name in ("metrics.csv", "metrics.jsonl", "marl_eval.json", "config.toml"):
            return read_seed_dir(path.parent, label)
        if FLAT.match(path.name) and path.with_name(path.name[: -len(".csv")] + ".config.toml").is_file():
            return read_flat(path, label)
        raise ReportError(f"{path}: not a run (give a run directory, a <label>_seed<k>.csv with its .config.toml, or a marl-eval JSON file)")
    runs = []
    for root, dirs, files in os.walk(path):
        d = Path(root)
        dirs.sort()
        dirs[:] = [x for x in dirs if not x.startswith(".")]
        if is_seed_dir(d):
            dirs[:] = []  # a seed's checkpoint/ and the like hold no runs
            runs += attempt(read_seed_dir, d, label)
            continue
        if (d / "config.toml").is_file() and set(dirs) <= {"checkpoint"}:  # a seed that has not logged yet
            warn(f"skipped: {d}: a run with no metrics.csv yet")
            dirs[:] = []
            continue
        for f in _flat_pairs(d, files):
            runs += attempt(read_flat, f, label)
    if not runs and not skip_bad:
        raise ReportError(
            f"{path}: no runs found (a run is a directory with config.toml and metrics.csv or marl_eval.json, "
            "or a <label>_seed<k>.csv with <label>_seed<k>.config.toml)"
        )
    return runs


def load_all(args: list[str], skip_bad: bool = False, warn=print) -> list[Run]:
    """The runs of every argument; the same (env, label, seed) twice is an error naming both."""
    runs, seen = [], {}
    for a in args:
        for r in load(a, skip_bad, warn):
            key = (r.env, r.label, r.seed)
            if key in seen:
                raise ReportError(
                    f"two runs of {r.label} on {r.env} with {r.seed}: {seen[key]} and {r.source} "
                    "(give one of them another label: LABEL=PATH)"
                )
            seen[key] = r.source
            runs.append(r)
    if not runs:
        raise ReportError("no runs could be read")
    return runs


def merged(runs: list[Run]) -> dict:
    """marl-eval's structure for all runs: family -> task -> label -> seed -> data."""
    out: dict = {}
    for r in runs:
        out.setdefault(r.family, {}).setdefault(r.task, {}).setdefault(r.label, {})[r.seed] = r.data
    return out
