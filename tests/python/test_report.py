"""lmac report (env-server/lmac_report): rliable's statistics, reading runs, the outputs, bad input.

Every run is a tiny synthetic directory made in tmp_path; bootstrap replicates are kept small."""

import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from lmac_report import stats
from lmac_report.cli import main
from lmac_report.runs import ReportError, load, load_all, merged

ROOT = pathlib.Path(__file__).resolve().parents[2]
FAST = ["--reps", "300", "--curve-reps", "50", "--points", "12"]

# ---------------------------------------------------------------------------------- statistics

# Three tasks with different run counts. Pooled and sorted (11 scores):
# 0, .1, .2, .3, .4, .5, .7, .9, 1, 2, 3; IQM cuts int(11/4) = 2 from each end:
# (.2+.3+.4+.5+.7+.9+1)/7 = 4/7. Task means .4, .75, 3: mean 4.15/3, median .75.
A, B, C = [0.0, 0.2, 0.4, 1.0], [0.1, 0.3, 0.5, 0.7, 0.9, 2.0], [3.0]


def test_point_estimates_by_hand():
    tasks = [np.array(A), np.array(B), np.array(C)]
    assert stats.iqm(tasks) == pytest.approx(4.0 / 7.0)
    assert stats.mean(tasks) == pytest.approx(4.15 / 3.0)
    assert stats.median(tasks) == pytest.approx(0.75)
    # one task: 8 scores, 2 cut from each end
    one = [np.array([1.0, 0.0, 0.2, 0.3, 0.4, 0.5, 0.9, 0.1])]
    assert stats.iqm(one) == pytest.approx(0.35)
    assert stats.mean(one) == pytest.approx(0.425)
    assert stats.median(one) == pytest.approx(0.425)  # rliable: the median of task means
    # fewer than 4 scores: nothing is cut
    assert stats.iqm([np.array([0.0, 0.3, 0.9])]) == pytest.approx(0.4)


def test_iqm_matches_scipy_trim_mean():
    scipy_stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(1)
    for n in range(1, 30):
        x = rng.normal(size=n)
        assert stats.iqm([x]) == pytest.approx(scipy_stats.trim_mean(x, 0.25))


def test_interval_contains_point_and_narrows_with_more_runs():
    data = np.random.default_rng(2).normal(0.5, 0.1, size=200)
    widths = []
    for n in (5, 50, 200):
        for name, f in stats.AGGREGATES.items():
            p, lo, hi = stats.interval([data[:n]], f, 2000, stats.rng_for(0, name))
            assert lo <= p <= hi, (name, n)
            if name == "iqm":
                widths.append(hi - lo)
    assert widths[0] > widths[1] > widths[2]


def test_interval_is_deterministic_and_stratified():
    g = np.random.default_rng(3)
    x = [g.normal(size=7), g.normal(size=9)]
    one = stats.interval(x, stats.iqm, 500, stats.rng_for(7, "qmix"))
    again = stats.interval(x, stats.iqm, 500, stats.rng_for(7, "qmix"))
    other = stats.interval(x, stats.iqm, 500, stats.rng_for(8, "qmix"))
    assert [float(v) for v in one] == [float(v) for v in again]
    assert [float(v) for v in one] != [float(v) for v in other]
    # resampling stays within each task: task means never change when each task is constant
    p, lo, hi = stats.interval([np.zeros(3), np.ones(5)], stats.mean, 500, stats.rng_for(0, "x"))
    assert p == lo == hi == 0.5


def test_performance_profile():
    f = stats.profile(np.array([0.0, 0.5, 1.0]))
    assert f([np.array([0.1, 0.5, 0.9])]).tolist() == pytest.approx([1.0, 1.0 / 3.0, 0.0])
    # averaged over tasks: (1 + 0) / 2 above 0.5
    assert f([np.array([0.8, 0.9]), np.array([0.1, 0.2, 0.3])]).tolist() == pytest.approx([1.0, 0.5, 0.0])


# ------------------------------------------------------------------------------------ run dirs

CONFIG = '[run]\nenv = "{env}"\nalgo = "{algo}"\nsteps = {steps}\n\n[learn]\nseed = {seed}\n'
HEADER = "t_env,episodes,train_return_mean,test_return_mean,test_win_rate,loss\n"


def metrics_csv(tests, interval=1000):
    """A metrics.csv with a training row between test rows; tests = test returns in order."""
    lines = [HEADER]
    for i, r in enumerate(tests):
        lines.append(f"{i * interval},{i * 10},,{r},{r / 2},\n")
        lines.append(f"{i * interval + interval // 2},{i * 10 + 5},0.1,,,0.5\n")
    return "".join(lines)


