//! `lmac experiment`: the paper's Algorithm 1 end to end. One protocol design (shared by every
//! seed), then LMAC and the baselines trained with the same settings for every seed, then a
//! comparison table and the curves. Rerunning the same command continues where it stopped: the
//! design is reused once written, finished seeds are skipped, unfinished ones resume from their
//! checkpoints.

use super::design::{design_dir, DesignArgs, DEFAULT_PRETRAIN_STEPS};
use super::parse_steps;
use anyhow::{bail, Context, Result};
use clap::Args;
use lmac_run::safe_fs;
use lmac_run::stats::{mean, sample_sd};
use lmac_run::train::{read_metrics, TrainConfig};
use lmac_run::workflow::{interrupt_flag, plot, train_dirs_holding};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The runs resolved while their configs were written, by run directory.
pub(crate) type Resolutions = std::collections::HashMap<PathBuf, lmac_run::train::ResolvedRun>;

#[derive(Args)]
pub(crate) struct ExperimentArgs {
    /// Environment, e.g. lbf:8x8-2p-2f-s1-coop.
    #[arg(long, default_value = "lbf:8x8-2p-2f-s1-coop")]
    env: String,
    /// Seeds, comma separated (one design for all of them).
    #[arg(long, default_value = "0,1,2", value_delimiter = ',')]
    seeds: Vec<u64>,
    /// Env steps per training run, e.g. 1M, 200k.
    #[arg(long, default_value = "1M", value_parser = parse_steps)]
    steps: u64,
    /// Algorithms to compare, comma separated (`lmac train --help` lists them); `--algos ''`
    /// trains only the --ablations and --variant rows.
    #[arg(long, default_value = "lmac,qmix,fullcomm,qmix-state", value_delimiter = ',')]
    algos: Vec<String>,
    /// Also train Table 1(a)'s rows: k = 0 and k = 1 (the design's first phases), LMAC without
    /// the consistency loss and without the meta loss. A design made here then keeps all three
    /// phases, so the k rows are prefixes of it, as in the paper.
    #[arg(long)]
    ablations: bool,
    /// An extra row: LABEL=ALGO with settings after commas, e.g.
    /// --variant lmac-window=lmac,method.encoder="window" (repeatable).
    #[arg(long = "variant", value_name = "LABEL=ALGO[,KEY=VALUE...]")]
    variants: Vec<String>,
    /// Protocol designer: offline, or an LLM as in `lmac design --llm`.
    #[arg(long, default_value = "offline")]
    llm: String,
    /// Env steps of the run that collects the design's dataset (as `lmac design --pretrain-steps`).
    #[arg(long, default_value = DEFAULT_PRETRAIN_STEPS, value_parser = parse_steps)]
    design_steps: u64,
    /// Episodes in the design's dataset.
    #[arg(long, default_value_t = 1000)]
    dataset_episodes: usize,
    /// Discriminator updates per design phase (default: the designer's).
    #[arg(long)]
    disc_updates: Option<usize>,
    /// Keep every design phase, as the paper does (as `lmac design --keep-all-phases`; by
    /// default a phase whose messages add nothing to the earlier phases' is dropped, and the
    /// design's log and summary.json say which and why)
    #[arg(long)]
    keep_all_phases: bool,
    /// The default (drop the phases that add nothing); accepted so older commands still run
    #[arg(long, hide = true, conflicts_with = "keep_all_phases")]
    drop_unhelpful_phases: bool,
    /// Use this design directory instead of designing one; `paper`: the LMAC authors' design
    /// for --env shipped in protocols/paper/ (an error naming the env when none is shipped).
    #[arg(long)]
    design: Option<PathBuf>,
    /// Settings for every training run: --set learn.lr=0.001 --set run.envs=8
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// A preset for every training run (as `lmac train --preset`).
    #[arg(long, value_parser = super::train::preset_names())]
    preset: Option<String>,
    /// Test return a run must reach for the "steps to threshold" columns (default: 80% of the
    /// way from the runs' first test return, the untrained policy's, to the best row's
    /// last-5-tests return; so also for negative returns).
    #[arg(long)]
    threshold: Option<f64>,
    /// The experiment's directory (default: experiments/<env>).
    #[arg(long)]
    out: Option<PathBuf>,
}

