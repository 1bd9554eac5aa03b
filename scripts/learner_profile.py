"""Where one learner update's time goes, op by op: `perf record` over `lmac bench learner` on one
thread, the samples grouped by what each function does, and beside them the machine's one-core
memory rate (a large copy), which bounds the passes over memory between the matmuls.

    python scripts/learner_profile.py target/release/lmac docs/figures/learner_profile_1o10b.json

The bench also sets up (random inputs, the ceiling's matmuls timed alone); its samples are taken
out by difference: each case runs once with `--updates N` and once with one update, and the
groups' sample counts are subtracted. Needs `perf` (linux-perf). Run it with nothing else on
the machine.
"""
import argparse
import json
import multiprocessing
import pathlib
import re
import subprocess
import tempfile
import time

import numpy as np

ONE_O = ["--shape", "1o10b", "--actions", "7"]
CASES = {
    "qmix": ONE_O + ["--input", "103", "--mixers", "qmix"],
    "vdn": ONE_O + ["--input", "103", "--mixers", "vdn"],
    "lmac-window": ONE_O + ["--input", "159", "--mixers", "qmix", "--algo", "lmac", "--messages", "56", "--critical", "4"],
    "lmac-paper": ONE_O + ["--input", "159", "--mixers", "qmix", "--algo", "lmac", "--messages", "56", "--critical", "4",
                           "--method", 'encoder="gru-gate"', "--method", "mask_consistency=false",
                           "--method", "dropout_when_acting=true"],
    "qmix-lbf8x8": ["--shape", "lbf8x8", "--mixers", "qmix"],
}

# (group, pattern on the symbol), first match wins
GROUPS = [
    ("matmul: gemm kernels", r"gemm_f32::microkernel|gemm_basic"),
    ("matmul: packing operands", r"gemm_common"),
    ("GRU recurrence: gate arithmetic", r"gru_sequence"),
    ("dense layer: bias, activation, mask, LayerNorm passes", r"lmac_learn::dense::(forward_on|layer_norm|activate)|DenseBackward"),
    ("dropout masks (random draws)", r"dropout_mask"),
    ("LMAC gate, agent input", r"latent_gate|agent_input"),
    ("QMIX mixing", r"qmix_mix"),
    ("window attention", r"window_attention"),
    ("copies (memmove)", r"memmove|memcpy"),
    ("zeroed buffers (memset, fresh pages)", r"memset|clear_page|exc_page_fault|page_fault"),
    ("burn operations (elementwise, reductions, layout)", r"burn_|cubecl|macerator"),
    ("allocation", r"malloc|_int_free|free|realloc|mmap|munmap"),
    ("exp, log (loss terms)", r"expf|logf|log1pf"),
]


def memory_rate_gb_s(_=None):
    """One core's copy rate: bytes read plus written per second, best of 5 copies of 256 MB."""
    a = np.ones(64 * 1024 * 1024, dtype=np.float32)
    b = np.empty_like(a)
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        np.copyto(b, a)
        best = min(best, time.perf_counter() - t0)
    return 2 * a.nbytes / best / 1e9


def memory_rate_two_cores_gb_s():
    """Each core's copy rate while both copy at once (two processes)."""
    with multiprocessing.Pool(2) as pool:
        return pool.map(memory_rate_gb_s, range(2))


def samples(binary, args, updates):
    """Sample counts per group of one bench run, and its report."""
    with tempfile.TemporaryDirectory() as tmp:
        data = pathlib.Path(tmp) / "perf.data"
        cmd = ["perf", "record", "-F", "999", "-o", str(data), binary, "bench", "learner", *args,
               "--no-stepwise", "--rounds", "1", "--updates", str(updates), "--json"]
        run = subprocess.run(cmd, check=True, capture_output=True, text=True)
        report = subprocess.run(["perf", "report", "-i", str(data), "--no-children", "-n", "--sort", "symbol", "--stdio",
                                 "--percent-limit", "0"], check=True, capture_output=True, text=True).stdout
    counts = {}
    for line in report.splitlines():
        m = re.match(r"\s+[0-9.]+%\s+([0-9]+)\s+\[[.k]\]\s+(.*)", line)
        if m:
            group = next((g for g, p in GROUPS if re.search(p, m.group(2))), "other")
            counts[group] = counts.get(group, 0) + int(m.group(1))
    return counts, json.loads(run.stdout)


def profile(binary, args, updates):
    many, bench = samples(binary, args, updates)
    one, _ = samples(binary, args, 1)
    diff = {g: max(many.get(g, 0) - one.get(g, 0), 0) for g in set(many) | set(one)}
    total = sum(diff.values())
    fig = bench["figures"][0]
    ceiling = bench["shape_ceiling"][0]["ms_if_every_matmul_ran_alone"]
    update_ms = fig["median_ms"]
    groups = {g: {"share": round(v / total, 4), "ms_per_update": round(update_ms * v / total, 2)}
              for g, v in sorted(diff.items(), key=lambda kv: -kv[1]) if v > 0}
    return {"update_ms": update_ms, "ceiling_ms": ceiling, "times_ceiling": update_ms / ceiling,
            "samples": {"with_updates": sum(many.values()), "with_one_update": sum(one.values())}, "groups": groups}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("binary")
    ap.add_argument("out")
    ap.add_argument("--updates", type=int, default=60)
    ap.add_argument("--only", default=",".join(CASES), help="cases, comma separated: " + ", ".join(CASES))
    a = ap.parse_args()
    out = {"command": f"python scripts/learner_profile.py LMAC {a.out} --updates {a.updates} --only {a.only}",
           "what": "perf samples of `lmac bench learner` on one thread, grouped by what each function does; "
                   "ms_per_update is the group's share of the median update",
           "memory_copy_rate_gb_s_one_core": round(memory_rate_gb_s(), 2),
           "memory_copy_rate_gb_s_each_of_two_cores_at_once": [round(r, 2) for r in memory_rate_two_cores_gb_s()],
           "cases": {}}
    for name in a.only.split(","):
        out["cases"][name] = profile(a.binary, CASES[name], a.updates)
        c = out["cases"][name]
        print(f"{name}: {c['update_ms']:.1f} ms per update, ceiling {c['ceiling_ms']:.1f} ms ({c['times_ceiling']:.2f}x)")
        for g, v in c["groups"].items():
            print(f"  {v['share'] * 100:5.1f}%  {v['ms_per_update']:6.1f} ms  {g}")
    print(f"copy rate: {out['memory_copy_rate_gb_s_one_core']} GB/s on one core, "
          f"{out['memory_copy_rate_gb_s_each_of_two_cores_at_once']} GB/s each with both copying (read + written)")
    pathlib.Path(a.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