def seed_dir(d, env="lbf:8x8-2p-2f-s1-coop", algo="qmix", seed=0, tests=(0.0, 0.2, 0.4, 0.6, 0.8, 1.0), steps=5000):
    d.mkdir(parents=True)
    (d / "config.toml").write_text(CONFIG.format(env=env, algo=algo, seed=seed, steps=steps))
    (d / "metrics.csv").write_text(metrics_csv(tests))
    return d


def marl_eval(env_family, task, algo, seed, returns, absolute=None, interval=1000):
    data = {f"step_{i}": {"step_count": i * interval, "return": [r], "win_rate": [r / 2]} for i, r in enumerate(returns)}
    if absolute is not None:
        data["absolute_metrics"] = {"return": absolute, "win_rate": [0.5]}
    return {env_family: {task: {algo: {f"seed_{seed}": data}}}}


def test_seed_dir_from_metrics_csv(tmp_path):
    d = seed_dir(tmp_path / "runs/lbf/qmix/20260101-000000/seed3", seed=3)
    [r] = load(str(d))
    assert (r.env, r.family, r.task, r.label, r.seed) == ("lbf:8x8-2p-2f-s1-coop", "lbf", "8x8-2p-2f-s1-coop", "qmix", "seed_3")
    assert sorted(r.data) == [f"step_{i}" for i in range(6)]
    assert r.data["step_2"] == {"step_count": 2000, "return": [0.4], "win_rate": [0.2]}
    score, source = r.final("return")
    assert (score, source) == (pytest.approx((0.2 + 0.4 + 0.6 + 0.8 + 1.0) / 5), "last5")
    assert not r.unfinished()


def test_seed_dir_from_marl_eval_json(tmp_path):
    d = seed_dir(tmp_path / "exp/runs/lmac-window/seed1", algo="lmac", seed=1, tests=(0.9,) * 6)
    (d / "marl_eval.json").write_text(json.dumps(marl_eval("lbf", "8x8-2p-2f-s1-coop", "lmac", 1, [0.0, 0.5], [0.25, 0.75, 1.0])))
    [r] = load(str(tmp_path / "exp"))
    assert r.label == "lmac-window"  # the experiment's run folder, not run.algo
    assert r.source.endswith("marl_eval.json")  # preferred over metrics.csv
    assert r.final("return") == (pytest.approx(2.0 / 3.0), "absolute")
    assert r.final("win_rate") == (0.5, "absolute")
    assert r.curve("return") == ([0, 1000], [0.0, 0.5])


def test_marl_eval_json_as_lmac_writes_it_and_as_it_did_before(tmp_path):
    """lmac writes which checkpoint the final evaluation used beside absolute_metrics; runs
    written before 2026-12-04 carry it inside (checkpoint "best", t_env), which a report reads past
    (it used to refuse every such run)."""
    for k, where in enumerate(["beside", "inside"]):
        d = seed_dir(tmp_path / f"exp{k}/runs/lmac/seed0", algo="lmac", seed=0)
        doc = marl_eval("lbf", "8x8-2p-2f-s1-coop", "lmac", 0, [0.0, 0.5], [0.25, 0.75])
        seed = doc["lbf"]["8x8-2p-2f-s1-coop"]["lmac"]["seed_0"]
        if where == "beside":
            seed["absolute_metrics_source"] = {"checkpoint": "best", "t_env": 1000}
        else:
            seed["absolute_metrics"].update({"checkpoint": "best", "t_env": 1000})
        (d / "marl_eval.json").write_text(json.dumps(doc))
        [r] = load(str(tmp_path / f"exp{k}"))
        assert r.final("return") == (pytest.approx(0.5), "absolute"), where


def test_flat_copies_and_json_files(tmp_path):
    (tmp_path / "lmac-td_seed2.csv").write_text(metrics_csv([0.1, 0.3]))
    (tmp_path / "lmac-td_seed2.config.toml").write_text(CONFIG.format(env="lbf:x", algo="lmac", seed=2, steps=1000))
    (tmp_path / "comparison_seed0.csv").write_text("not a run\n")  # no .config.toml beside it: ignored
    [r] = load(str(tmp_path))
    assert (r.label, r.seed, r.final("return")[0]) == ("lmac-td", "seed_2", pytest.approx(0.2))
    j = tmp_path / "other.json"
    j.write_text(json.dumps(marl_eval("smac", "3m", "qmix", 0, [1.0, 2.0])))
    [r] = load("renamed=" + str(j))
    assert (r.env, r.label) == ("smac:3m", "renamed")


