"""Per-row, per-seed numbers of an `lmac experiment` directory: final test return and win rate
(lmac_report.final's rule: the mean of the last 5 test phases), the best checkpoint's final evaluation
(marl_eval.json), and the mean of the last 10 logged rows of the LMAC module's terms.

    PYTHONPATH=env-server python scripts/seed_numbers.py EXPERIMENT_DIR [OUT.json]
"""
import csv, json, pathlib, statistics, sys

from lmac_report.final import final_of

root = pathlib.Path(sys.argv[1]) / "runs"
out = {}
for row in sorted(p.name for p in root.iterdir()):
    seeds = []
    for sd in sorted((root / row).glob("seed*")):
        if not (sd / "metrics.csv").exists():
            continue
        rows = [r for r in csv.DictReader(open(sd / "metrics.csv")) if r["test_return_mean"]]
        fin_r = final_of([float(r["test_return_mean"]) for r in rows]) if rows else None
        fin_w = final_of([float(r["test_win_rate"]) for r in rows]) if rows else None
        me = sd / "marl_eval.json"
        best = None
        if me.exists():
            d = json.load(open(me))
            (runs,) = [v for env in d.values() for v in env.values()]
            (seed,) = [s for a in runs.values() for s in a.values()]
            am = seed["absolute_metrics"]
            best = (statistics.mean(am["return"]), statistics.mean(am["win_rate"]) if "win_rate" in am else None)
        t_env = int(rows[-1]["t_env"]) if rows else 0
        logged = [r for r in csv.DictReader(open(sd / "metrics.csv")) if r.get("loss")][-10:]
        terms = {k: statistics.mean(float(r[k]) for r in logged) for k in
                 ["lmac_cons", "lmac_z_sq", "lmac_recon_mse", "lmac_recovered", "q_taken_mean", "grad_norm"]
                 if logged and all(r.get(k) for r in logged)}
        seeds.append({"seed": sd.name, "t_env": t_env, "final_return": fin_r, "final_win": fin_w, "best": best, "last_rows": terms})
    out[row] = seeds
    done = [s for s in seeds if s["best"]]
    if not done:
        continue
    fr = [s["final_return"] for s in done]
    print(f"{row}: {len(done)} done; final {statistics.mean(fr):.2f} +- {statistics.pstdev(fr):.2f} {[round(x,2) for x in fr]}; "
          f"win {[round(s['final_win'],3) for s in done]}; best {[tuple(round(v,3) for v in s['best']) for s in done]}")
json.dump(out, open(sys.argv[2], "w"), indent=1) if len(sys.argv) > 2 else None