/// What an experiment directory was made for: a rerun must ask for the same.
#[derive(Serialize, Deserialize, PartialEq, Debug)]
pub(crate) struct ExperimentSpec {
    pub env: String,
    pub steps: u64,
    pub set: Vec<String>,
    pub preset: Option<String>,
}

/// One row of the comparison: an algorithm (or an ablation) over its seeds.
#[derive(Serialize, Clone, Debug)]
pub(crate) struct Row {
    pub label: String,
    pub algo: String,
    pub seeds: usize,
    pub final_return_mean: f64,
    pub final_return_std: f64,
    /// Each seed's last-5-tests return, in seed order (with fewer than 5 seeds the spread is
    /// read from these, not from an interval).
    pub final_returns: Vec<f64>,
    /// Each seed's last-5-tests win rate (0 where the env reports none), in seed order.
    pub final_win_rates: Vec<f64>,
    pub final_win_rate_mean: Option<f64>,
    pub final_win_rate_std: Option<f64>,
    /// The best checkpoint's greedy evaluation (`evaluations/final.result.json`, what `lmac
    /// report` scores), mean and std over the seeds; None unless every seed has one.
    pub best_eval_return_mean: Option<f64>,
    pub best_eval_return_std: Option<f64>,
    /// Seeds that reached the threshold, and their mean env steps and wall seconds to it.
    pub reached: usize,
    pub steps_to_threshold: Option<f64>,
    pub wall_s_to_threshold: Option<f64>,
    pub wall_s_total: f64,
    /// The learning schedule the seeds were trained with (from their config.toml; distinct
    /// schedules joined with " / ").
    pub schedule: String,
}

/// The rows to train: (label, algo, extra overrides).
/// `a,b="x,y",c` -> [`a`, `b="x,y"`, `c`]: commas inside double quotes (an env name with its
/// options, say) do not split.
fn split_outside_quotes(s: &str) -> Vec<String> {
    let (mut out, mut cur, mut quoted) = (Vec::new(), String::new(), false);
    for c in s.chars() {
        match c {
            '"' => {
                quoted = !quoted;
                cur.push(c);
            }
            ',' if !quoted => out.push(std::mem::take(&mut cur)),
            _ => cur.push(c),
        }
    }
    out.push(cur);
    out
}

fn variants(a: &ExperimentArgs) -> Result<Vec<(String, String, Vec<String>)>> {
    let mut v: Vec<(String, String, Vec<String>)> =
        a.algos.iter().filter(|al| !al.is_empty()).map(|al| (al.clone(), al.clone(), Vec::new())).collect();
    if a.ablations {
        for (label, o) in [
            ("lmac-k0", "run.design_k=0"),
            ("lmac-k1", "run.design_k=1"),
            ("lmac-no-cons", "method.lambda_cons=0.0"),
            ("lmac-no-meta", "method.lambda_meta=0.0"),
        ] {
            v.push((label.into(), "lmac".into(), vec![o.into()]));
        }
    }
    for spec in &a.variants {
        let (label, rest) = spec.split_once('=').with_context(|| format!("--variant {spec:?}: use LABEL=ALGO[,KEY=VALUE...]"))?;
        let mut parts = split_outside_quotes(rest).into_iter();
        let algo = parts.next().unwrap_or_default();
        if label.is_empty() || label.contains(['/', '.']) || algo.is_empty() {
            bail!("--variant {spec:?}: use LABEL=ALGO[,KEY=VALUE...] with a label that is a plain name");
        }
        v.push((label.into(), algo, parts.collect()));
    }
    if v.is_empty() {
        bail!("nothing to train: --algos is empty and there are no --ablations or --variant rows");
    }
    let mut labels: Vec<&str> = v.iter().map(|x| x.0.as_str()).collect();
    labels.sort_unstable();
    if let Some(w) = labels.windows(2).find(|w| w[0] == w[1]) {
        bail!("two rows are called {:?}", w[0]);
    }
    Ok(v)
}

