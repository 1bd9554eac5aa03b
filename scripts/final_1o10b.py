"""Final test return (mean of the last 5 test phases), win rate and peak (the best mean of 5
consecutive test phases) of every smaclite:1o_10b_vs_1r run committed under docs/figures, with
the best checkpoint's greedy evaluation where the run has one (marl_eval.json).
figures:

    .venv/bin/python scripts/final_1o10b.py qmix,fullcomm,qmix-state,lmac,lmac-gru-gate,lmac-fullproto,lmac-td,lmac-raw,lmac-k0,lmac-k1,lmac-k2,lmac-no-cons,lmac-no-meta,lmac-cons-detached,ndq,ndq-rerun,cola,t2mac,maic,masia docs/figures/final_1o10b_all.json

`--stage DIR` gathers the found runs' metrics as flat `<label>_seed<k>.csv` and `.config.toml` copies in DIR
(`lmac-k2` as `lmac`; no marl_eval.json, so every run is scored on its last 5 test phases) for
`lmac report`; the 1o_10b comparison's curves and CIs:

    .venv/bin/python scripts/final_1o10b.py qmix,fullcomm,qmix-state,lmac-k2,ndq,cola,t2mac,maic,masia /tmp/final.json --stage /tmp/r1o10b
    target/release/lmac report /tmp/r1o10b --out docs/figures/comm_baselines_1o10b/report
"""
import argparse
import csv
import json
import os
import shutil
import statistics as st
import sys

from lmac_report.final import final_of, peak_of

FIGURES = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "docs", "figures")
# where the flat copies (<algo>_seed<k>.csv, .marl_eval.json) live, first match wins: LMAC's row
# is the window encoder (the default); the gru-gate seed of lmac_1o10b is `lmac-gru-gate`
FOLDERS = ["lmac_1o10b_window", "lmac_1o10b", "baselines_1o10b_seeds12", "comm_baselines_1o10b", "lmac_1o10b_ablations",
           "lmac_1o10b_diagnosis"]
ALIASES = {"lmac-gru-gate": ("lmac_1o10b", "lmac")}


def last5(path):
    """(final return, final win rate, last t_env, peak): means of test phases (lmac_report.final)."""
    tests = [r for r in csv.DictReader(open(path)) if r.get("test_return_mean") not in (None, "")]
    returns = [float(r["test_return_mean"]) for r in tests]
    wins = [float(r["test_win_rate"]) for r in tests]
    return final_of(returns), final_of(wins), int(float(tests[-1]["t_env"])), peak_of(returns)


def best_checkpoint(path):
    if not os.path.exists(path):
        return None
    m = json.load(open(path))
    runs = list(list(list(m.values())[0].values())[0].values())[0]
    am = list(runs.values())[0]["absolute_metrics"]
    return {"return": st.mean(am["return"]), "win_rate": st.mean(am["win_rate"]) if "win_rate" in am else None}


def main(algos, out_path, stage=None):
    out = {}
    if stage:
        os.makedirs(stage, exist_ok=True)
    for algo in algos:
        res = []
        folders, name = ([ALIASES[algo][0]], ALIASES[algo][1]) if algo in ALIASES else (FOLDERS, algo)
        for seed in range(3):
            for folder in folders:
                base = os.path.join(FIGURES, folder, f"{name}_seed{seed}")
                if os.path.exists(base + ".csv"):
                    r, w, t, peak = last5(base + ".csv")
                    res.append({"seed": f"seed{seed}", "folder": folder, "final_test_return": round(r, 3), "final_win_rate": round(w, 3),
                                "t_env": t, "peak_test_return": round(peak, 3),
                                "best_checkpoint_eval": best_checkpoint(base + ".marl_eval.json")})
                    if stage:
                        label = "lmac" if algo == "lmac-k2" else algo
                        for ext in (".csv", ".config.toml"):
                            shutil.copy(base + ext, os.path.join(stage, f"{label}_seed{seed}{ext}"))
                    break
        out[algo] = res
        if not res:
            print(algo, "no runs")
            continue
        rs = [x["final_test_return"] for x in res]
        ws = [x["final_win_rate"] for x in res]
        ps = [x["peak_test_return"] for x in res]
        print(algo, len(rs), f"{st.mean(rs):.2f} ± {st.pstdev(rs) if len(rs) > 1 else 0:.2f}", rs, f"win {st.mean(ws):.3f}",
              f"peak {st.mean(ps):.2f}", ps)
    json.dump(out, open(out_path, "w"), indent=1)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("labels", help="comma-separated run labels")
    ap.add_argument("out", help="the summary JSON to write")
    ap.add_argument("--stage", help="also gather the found runs as flat copies here, for `lmac report`")
    a = ap.parse_args()
    main(a.labels.split(","), a.out, a.stage)
