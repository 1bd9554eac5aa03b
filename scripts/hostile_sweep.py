"""Hostile inputs against the lmac binary, each in a watched child process: files that are
FIFOs, devices (`/dev/zero` linked in), directories, oversized, binary or malformed, given as a
config, a protocol, a dataset or inside a run directory; symlinks planted in a run directory
pointing at a victim file or folder; crafted names in /dev/shm. For every case it records the
exit status, the time taken and whether lmac panicked (exit 101 or a signal), hung (over
--timeout seconds, then killed), exceeded its memory cap (an address-space limit makes a
runaway read fail), wrote or deleted anything outside its own files (every victim is
checksummed before and after) or named the offending file in its error.

    .venv/bin/python scripts/hostile_sweep.py --out docs/figures/faults/hostile_sweep.json

Needs the release binary (`scripts/setup.sh`); takes a few minutes (one short LBF run is trained
as the template run directory, then copied per case). Not part of the tests.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import pathlib
import resource
import shutil
import stat
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
ENV = "lbf:8x8-2p-2f-s1-coop"
MEM_CAP = 16 << 30  # address space of each process: a runaway read fails instead of filling RAM


def tree_digest(p: pathlib.Path) -> str:
    """Content of a victim file or folder (names, bytes), without following links inside."""
    h = hashlib.sha256()
    if p.is_symlink():
        h.update(b"link:" + os.readlink(p).encode())
    elif p.is_dir():
        for q in sorted(p.rglob("*")):
            h.update(str(q.relative_to(p)).encode())
            if q.is_file() and not q.is_symlink():
                h.update(q.read_bytes())
    elif p.is_file():
        h.update(p.read_bytes())
    elif p.exists():  # a FIFO or device: its type and mode, never its bytes (a read would block)
        st = p.stat()
        h.update(f"{stat.S_IFMT(st.st_mode)}:{st.st_mode}".encode())
    else:
        h.update(b"missing")
    return h.hexdigest()


def limit_memory():
    resource.setrlimit(resource.RLIMIT_AS, (MEM_CAP, MEM_CAP))
    os.setsid()


class Sweep:
    def __init__(self, lmac: pathlib.Path, work: pathlib.Path, timeout: float):
        self.lmac, self.work, self.timeout = lmac, work, timeout
        self.cases: list[dict] = []
        self.victim_file = work / "victim.txt"
        self.victim_dir = work / "victim_dir"
        self.victim_file.write_text("someone else's file\n")
        self.victim_dir.mkdir()
        for f in ("manifest.json", "state.json", "net.bpk", "keep.txt"):
            (self.victim_dir / f).write_text("someone else's\n")

    def run(self, name: str, kind: str, args: list[str], names: str | None, expect_ok: bool = False,
            env: dict | None = None, watch: list[pathlib.Path] = (), timeout: float | None = None) -> dict:
        watched = [self.victim_file, self.victim_dir, *watch]
        before = {str(p): tree_digest(p) for p in watched}
        t0 = time.monotonic()
        proc = subprocess.Popen([str(self.lmac), *args], cwd=ROOT, stdin=subprocess.DEVNULL,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                preexec_fn=limit_memory, env={**os.environ, **(env or {})})
        hung = False
        try:
            out, err = proc.communicate(timeout=timeout or self.timeout)
        except subprocess.TimeoutExpired:
            hung = True
            os.killpg(proc.pid, 9)
            out, err = proc.communicate()
        secs = time.monotonic() - t0
        code = proc.returncode
        touched = [p for p in before if tree_digest(pathlib.Path(p)) != before[p]]
        text = (err or "") + (out or "")
        case = dict(
            name=name, kind=kind, args=args, exit=code, seconds=round(secs, 2), hung=hung,
            panicked=code == 101 or "panicked at" in text or (code is not None and code < 0),
            memory_cap_hit="memory allocation" in text or "capacity overflow" in text,
            touched_outside=touched,
            # Only an error must name its file; a hostile file lmac can use (a metrics file of
            # garbage lines, dropped on resume) is used, and the run goes on.
            names_the_file=None if names is None or expect_ok or code == 0 else names in text,
            ok=code == 0, expected_ok=expect_ok,
            stderr_tail=text.strip().splitlines()[-3:] if text.strip() else [],
        )
        self.cases.append(case)
        flag = "HUNG" if hung else "PANIC" if case["panicked"] else "TOUCHED" if touched else \
            "UNNAMED" if case["names_the_file"] is False else "ok"
        print(f"{flag:8s} {secs:6.2f}s exit {code!s:>4s} {kind:10s} {name}", flush=True)
        return case


def hostile_files(d: pathlib.Path, base: str, good: bytes) -> dict[str, pathlib.Path]:
    """One hostile file of each kind, named after `base`, in `d`."""
    d.mkdir(parents=True, exist_ok=True)
    f = {}

    def put(tag, make):
        p = d / f"{tag}-{base}"
        make(p)
        f[tag] = p

    put("devzero", lambda p: p.symlink_to("/dev/zero"))
    put("devurandom", lambda p: p.symlink_to("/dev/urandom"))
    put("devnull", lambda p: p.symlink_to("/dev/null"))
    put("fifo", lambda p: os.mkfifo(p))
    put("dir", lambda p: p.mkdir())
    put("dangling", lambda p: p.symlink_to(d / "nowhere"))
    put("selfloop", lambda p: p.symlink_to(p))
    put("sparse65m", lambda p: open(p, "wb").truncate(65 << 20))
    put("binary", lambda p: p.write_bytes(bytes(range(256)) * 64))
    put("notutf8", lambda p: p.write_bytes(good[:20] + b"\xff\xfe\x80" + good[20:]))
    put("empty", lambda p: p.write_bytes(b""))
    put("truncated", lambda p: p.write_bytes(good[: len(good) // 2]))
    put("bom", lambda p: p.write_bytes(b"\xef\xbb\xbf" + good))
    put("nul", lambda p: p.write_bytes(good.replace(b"\n", b"\x00\n", 3)))
    put("unreadable", lambda p: (p.write_bytes(good), p.chmod(0)))
    put("deep", lambda p: p.write_bytes(b"[" * 100000 + b"]" * 100000))
    put("hugenum", lambda p: p.write_bytes(good.replace(b"1", b"1" + b"0" * 400, 2)))
    return f


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lmac", default=str(ROOT / "target/release/lmac"))
    ap.add_argument("--out", default=str(ROOT / "docs/figures/faults/hostile_sweep.json"))
    ap.add_argument("--timeout", type=float, default=10.0, help="seconds before a case counts as hung")
    ap.add_argument("--train-timeout", type=float, default=180.0,
                    help="the same for run-directory cases, which may train 1000 steps before they end")
    a = ap.parse_args()
    work = pathlib.Path(tempfile.mkdtemp(prefix="lmac-hostile-"))
    s = Sweep(pathlib.Path(a.lmac), work, a.timeout)
    t_start = time.monotonic()

    # Files that are valid (a byte-order mark is skipped; an unreadable file is readable by root;
    # an empty config is every default) are used, not refused: they train 1000 steps.
    valid = {"bom"} | ({"unreadable"} if os.geteuid() == 0 else set())
    short = ["--steps", "1000", "--set", "run.envs=8", "--set", "run.servers=1", "--set", "run.test_episodes=0",
             "--set", "run.final_eval_episodes=0"]
    # 1. Configs: `lmac train --config X` (refused before anything is trained).
    good_cfg = f'[run]\nenv = "{ENV}"\nalgo = "qmix"\nsteps = 1000\n'.encode()
    out = work / "runs"
    for tag, p in hostile_files(work / "configs", "config.toml", good_cfg).items():
        ok = tag in valid | {"empty"}
        s.run(tag, "--config", ["train", "--config", str(p), *short, "--out", str(out)], names=p.name,
              expect_ok=ok, timeout=a.train_timeout if ok else None)
    # 2. Protocols: `lmac protocol check` and `lmac train --protocol`.
    good_proto = (ROOT / "protocols/paper/lbf_8x8-2p-2f-s1-coop/phase0/protocol.json").read_bytes()
    for tag, p in hostile_files(work / "protocols", "protocol.json", good_proto).items():
        ok = tag in valid
        s.run(tag, "protocol", ["protocol", "check", "--env", ENV, str(p)], names=p.name, expect_ok=ok)
        s.run(tag, "explain", ["protocol", "explain", "--env", ENV, str(p)], names=p.name, expect_ok=ok)
        s.run(tag, "--protocol", ["train", "--env", ENV, "--algo", "lmac", "--protocol", str(p), *short,
                                  "--out", str(out)], names=p.name, expect_ok=ok,
              timeout=a.train_timeout if ok else None)
    # 3. Run directories: a short finished run as the template, copied per case with one file
    #    replaced; resumed with a larger step target so that it trains (and writes) again.
    tmpl_out = work / "template"
    r = subprocess.run([str(s.lmac), "train", "--env", ENV, "--algo", "qmix", "--steps", "2000",
                        "--set", "run.envs=8", "--set", "run.servers=1", "--set", "run.checkpoint_interval=1000",
                        "--set", "run.test_episodes=0", "--set", "run.final_eval_episodes=0",
                        "--set", "run.dataset_episodes=4",
                        "--out", str(tmpl_out)], cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        print(r.stderr, file=sys.stderr)
        return 1
    template = next(tmpl_out.rglob("seed0"))
    in_run = {
        "config.toml": good_cfg,
        "metrics.csv": (template / "metrics.csv").read_bytes(),
        "metrics.jsonl": (template / "metrics.jsonl").read_bytes(),
        "checkpoint/state.json": (template / "checkpoint/state.json").read_bytes(),
        "checkpoint/manifest.json": (template / "checkpoint/manifest.json").read_bytes(),
        "checkpoint/net.bpk": b"",
        "checkpoint/optim.bpk": b"",
    }
    n = 0
    for rel, good in in_run.items():
        for tag in ("devzero", "fifo", "dir", "sparse65m", "binary", "truncated", "empty", "dangling"):
            n += 1
            case = work / "cases" / f"{n:03d}"
            shutil.copytree(template, case, symlinks=True)
            target = case / rel
            if target.is_dir():
                shutil.rmtree(target)
            else:
                target.unlink()
            src = hostile_files(work / "hostile" / f"{n:03d}", target.name, good or b"x" * 64)[tag]
            os.replace(src, target) if not src.is_symlink() else target.symlink_to(os.readlink(src))
            cfg = case / "config.toml"
            if rel != "config.toml":
                cfg.write_text(cfg.read_text().replace("steps = 2000", "steps = 3000"))
            s.run(f"{rel} as {tag}", "run dir", ["train", "--resume", str(case)], names=target.name,
                  timeout=a.train_timeout)
    # Datasets: `lmac protocol check --dataset DIR` with its header or payload replaced.
    good_files = [str(ROOT / "protocols/paper/lbf_8x8-2p-2f-s1-coop/phase0/protocol.json")]
    for rel in ("header.json", "episodes.bin"):
        good = (template / "dataset" / rel).read_bytes()
        for tag in ("devzero", "fifo", "dir", "sparse65m", "binary", "truncated", "empty", "dangling"):
            n += 1
            data = work / "datasets" / f"{n:03d}"
            shutil.copytree(template / "dataset", data, symlinks=True)
            target = data / rel
            target.unlink()
            src = hostile_files(work / "hostile" / f"{n:03d}", rel, good)[tag]
            os.replace(src, target) if not src.is_symlink() else target.symlink_to(os.readlink(src))
            s.run(f"dataset {rel} as {tag}", "dataset", ["protocol", "check", "--env", ENV, "--dataset", str(data),
                                                          *good_files], names=rel)
    # Links planted in a run directory: every write must refuse or replace the link itself.
    planted = {
        "lock": s.victim_file, "metrics.csv": s.victim_file, "metrics.jsonl": s.victim_file,
        "marl_eval.json.tmp": s.victim_file, "best_test.json.tmp": s.victim_file,
        "metrics.csv.tmp": s.victim_file, "checkpoint.old": s.victim_dir, "checkpoint.tmp": s.victim_dir,
        "evaluations": s.victim_dir,
    }
    for rel, victim in planted.items():
        n += 1
        case = work / "cases" / f"{n:03d}"
        shutil.copytree(template, case, symlinks=True)
        p = case / rel
        if p.exists() or p.is_symlink():
            shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
        p.symlink_to(victim)
        (case / "marl_eval.json").unlink(missing_ok=True)  # so the final evaluation runs (and writes)
        cfg = case / "config.toml"
        cfg.write_text(cfg.read_text().replace("steps = 2000", "steps = 3000").replace(
            "final_eval_episodes = 0", "final_eval_episodes = 8").replace("test_episodes = 0", "test_episodes = 8"))
        s.run(f"{rel} -> victim", "planted", ["train", "--resume", str(case), "--allow-changed"],
              names=None, timeout=a.train_timeout)
    # 4. /dev/shm: names lmac must not take for its own, then `lmac clean`.
    shm = pathlib.Path("/dev/shm")
    crafted = [f"lmac-otherapp{os.getpid()}-s0", f"lmac-{os.getpid():012x}-s0", f"lmac-{os.getpid():012x}-s01",
               f"lmac--s0", f"lmac-{'A' * 12}-s0", f"lmac-{os.getpid():012x}-sX"]
    made = []
    for name in crafted:
        p = shm / name
        p.write_bytes(b"\0" * 4096)
        made.append(p)
    fifo = shm / f"lmac-{os.getpid() + 1:012x}-s0"
    os.mkfifo(fifo)
    made.append(fifo)
    s.run("crafted /dev/shm names", "shm", ["clean"], names=None, expect_ok=True, watch=made)
    for p in made:
        p.unlink(missing_ok=True)
    # Planted iceoryx2-looking files are not this test's to make (they would refuse every run of
    # this user until removed); the root directory's checks have their own tests.

    summary = summarize(s.cases)
    summary["seconds"] = round(time.monotonic() - t_start, 1)
    doc = dict(what="lmac's binary against hostile files, planted links and crafted /dev/shm names "
                    "(scripts/hostile_sweep.py); each case in a child with a 16 GiB address-space limit "
                    f"and a {a.timeout:g} s timeout ({a.train_timeout:g} s for cases that may train)",
               summary=summary, cases=s.cases)
    pathlib.Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    pathlib.Path(a.out).write_text(json.dumps(doc, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    shutil.rmtree(work, ignore_errors=True)
    bad = summary["panics"] + summary["hangs"] + summary["touched_outside"] + summary["errors_not_naming_the_file"]
    return 1 if bad else 0


def summarize(cases: list[dict]) -> dict:
    return dict(
        inputs=len(cases),
        panics=sum(c["panicked"] for c in cases),
        hangs=sum(c["hung"] for c in cases),
        slowest_seconds=max(c["seconds"] for c in cases),
        memory_cap_hits=sum(c["memory_cap_hit"] for c in cases),
        touched_outside=sum(bool(c["touched_outside"]) for c in cases),
        errors_not_naming_the_file=sum(c["names_the_file"] is False and c["exit"] != 0 for c in cases),
        refused=sum(not c["ok"] for c in cases),
        used=sum(c["ok"] for c in cases),
    )


if __name__ == "__main__":
    sys.exit(main())