pub(crate) fn experiment(a: ExperimentArgs) -> Result<i32> {
    let rows_to_train = variants(&a)?;
    let interrupted = interrupt_flag();
    let dir = a.out.clone().unwrap_or_else(|| PathBuf::from("experiments").join(lmac_run::run_dir::env_dir_name(&a.env)));
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let _lock = lmac_run::run_dir::lock(&dir)?;
    let spec = ExperimentSpec { env: a.env.clone(), steps: a.steps, set: a.set.clone(), preset: a.preset.clone() };
    claim_dir(&dir, &spec)?;

    // 1. The protocol design, once.
    let needs_design = rows_to_train.iter().any(|(_, algo, _)| algo == "lmac");
    let design = match (&a.design, needs_design) {
        (Some(d), _) => Some(design_protocol(d, &a.env)?),
        (None, false) => None,
        (None, true) => Some(shared_design(&a, &dir, interrupted.clone())?.display().to_string()),
    };

    // 2. Every variant and seed, with the same settings.
    let mut resolved = Resolutions::new();
    let groups = prepare_runs(&dir, &spec, design.as_deref(), &rows_to_train, &a.seeds, &mut resolved)?;
    // Seed by seed, so an interrupted experiment has every variant of its first seeds.
    let all: Vec<PathBuf> = (0..a.seeds.len()).flat_map(|k| groups.iter().map(move |g| g.2[k].clone())).collect();
    eprintln!("lmac: experiment in {}: {} runs ({} variants x {} seeds)", dir.display(), all.len(), groups.len(), a.seeds.len());
    let per_dir: Vec<_> = all.iter().map(|d| resolved.get(d)).collect();
    train_dirs_holding(&all, Vec::new(), &per_dir, false, interrupted)?;

    // 3. The table and the curves.
    let mut rows = Vec::new();
    for (label, algo, dirs) in &groups {
        rows.push(summarize(label, algo, dirs)?);
    }
    // 80% of the way from where the runs start to the best row: a threshold at or below the
    // start would be "reached" at the first test, so then there is none.
    let best = rows.iter().map(|r| r.final_return_mean).fold(f64::MIN, f64::max);
    let start = first_test_return(&groups.iter().flat_map(|g| g.2.iter().cloned()).collect::<Vec<_>>())?;
    let threshold = a.threshold.unwrap_or(start + 0.8 * (best - start));
    if threshold > start {
        for (row, (_, _, dirs)) in rows.iter_mut().zip(&groups) {
            reach(row, dirs, threshold)?;
        }
    }
    let table = render(&a.env, &rows, threshold);
    std::fs::write(dir.join("comparison.md"), &table)?;
    std::fs::write(
        dir.join("comparison.json"),
        serde_json::to_string_pretty(
            &serde_json::json!({"env": a.env, "steps": a.steps, "threshold": threshold, "design": design, "rows": rows}),
        )?,
    )?;
    let mut csv = String::from("label,algo,seeds,final_return_mean,final_return_std,final_win_rate_mean,final_win_rate_std,best_eval_return_mean,best_eval_return_std,reached,steps_to_threshold,wall_s_to_threshold,wall_s_total,schedule\n");
    let o = |v: Option<f64>| v.map(|x| format!("{x:.4}")).unwrap_or_default();
    for r in &rows {
        csv.push_str(&format!(
            "{},{},{},{:.4},{:.4},{},{},{},{},{},{},{},{:.1},\"{}\"\n",
            r.label,
            r.algo,
            r.seeds,
            r.final_return_mean,
            r.final_return_std,
            o(r.final_win_rate_mean),
            o(r.final_win_rate_std),
            o(r.best_eval_return_mean),
            o(r.best_eval_return_std),
            r.reached,
            o(r.steps_to_threshold),
            o(r.wall_s_to_threshold),
            r.wall_s_total,
            r.schedule
        ));
    }
    std::fs::write(dir.join("comparison.csv"), csv)?;
    // The curves and, with the k ablations, the phase plot.
    plot("plot_experiment", &dir);
    println!("{table}");
    println!("written: {}/comparison.{{md,csv,json}} and the plots", dir.display());
    Ok(0)
}

