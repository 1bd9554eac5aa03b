"""One learner update of every method, two lmac builds side by side (before/after):
`lmac bench learner` for each method and shape, the builds alternating within each round, rounds
repeated, medians and after/before ratios written as JSON.

    python scripts/learner_ab.py BEFORE_BINARY AFTER_BINARY docs/figures/learner_ab.json --rounds 3

Absolute milliseconds move with the machine's load (+-20% here); the ratios of the two builds,
measured alternately in one run, are what to read.
"""
import argparse
import json
import pathlib
import statistics
import subprocess
import sys

TWO_CORES = "lmac-two-cores"  # the bench's name of the two-core figure

# 1o_10b_vs_1r's update shape (32 episodes x 50 steps x 11 agents, obs 85, 7 actions, state 148);
# LMAC reads the committed offline design's 211 message columns and reconstructs its 48 critical
# dims, or the authors' design's 56 columns and 4 dims; FullComm's agents read 960.
ONE_O = ["--shape", "1o10b", "--actions", "7"]
CASES = {
    "1o10b": [
        ("qmix", ONE_O + ["--input", "103", "--mixers", "qmix"]),
        ("vdn", ONE_O + ["--input", "103", "--mixers", "vdn"]),
        ("qplex", ONE_O + ["--input", "103", "--mixers", "qplex"]),
        ("lmac", ONE_O + ["--input", "314", "--mixers", "qmix", "--algo", "lmac", "--messages", "211", "--critical", "48"]),
        ("lmac-paper-design", ONE_O + ["--input", "159", "--mixers", "qmix", "--algo", "lmac", "--messages", "56", "--critical", "4"]),
        ("lmac-gru-gate", ONE_O + ["--input", "314", "--mixers", "qmix", "--algo", "lmac", "--messages", "211", "--critical", "48",
                                   "--method", 'encoder="gru-gate"']),
        # `--preset paper`'s module: the authors' GRU-gate encoder, unmasked consistency, the
        # embedding's dropout when acting (and in the target network's unroll)
        ("lmac-paper", ONE_O + ["--input", "159", "--mixers", "qmix", "--algo", "lmac", "--messages", "56", "--critical", "4",
                                "--method", 'encoder="gru-gate"', "--method", "mask_consistency=false",
                                "--method", "dropout_when_acting=true"]),
        ("fullcomm", ONE_O + ["--input", "1063", "--mixers", "qmix", "--algo", "fullcomm", "--messages", "960"]),
        ("qmix-state", ONE_O + ["--input", "103", "--mixers", "qmix", "--algo", "qmix-state"]),
        ("ndq", ONE_O + ["--input", "103", "--mixers", "qmix", "--algo", "ndq"]),
        ("maic", ONE_O + ["--input", "103", "--mixers", "qmix", "--algo", "maic"]),
        ("masia", ONE_O + ["--input", "103", "--mixers", "qmix", "--algo", "masia"]),
        ("cola", ONE_O + ["--input", "103", "--mixers", "qmix", "--algo", "cola"]),
        ("t2mac", ONE_O + ["--input", "103", "--mixers", "qmix", "--algo", "t2mac"]),
    ],
    "lbf8x8": [
        ("qmix", ["--shape", "lbf8x8", "--mixers", "qmix"]),
        ("vdn", ["--shape", "lbf8x8", "--mixers", "vdn"]),
        ("qplex", ["--shape", "lbf8x8", "--mixers", "qplex"]),
    ],
}


def bench(binary, args, updates, two_cores):
    cmd = [binary, "bench", "learner", *args, "--no-stepwise", "--rounds", "1", "--updates", str(updates), "--json"]
    if two_cores:
        cmd.append("--two-cores")
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    doc = json.loads(out)
    fig = doc["figures"][0]
    row = {"ms": fig["median_ms"], "gflops": fig["gflops"], "sgemm": doc["sgemm_gflops_single_thread"]}
    # the update's matmuls each timed alone at their own shape, in the same run
    ceiling = [c for c in doc.get("shape_ceiling") or [] if c.get("mixer") == fig["mixer"]]
    if ceiling:
        row["ceiling_ms"] = ceiling[0]["ms_if_every_matmul_ran_alone"]
    for other in doc["figures"][1:]:
        if other["name"] == TWO_CORES:
            row["two_cores_ms"] = other["median_ms"]
    return row


def median_of(rounds, key):
    values = [x[key] for x in rounds if key in x]
    return statistics.median(values) if values else None


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before")
    ap.add_argument("after")
    ap.add_argument("out", type=pathlib.Path)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--updates", type=int, default=3)
    ap.add_argument("--shapes", default="1o10b,lbf8x8")
    ap.add_argument("--only", default="", help="comma-separated method names (default: all)")
    ap.add_argument("--two-cores", action="store_true", help="also time each update on two cores, as --preset paper runs it")
    a = ap.parse_args()
    only = set(filter(None, a.only.split(",")))
    rows = {}
    for shape in a.shapes.split(","):
        for name, args in CASES[shape]:
            if only and name not in only:
                continue
            rounds = {"before": [], "after": []}
            for r in range(a.rounds):
                # alternate which build goes first, so a trend in the load favours neither
                order = ("before", "after") if r % 2 == 0 else ("after", "before")
                for which in order:
                    rounds[which].append(bench(getattr(a, which), args, a.updates, a.two_cores))
            med = {w: statistics.median(x["ms"] for x in rounds[w]) for w in rounds}
            gf = {w: [x["gflops"] for x in rounds[w]] for w in rounds}
            sgemm = max(x["sgemm"] for w in rounds for x in rounds[w])
            row = {
                "shape": shape, "method": name, "args": args, "rounds": rounds,
                "median_ms": med, "speedup": med["before"] / med["after"],
                "gflops_after": statistics.median(gf["after"]) if None not in gf["after"] else None,
                "sgemm_gflops": sgemm,
            }
            if row["gflops_after"] is not None:
                row["fraction_of_sgemm_after"] = row["gflops_after"] / sgemm
            for w in rounds:
                ceiling, two = median_of(rounds[w], "ceiling_ms"), median_of(rounds[w], "two_cores_ms")
                if ceiling:
                    row.setdefault("times_ceiling", {})[w] = med[w] / ceiling
                if two:
                    row.setdefault("two_cores_ms", {})[w] = two
                    row.setdefault("two_cores_speedup_over_one_thread", {})[w] = med[w] / two
            rows[f"{shape}/{name}"] = row
            frac = f", {100 * row['fraction_of_sgemm_after']:.0f}% of sgemm" if "fraction_of_sgemm_after" in row else ""
            if "times_ceiling" in row:
                frac += ", " + " / ".join(f"{v:.2f}x its ceiling {w}" for w, v in row["times_ceiling"].items())
            if "two_cores_ms" in row:
                frac += ", two cores " + " / ".join(f"{v:.1f} ms {w}" for w, v in row["two_cores_ms"].items())
            print(f"{shape:7s} {name:18s} before {med['before']:7.1f} ms  after {med['after']:7.1f} ms  x{row['speedup']:.2f}{frac}",
                  flush=True, file=sys.stderr)
    doc = {"command": " ".join(["python scripts/learner_ab.py", *sys.argv[1:]]), "rows": rows}
    a.out.write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