def test_a_seed_that_has_not_logged_yet_is_skipped_with_a_warning(tmp_path):
    seed_dir(tmp_path / "g/seed0")
    (tmp_path / "g/seed1").mkdir()
    (tmp_path / "g/seed1/config.toml").write_text(CONFIG.format(env="lbf:x", algo="qmix", seed=1, steps=10))
    said = []
    [r] = load(str(tmp_path / "g"), warn=said.append)
    assert r.seed == "seed_0" and said == [f"skipped: {tmp_path / 'g/seed1'}: a run with no metrics.csv yet"]


def test_duplicate_runs_are_an_error(tmp_path):
    seed_dir(tmp_path / "a/seed0")
    seed_dir(tmp_path / "b/seed0")
    with pytest.raises(ReportError, match="two runs of qmix .* LABEL=PATH"):
        load_all([str(tmp_path / "a"), str(tmp_path / "b")])
    runs = load_all([str(tmp_path / "a"), "lr2=" + str(tmp_path / "b")])
    assert sorted(r.label for r in runs) == ["lr2", "qmix"]
    assert set(merged(runs)["lbf"]["8x8-2p-2f-s1-coop"]) == {"qmix", "lr2"}


# ------------------------------------------------------------------------------- the command


def test_report_writes_table_json_and_plots(tmp_path, capsys):
    runs = tmp_path / "runs"
    for s in range(3):
        seed_dir(runs / f"qmix/t/seed{s}", seed=s, tests=[0.1 * i + 0.05 * s for i in range(8)], steps=7000)
        seed_dir(runs / f"maic/t/seed{s}", algo="maic", seed=s, tests=[0.05 * i for i in range(8)], steps=7000)
    seed_dir(runs / "ndq/t/seed0", algo="ndq", tests=[0.1, 0.2], steps=7000)  # unfinished
    assert main([str(runs)] + FAST) == 0
    out = capsys.readouterr().out
    assert "| lbf:8x8-2p-2f-s1-coop | qmix | 3 | 7k | last-5-tests |" in out
    assert "| ndq | 1 | 1k* |" in out and "ndq (1 of 1)" in out
    rep = runs / "report"  # the default: report/ inside the first RUNS directory
    j = json.loads((rep / "report.json").read_text())
    seeds = j["lbf"]["8x8-2p-2f-s1-coop"]
    assert sorted(seeds) == ["maic", "ndq", "qmix"] and sorted(seeds["qmix"]) == ["seed_0", "seed_1", "seed_2"]
    assert seeds["qmix"]["seed_1"]["step_7"] == {"step_count": 7000, "return": [pytest.approx(0.75)], "win_rate": [pytest.approx(0.375)]}
    rows = json.loads((rep / "report_stats.json").read_text())["rows"]
    qmix = next(r for r in rows if r["label"] == "qmix")
    # final scores: last 5 tests of 0.1*i + 0.05*s, i = 3..7: 0.5, 0.55, 0.6
    assert qmix["iqm"] == pytest.approx(0.55) and qmix["mean"] == pytest.approx(0.55)
    assert qmix["iqm_lo"] <= 0.55 <= qmix["iqm_hi"]
    # Three runs are too few for an IQM and a bootstrap CI: the table gives the mean, the sample
    # SD (0.05 over 0.5, 0.55, 0.6) and each run's score.
    assert "| last-5-tests | - | - | 0.550 ± 0.050 (runs: 0.500, 0.550, 0.600) |" in out, out
    assert (rep / "report.md").read_text() in out
    assert (rep / "report.csv").read_text().splitlines()[0].startswith("env,label,tasks,runs")
    for png in ("performance_profile.png", "sample_efficiency.png"):
        assert (rep / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_several_envs_are_strata_and_can_be_normalised(tmp_path, capsys):
    for s in range(2):
        seed_dir(tmp_path / f"lbf/seed{s}", seed=s, tests=[0.5 + 0.1 * s] * 5)
        seed_dir(tmp_path / f"smac/seed{s}", env="smaclite:2s3z", seed=s, tests=[0.0, 10.0 + 10 * s, 10.0 + 10 * s])
    assert main([str(tmp_path), "--out", str(tmp_path / "o"), "--no-plots"] + FAST) == 0
    out = capsys.readouterr().out
    assert "| all (2 envs) | qmix | 4 |" in out and "--normalise min-max" in out
    assert main([str(tmp_path), "--out", str(tmp_path / "n"), "--normalise", "min-max"] + FAST) == 0
    rows = json.loads((tmp_path / "n/report_stats.json").read_text())["rows"]
    allrow = next(r for r in rows if r["env"].startswith("all"))
    # lbf 0.5, 0.6 over [0.5, 0.6] -> 0, 1; smaclite final (10+10)/2... over [0, 20]
    assert all(0.0 <= v <= 1.0 for v in allrow["scores"].values())
    assert allrow["scores"]["lbf:8x8-2p-2f-s1-coop/seed_1"] == pytest.approx(1.0)


def run_cli(*args):
    env = dict(os.environ, PYTHONPATH=str(ROOT / "env-server"))
    return subprocess.run([sys.executable, "-m", "lmac_report", *args, *FAST, "--no-plots"], capture_output=True, text=True, env=env, timeout=60)


@pytest.mark.parametrize("case", ["empty", "no_test_rows", "corrupt_json", "bad_structure", "bad_number", "missing"])
def test_bad_input_names_the_file_without_traceback(tmp_path, case):
    if case == "empty":
        (tmp_path / "nothing").mkdir()
        target, expect = tmp_path / "nothing", "no runs found"
    elif case == "no_test_rows":
        d = seed_dir(tmp_path / "seed0")
        (d / "metrics.csv").write_text(HEADER + "500,5,0.1,,,0.5\n")
        target, expect = d / "metrics.csv", "no test rows"
    elif case == "corrupt_json":
        d = seed_dir(tmp_path / "seed0")
        (d / "marl_eval.json").write_text('{"lbf": {"8x8": ')
        target, expect = d / "marl_eval.json", "not valid JSON"
    elif case == "bad_structure":
        d = seed_dir(tmp_path / "seed0")
        (d / "marl_eval.json").write_text(json.dumps({"lbf": {"8x8": {"qmix": {"seed_0": {"step_0": {"step_count": 0, "return": "high"}}}}}}))
        target, expect = d / "marl_eval.json", "seed_0/step_0/return"
    elif case == "bad_number":
        d = seed_dir(tmp_path / "seed0")
        (d / "metrics.csv").write_text(HEADER + "0,0,,zero,0,\n")
        target, expect = d / "metrics.csv", "'zero' is not a number"
    else:
        target, expect = tmp_path / "absent", "no such file or directory"
    p = run_cli(str(target if case in ("empty", "missing") else tmp_path))
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr
    assert str(target) in p.stderr and expect in p.stderr, p.stderr


def test_skip_bad_reports_the_rest(tmp_path):
    seed_dir(tmp_path / "a/seed0")
    bad = seed_dir(tmp_path / "b/seed1", seed=1)
    (bad / "metrics.csv").write_text(HEADER)
    p = run_cli(str(tmp_path), "--skip-bad")
    assert p.returncode == 0, p.stderr
    assert "skipped:" in p.stderr and str(bad / "metrics.csv") in p.stderr
    assert "| qmix | 1 |" in p.stdout


def test_lmac_report_passes_arguments_output_and_exit_code(tmp_path):
    """`lmac report` (trainer/cli/src/cli/report.rs) runs `python -m lmac_report` with its arguments."""
    found = [p for p in (ROOT / "target/release/lmac", ROOT / "target/debug/lmac") if p.is_file()]
    if not found:
        pytest.skip("no lmac binary built (cargo build --release --bin lmac)")
    lmac = str(max(found, key=lambda p: p.stat().st_mtime))
    env = dict(os.environ, LMAC_ROOT=str(ROOT))
    h = subprocess.run([lmac, "report", "--help"], capture_output=True, text=True, env=env, timeout=60)
    if "usage: lmac report" not in h.stdout:
        pytest.skip(f"{lmac} predates `lmac report`")
    seed_dir(tmp_path / "g/seed0")
    ok = subprocess.run([lmac, "report", str(tmp_path / "g"), "--out", str(tmp_path / "o"), *FAST], capture_output=True, text=True, env=env, timeout=60)
    assert ok.returncode == 0, ok.stderr
    assert "| qmix | 1 |" in ok.stdout and (tmp_path / "o/sample_efficiency.png").is_file()
    bad = subprocess.run([lmac, "report", str(tmp_path / "absent")], capture_output=True, text=True, env=env, timeout=60)
    assert bad.returncode == 2 and "absent: no such file or directory" in bad.stderr and "Traceback" not in bad.stderr


def test_long_plot_titles_wrap_instead_of_running_off_the_figure():
    from lmac_report.titles import fit
    t = fit("pz:mpe2.simple_spread_v3,N=4,team_reward=mean qmix 20261207-003231: mean and std over seeds", 40)
    lines = t.split("\n")
    assert len(lines) > 1 and lines[0] == "pz:mpe2.simple_spread_v3,N=4,team_reward=mean"
    assert all(len(line) <= 40 for line in lines[1:])
    assert fit("short") == "short"
