"""`python -m lmac_report RUNS... [--out DIR]` (`lmac report`): the table and plots of rliable."""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from pathlib import Path

import numpy as np

from . import stats
from .runs import FINAL_TESTS, ReportError, Run, load_all, merged
from .titles import fit

DESCRIPTION = """\
Merge training runs and report the final performance as the field does (rliable, Agarwal et
al. 2021): IQM, median and mean with 95% stratified-bootstrap confidence intervals, a
performance profile and sample-efficiency curves (IQM over env steps with 95% CIs; a label with
fewer than 5 runs gets its mean ± sample SD in the table and the curves instead).

RUNS are seed directories (config.toml + metrics.csv or marl_eval.json), any directory above
them (a `lmac train` group, an `lmac experiment`, a folder of both), flat copies
(<label>_seed<k>.csv with <label>_seed<k>.config.toml, as in docs/figures) or marl-eval JSON
files (e.g. an earlier report.json). LABEL=PATH gives every run under PATH the label LABEL.

One row per (env, label): the label is the experiment's run folder (<exp>/runs/<label>/seed<k>),
else the flat copy's <label>, else run.algo. A label with runs on several envs gets one more
row, "all (N envs)", over those envs, each env a stratum of the bootstrap.

A run's final score is the mean of marl_eval.json's absolute_metrics (a greedy evaluation of the
best checkpoint) when present, else the mean of its last 5 test phases; the table says which.
rliable's median and mean are over per-env means (with one env both are that env's mean); the
IQM pools every run of every env."""

EPILOG = """\
Writes to --out (default: report/ inside the first RUNS directory, or beside it when it is a
seed directory or a file):
  report.md, report.csv     the table (report.md is also printed)
  report_stats.json         the table, every run's final score and the settings
  report.json               every run's marl-eval data merged (family -> task -> label -> seed)
  performance_profile.png   fraction of runs scoring above each threshold, 95% CIs
  sample_efficiency.png     IQM of the test score over env steps, 95% CIs (mean ± sample SD
                            for a label of fewer than 5 runs)

Scores are used as they are. IQM across envs with different return scales (SMAC-like tasks)
needs normalised scores: --normalise min-max maps each env's scores through the lowest and
highest test score any of its runs recorded.

Examples:
  lmac report runs/lbf_8x8-2p-2f-s1-coop/qmix/20261122-024003
  lmac report /work/exp/lbf_comm --out lbf_report
  lmac report qmix=runs/a/qmix/t1 lr1e-3=runs/a/qmix/t2 --reps 10000"""


