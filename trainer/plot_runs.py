"""Plots of `lmac train` runs: per seed the test return and win rate against env steps, and for
a group of seeds the mean with a standard-deviation band plus a table of final figures.

    python trainer/plot_runs.py RUN_GROUP_DIR   (called by `lmac train` at the end)
"""
import csv
import json
import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


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
    ax.set_title(f"{env} {algo} {run.name}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(run / "test_return.png", dpi=120)
    plt.close(fig)


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
    # Mean and std across seeds on a common grid of env steps.
    grid = np.unique(np.concatenate([c[:, 0] for c in curves.values()]))
    grid = grid[grid <= min(c[-1, 0] for c in curves.values())]
    ys = np.stack([np.interp(grid, c[:, 0], c[:, 1]) for c in curves.values()])
    wins = np.stack([np.interp(grid, c[:, 0], c[:, 2]) for c in curves.values()])
    fig, ax = plt.subplots(figsize=(6, 3.5))
    m, s = ys.mean(0), ys.std(0)
    ax.plot(grid, m, label=f"test return (mean of {len(curves)} seeds)")
    ax.fill_between(grid, m - s, m + s, alpha=0.25)
    ax.set_xlabel("env steps")
    ax.set_title(f"{group.parents[1].name} {group.parent.name}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(group / "summary.png", dpi=120)
    plt.close(fig)
    finals = [c[-1] for c in curves.values()]
    summary = {
        "seeds": len(curves),
        "final_t_env": [int(f[0]) for f in finals],
        "final_test_return_mean": float(np.mean([f[1] for f in finals])),
        "final_test_return_std": float(np.std([f[1] for f in finals])),
        "final_test_win_rate_mean": float(np.mean([f[2] for f in finals])),
        "final_test_win_rate_std": float(np.std([f[2] for f in finals])),
    }
    (group / "summary.json").write_text(json.dumps(summary, indent=2))
    with open(group / "summary.csv", "w") as f:
        f.write("t_env,test_return_mean,test_return_std,test_win_rate_mean,test_win_rate_std\n")
        for i, t in enumerate(grid):
            f.write(f"{int(t)},{ys[:, i].mean():.4f},{ys[:, i].std():.4f},{wins[:, i].mean():.4f},{wins[:, i].std():.4f}\n")
    print(f"{group}: final test return {summary['final_test_return_mean']:.3f} "
          f"± {summary['final_test_return_std']:.3f}, win rate {summary['final_test_win_rate_mean']:.3f} "
          f"over {len(curves)} seed(s); plots: {group / 'summary.png'}")


if __name__ == "__main__":
    main(pathlib.Path(sys.argv[1]))
