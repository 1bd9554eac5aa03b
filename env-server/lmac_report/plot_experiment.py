"""Plots of an `lmac experiment` directory (called by the command at its end):

- curves.png: test return against env steps, one line per algorithm (mean over seeds with a
  standard-deviation band), the paper's Figure 6 layout for one environment;
- phases.png, when the experiment trained the k = 0 and k = 1 ablations next to LMAC: final
  test return against the number of design phases used (the paper's Figure 7(d)).

    python -m lmac_report.plot_experiment EXPERIMENT_DIR
"""
import json
import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from .plot_runs import plot_curves  # noqa: E402
from .titles import fit  # noqa: E402


def main(exp: pathlib.Path) -> None:
    table = json.loads((exp / "comparison.json").read_text())
    env = table["env"]
    plot_curves(exp / "curves.png", env, [(r["label"], exp / "runs" / r["label"]) for r in table["rows"]])

    rows = {r["label"]: r for r in table["rows"]}
    phases = [(k, rows.get(label)) for k, label in [(0, "lmac-k0"), (1, "lmac-k1"), (2, "lmac")]]
    if all(r is not None for _, r in phases):
        fig, ax = plt.subplots(figsize=(4.5, 3.2))
        ks = [k for k, _ in phases]
        ax.errorbar(ks, [r["final_return_mean"] for _, r in phases], yerr=[r["final_return_std"] for _, r in phases],
                    marker="o", capsize=4)
        ax.set_xticks(ks, [f"k={k}" for k in ks])
        ax.set_ylabel("test return, mean of the last 5 test phases")
        ax.set_title(fit(f"{env}: design phases used"))
        fig.tight_layout()
        fig.savefig(exp / "phases.png", dpi=120)
        plt.close(fig)
        print(f"wrote {exp / 'phases.png'}")


if __name__ == "__main__":
    main(pathlib.Path(sys.argv[1]))
