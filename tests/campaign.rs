//! `lmac campaign` end to end with tiny budgets on LBF: a two-stage grid created and trained in
//! order, interrupted and resumed, its status and time left, a cell stopped at the campaign's
//! time limit and kept as reduced, a failed cell recorded and retried, cells whose settings no
//! longer match the campaign's rewritten or retrained (one that failed at step 0 included), a
//! tree restored from its export (partly trained cells restart), the results page beside
//! reference values,
//! and bad campaign files refused with the file and the field named.

use lmac_e2e::harness::{lmac, wait_for};
use std::path::Path;
use std::process::{Output, Stdio};
use std::time::Duration;

const RUN: &str = r#"set = ["run.envs=4", "run.servers=1", "run.test_interval=1000", "run.test_episodes=2", "run.log_interval=500", "run.checkpoint_interval=500", "run.final_eval_episodes=2"]"#;

fn campaign_file(dir: &Path, head_extra: &str, steps: &str) -> std::path::PathBuf {
    let text = format!(
        r#"[campaign]
title = "tiny grid"
out = "tree"
{RUN}
{head_extra}

[[stage]]
name = "short"
tasks = ["lbf:8x8-2p-2f-s1-coop"]
algos = ["qmix", "vdn"]
seeds = [0, 1]
steps = "{steps}"

[[stage]]
name = "longer"
tasks = ["lbf:8x8-2p-2f-s1-coop"]
algos = ["qmix"]
seeds = [0]
steps = 2500

[[reference]]
task = "lbf:8x8-2p-2f-s1-coop"
source = "values for the test"
metric = "return"
scale = 100
steps = [1500, 2500]
values = {{ qmix = [12, 40], vdn = [30, 50] }}
"#
    );
    let f = dir.join("c.toml");
    std::fs::write(&f, text).unwrap();
    f
}

/// An empty directory of this test process, `<tmp>/<name>-<pid>`.
fn fresh_dir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn campaign(dir: &Path, args: &[&str]) -> Output {
    let mut c = lmac();
    c.arg("campaign").args(args).current_dir(dir).stdin(Stdio::null());
    c.output().unwrap()
}

/// `lmac campaign run c.toml` in `dir`, in the background (to be interrupted).
fn spawn_campaign_run(dir: &Path) -> std::process::Child {
    let mut c = lmac();
    c.args(["campaign", "run", "c.toml"]).current_dir(dir).stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped());
    c.spawn().unwrap()
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