def parse_args(argv):
    p = argparse.ArgumentParser(
        prog=os.environ.get("LMAC_REPORT_PROG", "python -m lmac_report"),
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("runs", nargs="+", metavar="RUNS", help="run directories, flat copies or marl-eval JSON files; LABEL=PATH sets the label")
    p.add_argument("--out", type=Path, help="output directory (see below)")
    p.add_argument("--reps", type=int, default=50_000, help="bootstrap replicates for the table (default: 50000, rliable's)")
    p.add_argument("--curve-reps", type=int, default=2_000, help="bootstrap replicates per point of the profile and curves (default: 2000)")
    p.add_argument("--seed", type=int, default=0, help="bootstrap seed (default: 0); a group's intervals do not depend on the other groups")
    p.add_argument("--metric", default="return", choices=["return", "win_rate"], help="the score (default: return)")
    p.add_argument("--normalise", "--normalize", default="none", choices=["none", "min-max"],
                   help="per-env score normalisation (default: none)")
    p.add_argument("--points", type=int, default=100, help="env-step points of the sample-efficiency curves (default: 100)")
    p.add_argument("--skip-bad", action="store_true", help="skip runs that cannot be read (with a warning) instead of failing")
    p.add_argument("--no-plots", action="store_true", help="write the table and JSON only")
    a = p.parse_args(argv)
    for name in ("reps", "curve_reps", "points"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be at least 1")
    return a


def default_out(first: str) -> Path:
    path = Path(first)
    if not path.exists() and "=" in first:
        path = Path(first.partition("=")[2])
    if path.is_dir() and not (path / "config.toml").is_file() and not (path / "marl_eval.json").is_file():
        return path / "report"
    return path.parent / "report"


def fmt(v: float) -> str:
    return f"{v:.3f}"


def fmt_steps(t: float) -> str:
    return f"{t / 1e6:.2f}M" if t >= 1e6 else f"{t / 1e3:.0f}k" if t >= 1e3 else f"{t:.0f}"


class Report:
    def __init__(self, runs: list[Run], a):
        self.runs, self.a = runs, a
        self.envs = sorted({r.env for r in runs})
        self.labels = sorted({r.label for r in runs})
        self.final = {}  # id(run) -> (score, source)
        for r in runs:
            self.final[id(r)] = r.final(a.metric)
        self.bounds = {}  # env -> (lo, hi) of min-max normalisation
        if a.normalise == "min-max":
            for env in self.envs:
                vals = []
                for r in runs:
                    if r.env == env:
                        vals += r.curve(a.metric)[1] + [self.final[id(r)][0]]
                        vals += r.data.get("absolute_metrics", {}).get(a.metric, [])
                self.bounds[env] = (min(vals), max(vals))

    def score(self, r: Run) -> float:
        s = self.final[id(r)][0]
        return float(stats.normalise_min_max(s, *self.bounds[r.env])) if self.bounds else s

    def tasks(self, label: str, envs: list[str]) -> tuple[list[str], list[list[Run]]]:
        names, groups = [], []
        for env in envs:
            g = sorted((r for r in self.runs if r.label == label and r.env == env), key=lambda r: r.seed)
            if g:
                names.append(env)
                groups.append(g)
        return names, groups

    def row(self, label: str, envs: list[str], env_name: str) -> dict | None:
        names, groups = self.tasks(label, envs)
        if not groups:
            return None
        scores = [np.array([self.score(r) for r in g]) for g in groups]
        rng = stats.rng_for(self.a.seed, f"{env_name}\0{label}")
        row = {"env": env_name, "label": label, "tasks": len(groups), "runs": sum(len(g) for g in groups),
               "seeds": ",".join(r.seed.removeprefix("seed_") for g in groups for r in g),
               "steps": min(max(r.curve(self.a.metric)[0] or [0]) for g in groups for r in g)}
        row["unfinished"] = sum(r.unfinished() for g in groups for r in g)
        sources = {self.final[id(r)][1] for g in groups for r in g}
        row["final_score"] = ("best-checkpoint eval" if sources == {"absolute"} else
                              f"last-{FINAL_TESTS}-tests" if sources == {"last5"} else "mixed")
        for name, func in stats.AGGREGATES.items():
            point, lo, hi = stats.interval(scores, func, self.a.reps, rng)
            row[name], row[name + "_lo"], row[name + "_hi"] = float(point), float(lo), float(hi)
        row["scores"] = {f"{env}/{r.seed}": self.score(r) for env, g in zip(names, groups) for r in g}
        return row

    def rows(self) -> list[dict]:
        out = []
        for env in self.envs:
            out += [r for label in self.labels if (r := self.row(label, [env], env))]
        for label in self.labels if len(self.envs) > 1 else []:
            names, _ = self.tasks(label, self.envs)
            if len(names) > 1:  # a label on one env only has its env's row
                out.append(self.row(label, names, f"all ({len(names)} envs)" if len(names) == len(self.envs)
                                    else f"all ({len(names)} of {len(self.envs)} envs)"))
        return out

    # -- plots ----------------------------------------------------------------------------------

    def colour(self, i: int):
        if len(self.labels) <= 10:
            return f"C{i}"
        import matplotlib

        return matplotlib.colormaps["tab20"](i % 20)

    def profile(self, ax):
        all_scores = [self.score(r) for r in self.runs]
        lo, hi = min(all_scores), max(all_scores)
        pad = 0.05 * (hi - lo) if hi > lo else 0.5
        taus = np.linspace(lo - pad, hi + pad, 201)
        for i, label in enumerate(self.labels):
            _, groups = self.tasks(label, self.envs)
            scores = [np.array([self.score(r) for r in g]) for g in groups]
            p, plo, phi = stats.interval(scores, stats.profile(taus), self.a.curve_reps, stats.rng_for(self.a.seed, "profile\0" + label))
            n = sum(len(g) for g in groups)
            line, = ax.plot(taus, p, label=f"{label} ({n} runs)", color=self.colour(i))
            ax.fill_between(taus, plo, phi, color=line.get_color(), alpha=0.2, linewidth=0)
        ax.set_xlabel(("normalised " if self.bounds else "") + f"final {self.a.metric} (tau)")
        ax.set_ylabel(f"fraction of runs with score > tau")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)

    def curves(self, ax):
        for i, label in enumerate(self.labels):
            _, groups = self.tasks(label, self.envs)
            groups = [[r for r in g if r.curve(self.a.metric)[0]] for g in groups]  # not absolute_metrics alone
            groups = [g for g in groups if g]
            if not groups:
                continue
            runs = [r for g in groups for r in g]
            curves = [r.curve(self.a.metric) for r in runs]
            curves = [(np.array(x, dtype=float), np.array(y, dtype=float)) for x, y in curves]
            end = min(x[-1] for x, _ in curves)
            grid = np.linspace(0, end, self.a.points)
            per_run = {}
            for r, (x, y) in zip(runs, curves):
                y = stats.normalise_min_max(y, *self.bounds[r.env]) if self.bounds else y
                per_run[id(r)] = np.interp(grid, x, y)
            if len(runs) < stats.FEW_RUNS:
                # Too few runs for an IQM and a bootstrap CI: the mean and a sample-SD band.
                ys = np.stack([per_run[id(r)] for r in runs])
                mid, sd = ys.mean(0), stats.sample_sd(ys)
                lo, hi, what = mid - sd, mid + sd, "mean ± sample SD"
            else:
                rng = stats.rng_for(self.a.seed, "curve\0" + label)
                mid, lo, hi = [], [], []
                for k in range(len(grid)):
                    tasks = [np.array([per_run[id(r)][k] for r in g]) for g in groups]
                    p, l, h = stats.interval(tasks, stats.iqm, self.a.curve_reps, rng)
                    mid.append(p), lo.append(l), hi.append(h)
                what = "IQM, 95% CI"
            line, = ax.plot(grid, mid, label=f"{label} ({len(runs)} runs, {what})", color=self.colour(i))
            ax.fill_between(grid, lo, hi, color=line.get_color(), alpha=0.2, linewidth=0)
        ax.set_xlabel("env steps")
        ax.set_ylabel(f"test {self.a.metric}" + (" (normalised)" if self.bounds else ""))
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)

    def plots(self, out: Path) -> list[Path]:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        title = self.envs[0] if len(self.envs) == 1 else f"{len(self.envs)} envs"
        written = []
        for name, draw, what in (("performance_profile.png", self.profile, "performance profile"),
                                 ("sample_efficiency.png", self.curves, "sample efficiency")):
            fig, ax = plt.subplots(figsize=(8.4, 4.4))
            draw(ax)
            bands = "95% stratified-bootstrap CIs" if draw == self.profile else \
                f"IQM with 95% stratified-bootstrap CIs; mean ± sample SD below {stats.FEW_RUNS} runs"
            ax.set_title(fit(f"{title}: {what} ({bands})", 70), fontsize=10)
            fig.tight_layout()
            fig.savefig(out / name, dpi=120, bbox_inches="tight")
            plt.close(fig)
            written.append(out / name)
        return written