/// Take `dir` for an experiment made for `spec`: a directory made for other settings is refused.
pub(crate) fn claim_dir(dir: &Path, spec: &ExperimentSpec) -> Result<()> {
    let spec_path = dir.join("experiment.json");
    if spec_path.exists() {
        let old: ExperimentSpec = serde_json::from_slice(&safe_fs::read_capped(&spec_path, safe_fs::TEXT_CAP)?)
            .with_context(|| format!("reading {}", spec_path.display()))?;
        if &old != spec {
            bail!("{} was made for {old:?}; this command asks for {spec:?}: give another --out", dir.display());
        }
    } else {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        std::fs::write(&spec_path, serde_json::to_string_pretty(spec)?)?;
    }
    Ok(())
}

/// `run.protocol` for a design given by the user: `paper` stays named (each run finds the
/// authors' design for its env in the repository, and its config.toml carries no machine's
/// path), a design directory goes by its absolute path.
pub(crate) fn design_protocol(design: &Path, env: &str) -> Result<String> {
    if design.as_os_str() == "paper" {
        lmac_run::train::resolve_paper_spec("paper", env).context("--design paper")?;
        return Ok("paper".into());
    }
    Ok(std::fs::canonicalize(design).with_context(|| format!("--design {}", design.display()))?.display().to_string())
}

/// The seed directories of an experiment's rows under `dir/runs/<label>/seed<k>`, each with its
/// resolved `config.toml` written when missing (an existing one is kept: that is how a rerun
/// resumes). `protocol` is `run.protocol` for the LMAC rows. Each config written is resolved
/// once, and its resolution kept in `resolved` by run directory for training it.
pub(crate) fn prepare_runs(
    dir: &Path,
    spec: &ExperimentSpec,
    protocol: Option<&str>,
    rows: &[(String, String, Vec<String>)],
    seeds: &[u64],
    resolved: &mut Resolutions,
) -> Result<Vec<(String, String, Vec<PathBuf>)>> {
    let mut groups = Vec::new();
    for (label, algo, extra) in rows {
        let mut dirs = Vec::new();
        for &seed in seeds {
            let d = dir.join("runs").join(label).join(format!("seed{seed}"));
            if !d.join("config.toml").exists() {
                let o = run_overrides(spec, protocol, label, algo, extra, seed)?;
                let (cfg, run) = TrainConfig::resolve_with_run(None, &o).with_context(|| format!("the {label} runs"))?;
                std::fs::create_dir_all(&d)?;
                // Protocol copies left by a creation interrupted before its config.toml.
                let copies = d.join("protocol");
                if copies.symlink_metadata().is_ok_and(|m| m.is_dir()) {
                    std::fs::remove_dir_all(&copies).with_context(|| format!("clearing {}", copies.display()))?;
                }
                cfg.save_new_run(&d)?;
                resolved.insert(d.clone(), run);
            }
            dirs.push(d);
        }
        groups.push((label.clone(), algo.clone(), dirs));
    }
    Ok(groups)
}

/// The overrides that resolve one seed's config of an experiment's row: the preset, the
/// experiment's sets, the env, method, steps and seed, the design for LMAC, the row's own sets.
pub(crate) fn run_overrides(
    spec: &ExperimentSpec,
    protocol: Option<&str>,
    label: &str,
    algo: &str,
    extra: &[String],
    seed: u64,
) -> Result<Vec<String>> {
    let mut o = lmac_run::train::preset_then(spec.preset.as_deref(), Some(algo), &spec.set)?;
    o.push(format!("run.env={:?}", spec.env));
    o.push(format!("run.algo={algo:?}"));
    o.push(format!("run.steps={}", spec.steps));
    o.push(format!("learn.seed={seed}"));
    if algo == "lmac" {
        let p = protocol.with_context(|| format!("the {label} runs need a design"))?;
        o.push(format!("run.protocol={p:?}"));
    }
    o.extend(extra.iter().cloned());
    Ok(o)
}

