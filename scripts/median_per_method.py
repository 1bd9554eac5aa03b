"""Medians over alternating rounds of one figure per method, and each median's ratio to QMIX's
(scripts/figures.sh `methods`): reads DIR/<prefix><algo>_<round>.json for rounds 1-3.

    python scripts/median_per_method.py DIR OUT.json --prefix l_ --key figures.0.median_ms \\
        --command "lmac bench learner ..." qmix lmac ndq ...
"""
import argparse
import json
import pathlib
import statistics


def pick(doc, key):
    for part in key.split("."):
        doc = doc[int(part)] if isinstance(doc, list) else doc[part]
    return doc


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", type=pathlib.Path)
    ap.add_argument("out", type=pathlib.Path)
    ap.add_argument("algos", nargs="+", help="methods; the first is the ratios' reference")
    ap.add_argument("--prefix", default="")
    ap.add_argument("--key", default="ms_per_update", help="dotted path of the figure in each JSON")
    ap.add_argument("--command", required=True, help="what produced the files, for the record")
    a = ap.parse_args()
    runs = {m: [json.loads((a.dir / f"{a.prefix}{m}_{r}.json").read_text()) for r in (1, 2, 3)] for m in a.algos}
    ms = {m: [pick(x, a.key) for x in runs[m]] for m in a.algos}
    med = {m: statistics.median(ms[m]) for m in a.algos}
    ratio = {m: med[m] / med[a.algos[0]] for m in a.algos}
    doc = {"command": a.command, "ms_per_update_median": med, "ms_per_update_rounds": ms, "ratio_to_qmix": ratio, "runs": runs}
    a.out.write_text(json.dumps(doc, indent=1) + "\n")
    for m in a.algos:
        print(f"{m:13s} {med[m]:7.1f} ms/update (rounds {', '.join(f'{v:.1f}' for v in ms[m])})  x{ratio[m]:.2f} of {a.algos[0]}")


if __name__ == "__main__":
    main()
