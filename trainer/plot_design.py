"""The paper's Figure 3 for one `lmac design` run: per phase, the mean recovery rate E_t[chi]
over the target state dims and its variance across agents, with messages (k = 0, 1, 2) and
without (no messages).

    python trainer/plot_design.py DESIGN_DIR   (called by `lmac design` at the end)

Reads DESIGN_DIR/summary.json, writes DESIGN_DIR/recovery.png.
"""
import json
import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main(design: pathlib.Path) -> None:
    s = json.loads((design / "summary.json").read_text())
    rows = s["evaluations"]
    labels = ["no messages"] + [f"k = {r['phase']}" for r in rows]
    # The no-message figures of the first evaluation (every phase trains its own no-message
    # discriminator on the same data; they differ only by training noise).
    means = [rows[0]["without_messages"]["mean_recovery"]] + [r["with_messages"]["mean_recovery"] for r in rows]
    vars_ = [rows[0]["without_messages"]["mean_variance_across_agents"]] + \
        [r["with_messages"]["mean_variance_across_agents"] for r in rows]
    colors = ["#999999"] + ["#4C72B0", "#55A868", "#C44E52"][: len(rows)]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for ax, vals, title in [(axes[0], means, "(a) mean recovery E_t[chi]"),
                            (axes[1], vars_, "(b) variance across agents")]:
        ax.bar(labels, vals, color=colors)
        for i, v in enumerate(vals):
            ax.text(i, v, f"{v:.3g}", ha="center", va="bottom", fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.tick_params(axis="x", labelsize=8)
    axes[0].set_ylim(0, 1.05)
    dims = s["target_dims"]
    n_dims = len(dims) if isinstance(dims, list) else dims
    fig.suptitle(f"{s['env']}: protocol design with the {s['designer']} designer "
                 f"({n_dims} target state dims, alpha {s['alpha']})", fontsize=10)
    fig.tight_layout()
    out = design / "recovery.png"
    fig.savefig(out, dpi=120)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(pathlib.Path(sys.argv[1]))
