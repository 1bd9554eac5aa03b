"""The paper's Figure 3 for one `lmac design` run, on a fixed set of state dims: per phase
k = 0, 1, 2 (the messages of phases 0..=k), the mean recovery rate E_t[chi], its skill over a
constant guess of each dim's median, and its variance across agents, with messages and without
(both definitions: a discriminator retrained without messages, and the paper's, the
with-messages discriminator given zeroed messages).

    python -m lmac_report.plot_design DESIGN_DIR   (called by `lmac design` at the end)

Reads DESIGN_DIR/summary.json, writes DESIGN_DIR/recovery.png. The fixed dims are phase 0's
critical dims (all dims when it names none); the second row shows all dims.
"""
import json
import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from .titles import fit  # noqa: E402

SIDES = [("with_messages", "with messages", "#4C72B0"),
         ("without_retrained", "without (retrained)", "#999999"),
         ("without_zeroed", "without (zeroed, the paper's)", "#DD8452")]
PANELS = [("mean_recovery", "mean recovery E_t[chi]"),
          ("skill", "skill over a constant guess"),
          ("mean_variance_across_agents", "variance across agents")]


def main(design: pathlib.Path) -> None:
    s = json.loads((design / "summary.json").read_text())
    rows = s["evaluations"]
    sets = [("fixed_dims", f"{len(s['fixed_dims']) or 'all'} fixed dims ({s['fixed_dims_source']})"),
            ("all_dims", f"all {rows[0]['all_dims']['dims']} dims")]
    fig, axes = plt.subplots(len(sets), len(PANELS), figsize=(12, 3.4 * len(sets)), squeeze=False)
    width = 0.27
    for r, (key, title) in enumerate(sets):
        for c, (metric, label) in enumerate(PANELS):
            ax = axes[r][c]
            for j, (side, side_label, color) in enumerate(SIDES):
                xs = [row["phase"] + (j - 1) * width for row in rows]
                vals = [row[key][side][metric] for row in rows]
                ax.bar(xs, vals, width, color=color, label=side_label)
                for x, v in zip(xs, vals):
                    ax.text(x, v, f"{v:.3g}", ha="center", va="bottom", fontsize=6)
            if metric == "mean_recovery":
                ax.axhline(rows[0][key]["constant_guess_rate"], color="black", lw=0.8, ls="--",
                           label="constant guess")
            ax.set_xticks([row["phase"] for row in rows], [f"k = {row['phase']}" for row in rows])
            ax.set_title(fit(f"{label}: {title}", 50), fontsize=8)
            ax.tick_params(labelsize=7)
    axes[0][0].legend(fontsize=6)
    fig.suptitle(fit(f"{s['env']}: protocol design with the {s['designer']} designer (alpha {s['alpha']})", 90), fontsize=10)
    fig.tight_layout()
    out = design / "recovery.png"
    fig.savefig(out, dpi=120)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(pathlib.Path(sys.argv[1]))