/// The experiment's design: reused when it already finished, else designed into `<dir>/design`.
fn shared_design(a: &ExperimentArgs, dir: &Path, interrupted: std::sync::Arc<std::sync::atomic::AtomicBool>) -> Result<PathBuf> {
    let note = dir.join("design.txt");
    if let Ok(p) = std::fs::read_to_string(&note) {
        let p = PathBuf::from(p.trim());
        if p.join("phase0").join("protocol.json").exists() {
            eprintln!("lmac: experiment: reusing the design in {}", p.display());
            return Ok(p);
        }
    }
    let mut d = DesignArgs::defaults(&a.env, dir.join("design"));
    d.llm = a.llm.clone();
    d.pretrain_steps = a.design_steps;
    d.dataset_episodes = a.dataset_episodes;
    d.disc_updates = a.disc_updates;
    // The k = 0, 1 rows train the design's first phases: all three are kept for them.
    d.keep_all_phases = a.keep_all_phases || a.ablations;
    d.seed = a.seeds.first().copied().unwrap_or(0);
    let p = std::fs::canonicalize(design_dir(&d, interrupted)?)?;
    std::fs::write(&note, p.display().to_string())?;
    Ok(p)
}

/// The last few test phases of a run average into its final figure (one phase is only
/// run.test_episodes episodes): the rule of `env-server/lmac_report/final.py`, which every report
/// and plot uses.
const FINAL_TESTS: usize = 5;

/// Mean and sample standard deviation over seeds.
fn mean_std(v: &[f64]) -> (f64, f64) {
    (mean(v), sample_sd(v))
}

pub(crate) fn summarize(label: &str, algo: &str, dirs: &[PathBuf]) -> Result<Row> {
    let (mut ret, mut win, mut wall) = (Vec::new(), Vec::new(), Vec::new());
    let mut schedules: Vec<String> = Vec::new();
    for d in dirs {
        let s = schedule(&TrainConfig::load(d)?);
        if !schedules.contains(&s) {
            schedules.push(s);
        }
        let rows = read_metrics(d)?;
        let tests: Vec<_> = rows.iter().filter(|r| r.test_return_mean.is_some()).collect();
        if tests.is_empty() {
            bail!("{}: no test phase was logged", d.display());
        }
        let last = &tests[tests.len().saturating_sub(FINAL_TESTS)..];
        ret.push(last.iter().map(|r| r.test_return_mean.unwrap_or(0.0)).sum::<f64>() / last.len() as f64);
        win.push(last.iter().map(|r| r.test_win_rate.unwrap_or(0.0)).sum::<f64>() / last.len() as f64);
        wall.push(rows.last().map_or(0.0, |r| r.wall_s));
    }
    let (rm, rs) = mean_std(&ret);
    let (wm, ws) = mean_std(&win);
    let has_wins = win.iter().any(|&w| w > 0.0);
    let evals: Vec<f64> = dirs.iter().filter_map(|d| best_eval_return(d)).collect();
    let (em, es) =
        if evals.len() == dirs.len() && !evals.is_empty() { (Some(mean(&evals)), Some(sample_sd(&evals))) } else { (None, None) };
    Ok(Row {
        label: label.into(),
        algo: algo.into(),
        seeds: dirs.len(),
        final_return_mean: rm,
        final_return_std: rs,
        final_returns: ret.clone(),
        final_win_rates: win.clone(),
        final_win_rate_mean: has_wins.then_some(wm),
        final_win_rate_std: has_wins.then_some(ws),
        best_eval_return_mean: em,
        best_eval_return_std: es,
        reached: 0,
        steps_to_threshold: None,
        wall_s_to_threshold: None,
        wall_s_total: mean(&wall),
        schedule: schedules.join(" / "),
    })
}