COLUMNS = ["env", "label", "tasks", "runs", "seeds", "steps", "unfinished", "final_score",
           "iqm", "iqm_lo", "iqm_hi", "median", "median_lo", "median_hi", "mean", "mean_lo", "mean_hi"]


def markdown(rows: list[dict], a, n_envs: int) -> str:
    ci = lambda r, k: f"{fmt(r[k])} [{fmt(r[k + '_lo'])}, {fmt(r[k + '_hi'])}]"
    what = ("min-max normalised " if a.normalise == "min-max" else "") + f"final {a.metric}"
    lines = [f"{what}: IQM, median and mean with 95% stratified-bootstrap CIs ({a.reps} replicates, seed {a.seed}); "
             f"rows of fewer than {stats.FEW_RUNS} runs: mean ± sample SD and every run's score", "",
             "| env | label | runs | steps | scored by | IQM [95% CI] | median [95% CI] | mean [95% CI] or ± sample SD |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        steps = fmt_steps(r["steps"]) + ("*" if r["unfinished"] else "")
        if r["runs"] < stats.FEW_RUNS:
            scores = list(r["scores"].values())
            each = ", ".join(fmt(s) for s in scores)
            cells = f"- | - | {fmt(float(np.mean(scores)))} ± {fmt(float(stats.sample_sd(np.array(scores))))} (runs: {each})"
        else:
            cells = f"{ci(r, 'iqm')} | {ci(r, 'median')} | {ci(r, 'mean')}"
        lines.append(f"| {r['env']} | {r['label']} | {r['runs']} | {steps} | {r['final_score']} | {cells} |")
    lines += ["", f"scored by: best-checkpoint eval = the mean return of marl_eval.json's absolute_metrics, the greedy "
                  f"evaluation of the run's best checkpoint (`lmac experiment`'s best-checkpoint eval column); "
                  f"last-{FINAL_TESTS}-tests = the mean of the run's last {FINAL_TESTS} test phases (`lmac experiment`'s "
                  f"last-{FINAL_TESTS}-tests column). "
                  "median and mean are over per-env means (rliable); the IQM pools all runs."]
    unfinished = [f"{r['label']} ({r['unfinished']} of {r['runs']})" for r in rows if r["unfinished"] and not r["env"].startswith("all (")]
    if unfinished:
        lines.append("steps: the last test phase of the shortest run; * some runs have not reached their run.steps yet: "
                     + ", ".join(unfinished) + ".")
    if n_envs > 1 and a.normalise == "none":
        lines.append("note: the 'all' rows mix envs whose returns may have different scales; "
                     "IQM across such tasks needs normalised scores (--normalise min-max).")
    if a.normalise == "min-max":
        lines.append("normalised: (score - lowest) / (highest - lowest) over every test score of the env's runs.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    a = parse_args(sys.argv[1:] if argv is None else argv)
    warn = lambda m: print(f"lmac report: {m}", file=sys.stderr)
    try:
        runs = load_all(a.runs, a.skip_bad, warn)
        for r in runs:
            for n in r.notes:
                warn(n)
        report = Report(runs, a)
        rows = report.rows()
        out = a.out or default_out(a.runs[0])
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ReportError(f"{out}: cannot create the output directory ({e.strerror})") from None
        md = markdown(rows, a, len(report.envs))
        print(md, end="")
        (out / "report.md").write_text(md)
        with open(out / "report.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)
        settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
        stats_json = {"settings": settings, "bounds": {e: list(b) for e, b in report.bounds.items()}, "rows": rows,
                      "runs": [{"env": r.env, "label": r.label, "seed": r.seed, "source": r.source,
                                "final": report.final[id(r)][0], "final_source": report.final[id(r)][1]} for r in runs]}
        (out / "report_stats.json").write_text(json.dumps(stats_json, indent=1) + "\n")
        (out / "report.json").write_text(json.dumps(merged(runs), indent=1) + "\n")
        written = ["report.md", "report.csv", "report_stats.json", "report.json"]
        if not a.no_plots:
            written += [p.name for p in report.plots(out)]
        print(f"\nwrote {out}/{{{','.join(written)}}} ({len(runs)} runs)")
        return 0
    except ReportError as e:
        print(f"lmac report: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"lmac report: error: {e.filename or ''}: {e.strerror}", file=sys.stderr)
        return 2
