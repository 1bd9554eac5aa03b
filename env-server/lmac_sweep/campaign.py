"""Run an lmac campaign's cells as Ray tasks: what `lmac campaign run FILE --ray ADDRESS` calls.

    python -m lmac_sweep.campaign --address auto --lmac /path/to/lmac --file fig6.toml \\
        --out /shared/campaigns/fig6 CELL_ID [CELL_ID ...]

Each cell becomes one Ray task that runs `lmac campaign cell FILE ID --out OUT` on whichever node
has `--cpus-per-cell` CPUs free, so a cell trains, resumes, stops at the campaign's time limit
and writes its run directory exactly as on one machine: the results tree is the same either way.
The tasks are submitted in the campaign's order. `--address local` starts a Ray on this machine.
Exit status: 0 when every cell finished, 1 when some failed (each failure's log tail is printed),
130 when interrupted (the running cells get SIGTERM and keep their last checkpoints).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import signal
import subprocess
import sys

from .sweep import _die_with_parent, _stop


def run_cell(lmac: str, file: str, out: str, cell: str) -> dict:
    """One cell, on the node Ray chose: `lmac campaign cell`, its log beside the run directory."""
    log = pathlib.Path(out) / "logs" / (cell.replace("/", "__") + ".log")
    log.parent.mkdir(parents=True, exist_ok=True)
    cmd = [lmac, "campaign", "cell", file, cell, "--out", out]
    with open(log, "ab") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, preexec_fn=_die_with_parent)
        try:
            rc = proc.wait()
        except BaseException:
            _stop(proc)
            raise
    tail = log.read_text(errors="replace").splitlines()[-12:] if rc != 0 else []
    return {"cell": cell, "rc": rc, "node": os.uname().nodename, "log": str(log), "tail": tail}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lmac_sweep.campaign", description=__doc__.split("\n\n")[0])
    ap.add_argument("--address", required=True, help="a Ray cluster (auto, HOST:6379) or `local` to start one here")
    ap.add_argument("--cpus-per-cell", type=float, default=2.0)
    ap.add_argument("--lmac", required=True, help="the lmac binary every node runs (the same path on each)")
    ap.add_argument("--file", required=True, help="the campaign file (a path every node sees)")
    ap.add_argument("--out", required=True, help="the results tree (on storage every node sees)")
    ap.add_argument("cells", nargs="+", help="cell ids, in the order to submit them")
    a = ap.parse_args(argv)

    import ray

    try:
        if a.address == "local":
            ray.init(include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=a.address, log_to_driver=False)
    except Exception as e:  # noqa: BLE001 - Ray raises many kinds; all mean the same here
        print(f"lmac-campaign: could not start or reach Ray at {a.address}: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    total = ray.cluster_resources().get("CPU", 0)
    if total < a.cpus_per_cell:
        print(f"lmac-campaign: the cluster has {total:g} CPUs, fewer than --cpus-per-cell {a.cpus_per_cell:g}", file=sys.stderr)
        return 2
    task = ray.remote(num_cpus=a.cpus_per_cell, max_retries=0)(run_cell)
    refs = {task.remote(a.lmac, a.file, a.out, c): c for c in a.cells}
    print(f"lmac-campaign: {len(refs)} cells submitted to a cluster of {total:g} CPUs", file=sys.stderr)
    failed = 0
    try:
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            try:
                r = ray.get(ready[0])
            except Exception as e:  # noqa: BLE001 - a task lost with its node, say
                failed += 1
                print(f"lmac-campaign: {refs[ready[0]]}: the task failed: {type(e).__name__}: {e}", file=sys.stderr)
                continue
            if r["rc"] == 0:
                print(f"lmac-campaign: {r['cell']}: done on {r['node']} ({len(pending)} left)", file=sys.stderr)
            else:
                failed += 1
                print(f"lmac-campaign: {r['cell']}: exit {r['rc']} on {r['node']}, log {r['log']}:\n  " + "\n  ".join(r["tail"]), file=sys.stderr)
    except KeyboardInterrupt:
        for ref in refs:
            ray.cancel(ref, force=False)
        print("lmac-campaign: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    return 1 if failed else 0


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    sys.exit(main())
