# Final test returns of the 1o_10b runs (issue 13/15 figures): python scripts/final_1o10b.py ALGOS OUT.json
"""Final test return (mean of the last 5 test phases) and win rate per run, for 1o_10b runs:
seed 0 from docs/figures flat copies, seeds 1-2 from /work/exp run dirs; plus marl_eval (best
checkpoint, greedy) where present."""
import csv, json, os, sys, statistics as st
def last5(path):
    rows=[r for r in csv.DictReader(open(path)) if r.get("test_return_mean") not in (None,"")]
    rows=rows[-5:]
    return statistics(rows)
def statistics(rows):
    return (sum(float(r["test_return_mean"]) for r in rows)/len(rows), sum(float(r["test_win_rate"]) for r in rows)/len(rows), int(float(rows[-1]["t_env"])))
out={}
for algo in sys.argv[1].split(","):
    runs=[]
    flat=f"/work/main/docs/figures/lmac_1o10b/{algo}_seed0.csv"
    if os.path.exists(flat): runs.append(("seed0",flat,None))
    for base in ["/work/exp/1o10b_base/runs","/work/exp/1o10b_comm/runs"]:
        for s in (0,1,2):
            d=f"{base}/{algo}/seed{s}"
            if os.path.exists(f"{d}/metrics.csv") and os.path.exists(f"{d}/marl_eval.json"):
                runs.append((f"seed{s}",f"{d}/metrics.csv",f"{d}/marl_eval.json"))
    res=[]
    for s,p,me in runs:
        r,w,t=last5(p)
        ev=None
        if me:
            m=json.load(open(me)); a=list(list(list(m.values())[0].values())[0].values())[0]
            am=list(a.values())[0]["absolute_metrics"]
            ev={"return":st.mean(am["return"]),"win_rate":st.mean(am["win_rate"]) if "win_rate" in am else None}
        res.append({"seed":s,"final_test_return":round(r,3),"final_win_rate":round(w,3),"t_env":t,"best_checkpoint_eval":ev})
    out[algo]=res
    rs=[x["final_test_return"] for x in res]; ws=[x["final_win_rate"] for x in res]
    print(algo, len(rs), f"{st.mean(rs):.2f} ± {st.pstdev(rs) if len(rs)>1 else 0:.2f}", rs, f"win {st.mean(ws):.3f}", [x["best_checkpoint_eval"] for x in res])
json.dump(out,open(sys.argv[2],"w"),indent=1)
