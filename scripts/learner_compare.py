"""Two or more groups of training runs of one environment side by side, on their test phases
alone: final test return and win rate (the mean of the last 5 test phases, lmac_report.final),
peak (the best 5 consecutive phases) and the best single phase's win rate, per seed and as the
mean with the sample SD over seeds (fewer than 5 seeds: no IQM, no CI), the difference of each
group's mean from the first group's with a Welch 95% interval, and the mean test win-rate curve.

A group is LABEL=GLOB, the GLOB matching run directories (each with a `metrics.csv` holding
`t_env`, `test_return_mean` and `test_win_rate`: lmac's runs and scripts/epymarl_qmix.py's) or
such CSV files themselves:

    .venv/bin/python scripts/learner_compare.py --out docs/figures/epymarl_qmix_1o10b/compare \\
        'epymarl-qmix=docs/figures/epymarl_qmix_1o10b/epymarl/seed_*' \\
        'lmac-qmix=docs/figures/epymarl_qmix_1o10b/lmac/seed*'

Writes OUT.json, OUT.md and OUT.png.
"""
from __future__ import annotations

import argparse
import csv
import glob
import json
import math
import pathlib
import statistics as st
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "env-server"))
from lmac_report.final import final_of, peak_of  # noqa: E402

# Two-sided 97.5% quantiles of Student's t for small degrees of freedom (Welch's interval).
T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306,
        9: 2.262, 10: 2.228, 12: 2.179, 15: 2.131, 20: 2.086, 30: 2.042}


def t975(df: float) -> float:
    keys = sorted(T975)
    for k in keys:
        if df <= k:
            return T975[k]
    return 1.96


def metrics_file(run: pathlib.Path) -> pathlib.Path:
    """A run directory's metrics.csv, or a metrics CSV itself (the flat `<label>_seed<k>.csv`
    copies under docs/figures)."""
    return run if run.suffix == ".csv" else run / "metrics.csv"


def tests_of(run: pathlib.Path):
    rows = [r for r in csv.DictReader(open(metrics_file(run))) if r.get("test_return_mean") not in (None, "")]
    if not rows:
        raise SystemExit(f"{metrics_file(run)} has no test phases")
    t = [int(float(r["t_env"])) for r in rows]
    ret = [float(r["test_return_mean"]) for r in rows]
    win = [float(r["test_win_rate"] or 0.0) for r in rows]
    return t, ret, win


def seed_figures(run: pathlib.Path) -> dict:
    t, ret, win = tests_of(run)
    return {"run": str(run), "last_t_env": t[-1], "tests": len(t),
            "final_return": final_of(ret), "final_win_rate": final_of(win),
            "peak_return": peak_of(ret), "peak_win_rate": peak_of(win),
            "best_phase_win_rate": max(win)}


def mean_sd(xs):
    return (st.mean(xs), st.stdev(xs) if len(xs) > 1 else 0.0)


def welch(a, b):
    """b's mean minus a's, with Welch's 95% interval (None when either has one value)."""
    d = st.mean(b) - st.mean(a)
    if len(a) < 2 or len(b) < 2:
        return {"difference": d, "ci95": None}
    va, vb = st.variance(a) / len(a), st.variance(b) / len(b)
    se = math.sqrt(va + vb)
    if se == 0:
        return {"difference": d, "ci95": [d, d]}
    df = (va + vb) ** 2 / (va ** 2 / (len(a) - 1) + vb ** 2 / (len(b) - 1))
    h = t975(df) * se
    return {"difference": d, "ci95": [d - h, d + h], "df": df}


METRICS = ["final_return", "final_win_rate", "peak_return", "peak_win_rate", "best_phase_win_rate"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("groups", nargs="+", metavar="LABEL=GLOB")
    p.add_argument("--out", required=True, type=pathlib.Path, help="path without extension")
    a = p.parse_args(argv)
    groups = {}
    for g in a.groups:
        label, sep, pattern = g.partition("=")
        if not sep:
            p.error(f"{g!r}: expected LABEL=GLOB")
        runs = sorted(pathlib.Path(x) for x in glob.glob(pattern) if metrics_file(pathlib.Path(x)).is_file())
        if not runs:
            p.error(f"{label}: no run directory with a metrics.csv matches {pattern!r}")
        groups[label] = [seed_figures(r) for r in runs]
    first = next(iter(groups))
    out = {"groups": {}, "differences_from": first}
    for label, seeds in groups.items():
        agg = {m: dict(zip(("mean", "sd"), mean_sd([s[m] for s in seeds]))) for m in METRICS}
        entry = {"seeds": seeds, "mean_sd": agg}
        if label != first:
            entry["difference"] = {m: welch([s[m] for s in groups[first]], [s[m] for s in seeds]) for m in METRICS}
        out["groups"][label] = entry
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".json").write_text(json.dumps(out, indent=2) + "\n")

    lines = ["| group | seeds | final test return | final win rate | peak win rate | best phase win rate |",
             "| --- | --- | --- | --- | --- | --- |"]
    for label, e in out["groups"].items():
        ms = e["mean_sd"]
        cell = lambda m, f="{:.3f}": f"{f.format(ms[m]['mean'])} ± {f.format(ms[m]['sd'])}"
        lines.append(f"| {label} | {len(e['seeds'])} | {cell('final_return', '{:.2f}')} | {cell('final_win_rate')} "
                     f"| {cell('peak_win_rate')} | {cell('best_phase_win_rate')} |")
    lines += ["", "Per seed (final return / final win rate / best phase win rate):", ""]
    for label, e in out["groups"].items():
        per = ", ".join(f"{s['final_return']:.2f} / {s['final_win_rate']:.3f} / {s['best_phase_win_rate']:.3f}" for s in e["seeds"])
        lines.append(f"- {label}: {per}")
    for label, e in out["groups"].items():
        if "difference" in e:
            lines.append("")
            for m in ("final_return", "final_win_rate", "best_phase_win_rate"):
                d = e["difference"][m]
                ci = d["ci95"]
                ci_text = f" [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else ""
                lines.append(f"- {label} minus {first}, {m.replace('_', ' ')}: {d['difference']:+.3f}{ci_text} (Welch 95%)")
    a.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))

    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return 0
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for label, e in out["groups"].items():
        curves = [tests_of(pathlib.Path(s["run"])) for s in e["seeds"]]
        n = min(len(c[0]) for c in curves)
        t = curves[0][0][:n]
        for k, (i, name) in enumerate([(1, "test return"), (2, "test win rate")]):
            ys = [[c[i][j] for c in curves] for j in range(n)]
            ax[k].plot(t, [st.mean(y) for y in ys], label=f"{label} ({len(curves)} seeds)")
            ax[k].fill_between(t, [min(y) for y in ys], [max(y) for y in ys], alpha=0.2)
            ax[k].set_xlabel("env steps")
            ax[k].set_ylabel(name + " (mean, band: min-max over seeds)")
    ax[0].legend()
    fig.tight_layout()
    fig.savefig(a.out.with_suffix(".png"), dpi=110)
    return 0


if __name__ == "__main__":
    sys.exit(main())
