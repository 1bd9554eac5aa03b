"""Plots of `lmac train` runs: per seed the test return and win rate against env steps, and for
a group of seeds the mean with a standard-deviation band plus a table of final figures.

    python -m lmac_report.plot_runs RUN_GROUP_DIR   (called by `lmac train` at the end)
    python -m lmac_report.plot_runs --compare OUT.png GROUP_DIR...   (several algorithms in one plot)

Seeds test at nearly the same env steps (each test phase starts when its run crosses a multiple
of run.test_interval), so the common grid is the test points of the seed with the fewest. The
"final" figures average the last test phases of each seed (`final.py`: the one rule), then
report mean and standard deviation across seeds.
"""
import csv
import json
import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .final import FINAL_TEST_PHASES, final_of  # noqa: E402
from .stats import sample_sd  # noqa: E402
from .titles import fit  # noqa: E402


def read(run: pathlib.Path):
    rows = list(csv.DictReader(open(run / "metrics.csv")))
    test = [(int(r["t_env"]), float(r["test_return_mean"]), float(r["test_win_rate"]))
            for r in rows if r["test_return_mean"]]
    return np.array(test) if test else np.zeros((0, 3))


def plot_seed(run: pathlib.Path, test: np.ndarray) -> None:
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(test[:, 0], test[:, 1], label="test return")
    ax.plot(test[:, 0], test[:, 2], label="test win rate", alpha=0.7)
    ax.set_xlabel("env steps")
    env, algo = run.parents[2].name, run.parents[1].name
    ax.set_title(fit(f"{env} {algo} {run.name}"))
    ax.legend()
    fig.tight_layout()
    fig.savefig(run / "test_return.png", dpi=120)
    plt.close(fig)



def group_curves(group: pathlib.Path):
    """(grid, returns [seeds x grid], win rates [seeds x grid]) of a group's seeds."""
    curves = [c for c in (read(r) for r in sorted(p.parent for p in group.glob("**/metrics.csv"))) if len(c)]
    if not curves:
        return None
    grid = min(curves, key=len)[:, 0]
    ys = np.stack([np.interp(grid, c[:, 0], c[:, 1]) for c in curves])
    wins = np.stack([np.interp(grid, c[:, 0], c[:, 2]) for c in curves])
    return grid, ys, wins


def plot_curves(out: pathlib.Path, env: str, labelled: list[tuple[str, pathlib.Path]]) -> None:
    """Test return of each (label, group of seeds): mean with a sample-SD band, one line each."""
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    for label, g in labelled:
        gc = group_curves(g)
        if gc is None:
            continue
        grid, ys, _ = gc
        m, s = ys.mean(0), sample_sd(ys)
        ax.plot(grid, m, label=f"{label} ({len(ys)} seeds)")
        ax.fill_between(grid, m - s, m + s, alpha=0.2)
    ax.set_xlabel("env steps")
    ax.set_ylabel("test return")
    ax.set_title(fit(f"{env}: mean and std over seeds"))
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    print(f"wrote {out}")


def compare(out: pathlib.Path, groups: list[pathlib.Path]) -> None:
    # `lmac train` groups are runs/<env>/<algo>/<time>.
    plot_curves(out, groups[0].parents[1].name if groups else "", [(g.parent.name, g) for g in groups])


def main(group: pathlib.Path) -> None:
    runs = sorted(p.parent for p in group.glob("**/metrics.csv"))
    curves = {}
    for run in runs:
        test = read(run)
        if len(test):
            plot_seed(run, test)
            curves[run] = test
    if not curves:
        print(f"no test results under {group} yet")
        return
    # Mean and sample SD across seeds on a common grid of env steps.
    grid, ys, wins = group_curves(group)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    m, s = ys.mean(0), sample_sd(ys)
    ax.plot(grid, m, label=f"test return (mean of {len(curves)} seeds)")
    ax.fill_between(grid, m - s, m + s, alpha=0.25)
    ax.set_xlabel("env steps")
    ax.set_title(fit(f"{group.parents[1].name} {group.parent.name}"))
    ax.legend()
    fig.tight_layout()
    fig.savefig(group / "summary.png", dpi=120)
    plt.close(fig)
    finals = [(final_of(c[:, 1]), final_of(c[:, 2])) for c in curves.values()]
    summary = {
        "seeds": len(curves),
        "final_tests_averaged": min(FINAL_TEST_PHASES, min(len(c) for c in curves.values())),
        "final_t_env": [int(c[-1, 0]) for c in curves.values()],
        "final_test_return_mean": float(np.mean([f[0] for f in finals])),
        "final_test_return_std": float(sample_sd(np.array([f[0] for f in finals]))),
        "final_test_win_rate_mean": float(np.mean([f[1] for f in finals])),
        "final_test_win_rate_std": float(sample_sd(np.array([f[1] for f in finals]))),
    }
    (group / "summary.json").write_text(json.dumps(summary, indent=2))
    with open(group / "summary.csv", "w") as f:
        f.write("t_env,test_return_mean,test_return_std,test_win_rate_mean,test_win_rate_std\n")
        for i, t in enumerate(grid):
            f.write(f"{int(t)},{ys[:, i].mean():.4f},{sample_sd(ys[:, i]):.4f},{wins[:, i].mean():.4f},{sample_sd(wins[:, i]):.4f}\n")
    print(f"{group}: last-5-tests return {summary['final_test_return_mean']:.3f} "
          f"± {summary['final_test_return_std']:.3f}, win rate {summary['final_test_win_rate_mean']:.3f} "
          f"over {len(curves)} seed(s); plots: {group / 'summary.png'}")


if __name__ == "__main__":
    if sys.argv[1] == "--compare":
        compare(pathlib.Path(sys.argv[2]), [pathlib.Path(a) for a in sys.argv[3:]])
    else:
        main(pathlib.Path(sys.argv[1]))