/// A run's learning schedule in words: updates per collected episode, batch, target copies.
fn schedule(cfg: &TrainConfig) -> String {
    let per_episode = cfg.run.updates_per_episode;
    format!(
        "{per_episode} update{} per episode, batch {}, target copy every {} episodes",
        if per_episode == 1.0 { "" } else { "s" },
        cfg.learn.batch_size,
        cfg.learn.target_update_interval_episodes
    )
}

/// The best checkpoint's greedy evaluation return of a run, when it has one.
fn best_eval_return(d: &Path) -> Option<f64> {
    let bytes = safe_fs::read_capped(&d.join("evaluations").join("final.result.json"), safe_fs::TEXT_CAP).ok()?;
    serde_json::from_slice::<serde_json::Value>(&bytes).ok()?.get("mean_return")?.as_f64()
}

/// The mean over runs of their first test return (the untrained policy's).
fn first_test_return(dirs: &[PathBuf]) -> Result<f64> {
    let mut first = Vec::new();
    for d in dirs {
        if let Some(v) = read_metrics(d)?.into_iter().find_map(|r| r.test_return_mean) {
            first.push(v);
        }
    }
    Ok(if first.is_empty() { 0.0 } else { mean(&first) })
}

fn reach(row: &mut Row, dirs: &[PathBuf], threshold: f64) -> Result<()> {
    let (mut steps, mut wall) = (Vec::new(), Vec::new());
    for d in dirs {
        if let Some(r) = read_metrics(d)?.into_iter().find(|r| r.test_return_mean.is_some_and(|v| v >= threshold)) {
            steps.push(r.t_env as f64);
            wall.push(r.wall_s);
        }
    }
    row.reached = steps.len();
    row.steps_to_threshold = (!steps.is_empty()).then(|| mean(&steps));
    row.wall_s_to_threshold = (!wall.is_empty()).then(|| mean(&wall));
    Ok(())
}

fn render(env: &str, rows: &[Row], threshold: f64) -> String {
    let mut s = format!(
        "{env}: last-5-tests return and win rate (mean +- sample SD over seeds of each run's last {FINAL_TESTS} test phases; the return also per seed); best-checkpoint eval return (the greedy evaluation of each run's best checkpoint, what `lmac report` scores); steps and wall time to a test return of {threshold:.3} (mean over the seeds that reached it)\n\n"
    );
    s.push_str("| algorithm | seeds | last-5-tests return | last-5-tests win rate | best-checkpoint eval return | reached | env steps to threshold | wall s to threshold | wall s total | schedule |\n");
    s.push_str("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n");
    for r in rows {
        let win = match (r.final_win_rate_mean, r.final_win_rate_std) {
            (Some(m), Some(sd)) => format!("{m:.3} +- {sd:.3}"),
            _ => "-".into(),
        };
        let eval = match (r.best_eval_return_mean, r.best_eval_return_std) {
            (Some(m), Some(sd)) => format!("{m:.3} +- {sd:.3}"),
            _ => "-".into(),
        };
        s.push_str(&format!(
            "| {} | {} | {:.3} +- {:.3} ({}) | {win} | {eval} | {}/{} | {} | {} | {:.0} | {} |\n",
            r.label,
            r.seeds,
            r.final_return_mean,
            r.final_return_std,
            r.final_returns.iter().map(|v| format!("{v:.3}")).collect::<Vec<_>>().join(", "),
            r.reached,
            r.seeds,
            r.steps_to_threshold.map_or("-".into(), |v| format!("{v:.0}")),
            r.wall_s_to_threshold.map_or("-".into(), |v| format!("{v:.0}")),
            r.wall_s_total,
            r.schedule
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::split_outside_quotes;

    #[test]
    fn a_variants_quoted_value_keeps_its_commas() {
        assert_eq!(
            split_outside_quotes(r#"lmac,run.protocol="designs/pz_x,N=4",method.window=5"#),
            vec!["lmac", r#"run.protocol="designs/pz_x,N=4""#, "method.window=5"]
        );
        assert_eq!(split_outside_quotes("qmix"), vec!["qmix"]);
    }
}
