"""Final test return (mean of the last 5 test phases) and win rate of every smaclite:1o_10b_vs_1r
run committed under docs/figures, with the best checkpoint's greedy evaluation where the run has
one (marl_eval.json). Issue 13/15 figures:

    .venv/bin/python scripts/final_1o10b.py qmix,fullcomm,qmix-state,ndq,cola,t2mac,maic docs/figures/final_1o10b_all.json
"""
import csv
import json
import os
import statistics as st
import sys

FIGURES = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "docs", "figures")
# where each seed's flat copies (<algo>_seed<k>.csv, .marl_eval.json) live
FOLDERS = {0: ["lmac_1o10b", "comm_baselines_1o10b"], 1: ["baselines_1o10b_seeds12"], 2: ["baselines_1o10b_seeds12"]}


def last5(path):
    rows = [r for r in csv.DictReader(open(path)) if r.get("test_return_mean") not in (None, "")][-5:]
    ret = sum(float(r["test_return_mean"]) for r in rows) / len(rows)
    win = sum(float(r["test_win_rate"]) for r in rows) / len(rows)
    return ret, win, int(float(rows[-1]["t_env"]))


def best_checkpoint(path):
    if not os.path.exists(path):
        return None
    m = json.load(open(path))
    runs = list(list(list(m.values())[0].values())[0].values())[0]
    am = list(runs.values())[0]["absolute_metrics"]
    return {"return": st.mean(am["return"]), "win_rate": st.mean(am["win_rate"]) if "win_rate" in am else None}


def main(algos, out_path):
    out = {}
    for algo in algos:
        res = []
        for seed, folders in FOLDERS.items():
            for folder in folders:
                base = os.path.join(FIGURES, folder, f"{algo}_seed{seed}")
                if os.path.exists(base + ".csv"):
                    r, w, t = last5(base + ".csv")
                    res.append({"seed": f"seed{seed}", "final_test_return": round(r, 3), "final_win_rate": round(w, 3), "t_env": t,
                                "best_checkpoint_eval": best_checkpoint(base + ".marl_eval.json")})
                    break
        out[algo] = res
        rs = [x["final_test_return"] for x in res]
        ws = [x["final_win_rate"] for x in res]
        print(algo, len(rs), f"{st.mean(rs):.2f} ± {st.pstdev(rs) if len(rs) > 1 else 0:.2f}", rs, f"win {st.mean(ws):.3f}")
    json.dump(out, open(out_path, "w"), indent=1)


if __name__ == "__main__":
    main(sys.argv[1].split(","), sys.argv[2])