#[test]
fn a_campaign_trains_its_grid_in_order_resumes_and_reports_beside_the_reference() {
    let dir = fresh_dir("lmac-campaign");
    let file = campaign_file(&dir, "", "1500");

    // Status before anything exists says how to start.
    let st = campaign(&dir, &["status", "c.toml"]);
    assert!(!st.status.success() && text(&st).contains("no cell has been created yet"), "{}", text(&st));

    // One cell only: the first in the file's order (stage, seed, task, method).
    let first = campaign(&dir, &["run", "c.toml", "--max-cells", "1"]);
    assert!(first.status.success(), "{}", text(&first));
    assert!(text(&first).contains("5 cells: 0 finished"), "{}", text(&first));
    let st = campaign(&dir, &["status", "c.toml", "--json"]);
    let v: serde_json::Value = serde_json::from_slice(&st.stdout).unwrap();
    let cells = v["cells"].as_array().unwrap();
    let ids: Vec<&str> = cells.iter().map(|c| c["cell"]["id"].as_str().unwrap()).collect();
    assert_eq!(
        ids,
        [
            "short/lbf_8x8-2p-2f-s1-coop/qmix/seed0",
            "short/lbf_8x8-2p-2f-s1-coop/vdn/seed0",
            "short/lbf_8x8-2p-2f-s1-coop/qmix/seed1",
            "short/lbf_8x8-2p-2f-s1-coop/vdn/seed1",
            "longer/lbf_8x8-2p-2f-s1-coop/qmix/seed0",
        ],
        "every cell's first seed before any second, stage by stage"
    );
    assert_eq!(cells[0]["status"]["state"], "finished");
    assert_eq!(cells[1]["status"]["state"], "pending");
    // qmix's speed is known from its first cell: its other cells have a time estimate, vdn's none.
    assert!(cells[2]["eta_s"].as_f64().unwrap() > 0.0 && cells[1]["eta_s"].is_null(), "{cells:?}");
    // Every cell exists with its config before any trains; the tree is an experiment per stage and task.
    for c in cells {
        assert!(dir.join(c["cell"]["dir"].as_str().unwrap()).join("config.toml").exists(), "{c}");
    }
    assert!(dir.join("tree/short/lbf_8x8-2p-2f-s1-coop/experiment.json").exists());

    // Interrupted during the next cell, then rerun: it resumes from its checkpoint.
    let child = spawn_campaign_run(&dir);
    let vdn0 = dir.join("tree/short/lbf_8x8-2p-2f-s1-coop/runs/vdn/seed0");
    let ck = wait_for(Duration::from_secs(240), || vdn0.join("checkpoint/state.json").exists().then_some(()));
    assert!(ck.is_some(), "the second cell wrote a checkpoint");
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let stopped = child.wait_with_output().unwrap();
    assert!(!stopped.status.success(), "an interrupted campaign reports failure");
    let rest = campaign(&dir, &["run", "c.toml"]);
    let t = text(&rest);
    assert!(rest.status.success(), "{t}");
    assert!(t.contains("already finished") || t.contains("resuming from"), "the interrupted cell continued: {t}");
    assert!(t.contains("5 cells: 5 finished"), "{t}");

    // The page: a row per stage, task and method, ours beside the reference at the same steps.
    let page = campaign(&dir, &["report", "c.toml", "--export", "copy", "--page", "fig.md"]);
    assert!(page.status.success(), "{}", text(&page));
    let md = std::fs::read_to_string(dir.join("fig.md")).unwrap();
    assert!(md.contains("Progress when this page was made: 5 cells: 5 finished"), "the tree's progress, not the copy's: {md}");
    let qmix = md.lines().find(|l| l.starts_with("| lbf:8x8-2p-2f-s1-coop | qmix | 2/2")).expect("qmix's short row");
    assert!(qmix.contains("| 0.120 |"), "the reference at 1500 steps, as a fraction: {qmix}");
    assert!(md.contains("## Stage longer: 2500 steps") && md.contains("| 0.400 |"), "{md}");
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join("fig.json")).unwrap()).unwrap();
    assert_eq!(json["rows"].as_array().unwrap().len(), 3);
    assert_eq!(json["rows"][0]["returns"].as_array().unwrap().len(), 2);
    // The export holds the small files only, in the same tree.
    let copied = dir.join("copy/short/lbf_8x8-2p-2f-s1-coop/runs/qmix/seed1");
    assert!(copied.join("metrics.csv").exists() && copied.join("config.toml").exists() && !copied.join("checkpoint").exists());

    // Settings changed under existing cells are refused, naming the stage.
    campaign_file(&dir, "", "1600");
    let changed = campaign(&dir, &["run", "c.toml"]);
    assert!(!changed.status.success() && text(&changed).contains("stage short"), "{}", text(&changed));
    drop(file);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_cell_over_the_time_limit_is_kept_as_reduced_and_said_so() {
    let dir = fresh_dir("lmac-campaign-limit");
    // 6 seconds for a cell of 200k steps: it stops at its last checkpoint.
    campaign_file(&dir, "max_cell_hours = 0.0017", "200k");
    let r = campaign(&dir, &["run", "c.toml", "--max-cells", "1"]);
    let t = text(&r);
    assert!(r.status.success(), "{t}");
    assert!(t.contains("reduced: still training at the campaign's limit"), "{t}");
    let cell = dir.join("tree/short/lbf_8x8-2p-2f-s1-coop/runs/qmix/seed0");
    let red: serde_json::Value = serde_json::from_slice(&std::fs::read(cell.join("reduced.json")).unwrap()).unwrap();
    let reached = red["steps"].as_u64().unwrap();
    assert!(reached > 0 && reached < 200_000 && red["planned_steps"] == 200_000, "{red}");
    let st = text(&campaign(&dir, &["status", "c.toml"]));
    assert!(st.contains(&format!("REDUCED: {reached} of 200000 steps")), "{st}");
    // Its final evaluation ran on what it reached, and the page names the reduction.
    assert!(cell.join("marl_eval.json").exists());
    let md = text(&campaign(&dir, &["report", "c.toml"]));
    assert!(md.contains(&format!("seed 0 reduced to {reached} of 200000 steps")), "{md}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_failed_cell_is_recorded_said_so_and_retried_by_the_next_run() {
    let dir = fresh_dir("lmac-campaign-failed");
    campaign_file(&dir, "", "1500");
    // Env servers that cannot start (a Python that does not exist): the cell fails, the run goes
    // on to the next cell and ends in failure, and the tree records why.
    let mut c = lmac();
    c.args(["campaign", "run", "c.toml", "--max-cells", "1"]).current_dir(&dir).stdin(Stdio::null());
    let broken = c.env("LMAC_PYTHON", dir.join("no-such-python")).output().unwrap();
    let t = text(&broken);
    assert!(!broken.status.success() && t.contains("1 cells failed (rerun to retry them)"), "{t}");
    let cell = dir.join("tree/short/lbf_8x8-2p-2f-s1-coop/runs/qmix/seed0");
    let rec: serde_json::Value = serde_json::from_slice(&std::fs::read(cell.join("failed.json")).unwrap()).unwrap();
    assert!(rec["error"].as_str().unwrap().contains("no-such-python"), "the error names the cause: {rec}");
    let st = text(&campaign(&dir, &["status", "c.toml"]));
    assert!(st.contains("FAILED at 0 steps (the next run retries it)") && st.contains("1 failed"), "{st}");
    let md = text(&campaign(&dir, &["report", "c.toml"]));
    assert!(md.contains("seed 0 failed: ") && md.contains("no-such-python"), "the page says which seed failed and why: {md}");
    // Retried with a working Python: trained, and the record is gone.
    let fixed = campaign(&dir, &["run", "c.toml", "--max-cells", "1"]);
    assert!(fixed.status.success(), "{}", text(&fixed));
    assert!(!cell.join("failed.json").exists());
    let st = text(&campaign(&dir, &["status", "c.toml"]));
    assert!(st.contains("1 finished") && st.contains("0 failed"), "{st}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A cell whose start failed before its first step holds a checkpoint of step 0; when the
/// campaign's settings for it change, the next run writes its config again and trains it from
/// scratch (the trainer would refuse to resume that checkpoint under the new settings).
#[test]
fn a_cell_that_failed_at_step_0_trains_under_changed_settings() {
    let dir = fresh_dir("lmac-campaign-step0");
    campaign_file(&dir, "", "1500");
    assert!(campaign(&dir, &["run", "c.toml", "--max-cells", "0"]).status.success());
    let cell = dir.join("tree/short/lbf_8x8-2p-2f-s1-coop/runs/qmix/seed0");
    // The settings the start ran under, unlike the campaign's.
    let cfg = cell.join("config.toml");
    let kept = std::fs::read_to_string(&cfg).unwrap();
    let lr = kept.lines().find(|l| l.starts_with("lr = ")).expect("learn.lr is written").to_string();
    std::fs::write(&cfg, kept.replace(&lr, "lr = 0.00123")).unwrap();
    // An env server that dies before the first episode: the run fails at step 0 with a checkpoint.
    let python = dir.join("dying-python");
    std::fs::write(&python, "#!/bin/sh\nsleep 3\nexit 1\n").unwrap();
    std::fs::set_permissions(&python, std::os::unix::fs::PermissionsExt::from_mode(0o755)).unwrap();
    let mut c = lmac();
    c.arg("train").arg("--resume").arg(&cell).stdin(Stdio::null()).env("LMAC_PYTHON", &python);
    let failed = c.output().unwrap();
    assert!(!failed.status.success(), "{}", text(&failed));
    assert!(cell.join("checkpoint").exists(), "a failed start leaves a checkpoint of step 0: {}", text(&failed));

    let next = campaign(&dir, &["run", "c.toml", "--max-cells", "1"]);
    let t = text(&next);
    assert!(next.status.success(), "{t}");
    assert!(t.contains("qmix/seed0 has not trained; its config is written again"), "{t}");
    assert!(std::fs::read_to_string(&cfg).unwrap().contains(&lr));
    let st = text(&campaign(&dir, &["status", "c.toml"]));
    assert!(st.contains("1 finished"), "{st}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A tree restored from its export on another machine (small files only, no checkpoints): its
/// finished cells stay finished, a partly trained one cannot resume, so it is set aside under
/// `superseded/` and trains from the start.
#[test]
fn a_tree_restored_from_its_export_keeps_finished_cells_and_restarts_partial_ones() {
    let dir = fresh_dir("lmac-campaign-restored");
    campaign_file(&dir, "", "6000");
    assert!(campaign(&dir, &["run", "c.toml", "--max-cells", "1"]).status.success());
    // The next cell interrupted once it has a checkpoint past step 0 (a run interrupted keeps
    // the metrics up to its last checkpoint).
    let child = spawn_campaign_run(&dir);
    let vdn0 = dir.join("tree/short/lbf_8x8-2p-2f-s1-coop/runs/vdn/seed0");
    let logged = || {
        let t = std::fs::read_to_string(vdn0.join("metrics.csv")).ok()?;
        let t_env: u64 = t.lines().last()?.split(',').next()?.parse().ok()?;
        (t_env >= 1000).then_some(())
    };
    let ok = wait_for(Duration::from_secs(240), logged);
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let stopped = child.wait_with_output().unwrap();
    assert!(ok.is_some(), "the second cell logged steps: {}", text(&stopped));
    assert!(campaign(&dir, &["report", "c.toml", "--export", "copy"]).status.success());

    // The copy as the tree on a new machine.
    let st = text(&campaign(&dir, &["status", "c.toml", "--out", "copy"]));
    assert!(st.contains("1 finished, 0 reduced, 1 partly trained"), "{st}");
    let run = campaign(&dir, &["run", "c.toml", "--out", "copy", "--max-cells", "1"]);
    let t = text(&run);
    assert!(run.status.success(), "{t}");
    assert!(t.contains("vdn/seed0 trained") && t.contains("but has no checkpoint to resume from"), "{t}");
    let st = text(&campaign(&dir, &["status", "c.toml", "--out", "copy"]));
    assert!(st.contains("2 finished"), "the finished cell kept, the partial one trained from the start: {st}");
    let set_aside = std::fs::read_dir(dir.join("copy/superseded")).unwrap().next().unwrap().unwrap().path();
    assert!(set_aside.join("short/lbf_8x8-2p-2f-s1-coop/vdn/seed0/metrics.csv").exists(), "its first steps are kept");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A kept config the campaign would no longer write (as when a preset's meaning changes): an
/// untrained cell's is written again, a trained cell is said to differ and, when asked, moved
/// whole under `superseded/` and trained again.
#[test]
fn cells_whose_settings_changed_are_rewritten_or_said_so_and_retrained_when_asked() {
    let dir = fresh_dir("lmac-campaign-changed");
    campaign_file(&dir, "", "1500");
    assert!(campaign(&dir, &["run", "c.toml", "--max-cells", "1"]).status.success());
    let runs = dir.join("tree/short/lbf_8x8-2p-2f-s1-coop/runs");
    let edit = |cell: &str| {
        let p = runs.join(cell).join("config.toml");
        let text = std::fs::read_to_string(&p).unwrap();
        let lr = text.lines().find(|l| l.starts_with("lr = ")).expect("learn.lr is written").to_string();
        std::fs::write(&p, text.replace(&lr, "lr = 0.00123")).unwrap();
        lr.trim_start_matches("lr = ").to_string()
    };
    let lr = edit("qmix/seed0");
    edit("vdn/seed0");
    let st = text(&campaign(&dir, &["status", "c.toml"]));
    let want = format!("learn.lr: 0.00123 -> {lr}");
    assert!(st.contains(&format!("TRAINED WITH OTHER SETTINGS than the campaign's now: {want}")), "{st}");
    assert!(st.contains(&format!("the next run writes its config again: {want}")), "{st}");
    assert!(st.contains("1 cells trained with settings the campaign no longer resolves to"), "{st}");
    let md = text(&campaign(&dir, &["report", "c.toml"]));
    assert!(md.contains(&format!("seed 0 trained with settings the campaign no longer resolves to: {want}")), "{md}");

    // The next run writes the untrained cell's config again and trains it; the trained one is kept.
    let next = campaign(&dir, &["run", "c.toml", "--max-cells", "1"]);
    let t = text(&next);
    assert!(next.status.success(), "{t}");
    assert!(t.contains("vdn/seed0 has not trained; its config is written again"), "{t}");
    assert!(t.contains("qmix/seed0 trained with settings the campaign no longer resolves to"), "{t}");
    assert!(std::fs::read_to_string(runs.join("vdn/seed0/config.toml")).unwrap().contains(&format!("lr = {lr}")));
    assert!(runs.join("qmix/seed0/metrics.csv").exists());

    // Asked to, the trained cell moves whole under superseded/ (here without training yet): an
    // export then shows no results for it, where an earlier export did.
    assert!(campaign(&dir, &["report", "c.toml", "--export", "copy"]).status.success());
    let copied = dir.join("copy/short/lbf_8x8-2p-2f-s1-coop/runs/qmix/seed0");
    assert!(copied.join("metrics.csv").exists());
    let moved_only = campaign(&dir, &["run", "c.toml", "--max-cells", "0", "--retrain-changed"]);
    assert!(moved_only.status.success(), "{}", text(&moved_only));
    assert!(campaign(&dir, &["report", "c.toml", "--export", "copy"]).status.success());
    assert!(!copied.join("metrics.csv").exists() && copied.join("config.toml").exists(), "the copy follows the tree");
    let onto_itself = campaign(&dir, &["report", "c.toml", "--export", "tree"]);
    assert!(!onto_itself.status.success() && text(&onto_itself).contains("that is the results tree itself"), "{}", text(&onto_itself));
    // It trains again with today's settings.
    let again = campaign(&dir, &["run", "c.toml", "--max-cells", "1", "--retrain-changed"]);
    let t = text(&again);
    assert!(again.status.success(), "{t}");
    let moved: Vec<_> = std::fs::read_dir(dir.join("tree/superseded")).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(moved.len(), 1, "{moved:?}");
    let old = moved[0].join("short/lbf_8x8-2p-2f-s1-coop/qmix/seed0");
    assert!(old.join("metrics.csv").exists() && old.join("config.toml").exists(), "the old run is kept whole");
    assert!(std::fs::read_to_string(runs.join("qmix/seed0/config.toml")).unwrap().contains(&format!("lr = {lr}")));
    let st = text(&campaign(&dir, &["status", "c.toml"]));
    assert!(st.contains("2 finished") && !st.contains("OTHER SETTINGS"), "{st}");

    // A stage added to a running campaign: its cells are not created yet, and status still
    // says they are pending and how long they will take.
    let f = dir.join("c.toml");
    let added = "\n[[stage]]\nname = \"added\"\ntasks = [\"lbf:8x8-2p-2f-s1-coop\"]\nalgos = [\"qmix\"]\nseeds = [0]\nsteps = 1000\n";
    std::fs::write(&f, std::fs::read_to_string(&f).unwrap() + added).unwrap();
    let st = campaign(&dir, &["status", "c.toml", "--json"]);
    assert!(st.status.success(), "{}", text(&st));
    let v: serde_json::Value = serde_json::from_slice(&st.stdout).unwrap();
    let new = v["cells"].as_array().unwrap().iter().find(|c| c["cell"]["stage"] == "added").expect("the added stage's cell");
    assert_eq!(new["status"]["state"], "pending");
    assert!(new["eta_s"].as_f64().unwrap() > 0.0, "qmix's speed gives it an estimate: {new}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_campaign_files_are_refused_naming_the_file_and_the_field() {
    let dir = fresh_dir("lmac-campaign-bad");
    let head = "[campaign]\ntitle = \"t\"\nout = \"tree\"\n";
    let stage = |body: &str| format!("{head}\n[[stage]]\nname = \"s\"\ntasks = [\"lbf:8x8-2p-2f-s1-coop\"]\nseeds = [0]\n{body}\n");
    for (body, says) in [
        (stage("algos = [\"qmix\"]\nsteps = \"1k\"\nspeed = 3"), "unknown field `speed`"),
        (stage("algos = [\"qmixx\"]\nsteps = \"1k\""), "unknown method \"qmixx\""),
        (stage("algos = [\"lmac\"]\nsteps = \"1k\""), "lmac needs a design"),
        (stage("algos = [\"qmix\"]\nsteps = \"lots\""), "is not a step count"),
        (stage("algos = []\nsteps = \"1k\""), "algos is empty"),
        (format!("{head}max_cell_hours = -1\n{}", stage("algos = [\"qmix\"]\nsteps = \"1k\"").trim_start_matches(head)), "max_cell_hours"),
        (format!("{head}preset = \"fast\"\n{}", stage("algos = [\"qmix\"]\nsteps = \"1k\"").trim_start_matches(head)), "not a preset"),
        ("[campaign\n".to_string(), "c.toml"),
    ] {
        std::fs::write(dir.join("c.toml"), &body).unwrap();
        let o = campaign(&dir, &["run", "c.toml"]);
        let t = text(&o);
        assert!(!o.status.success() && t.contains("c.toml") && t.contains(says), "{says}: {t}");
        assert!(!t.contains("panicked"), "{t}");
        assert!(!dir.join("tree/s").exists(), "nothing is created from a bad file");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
