//! `lmac chaos` and `lmac soak` (the work is `lmac_benches::faults`).

use super::parse_duration;
use anyhow::{bail, Context, Result};
use clap::Args;

#[derive(Args)]
pub(crate) struct ChaosArgs {
    /// Kills (each followed by a resume).
    #[arg(long, default_value_t = 100)]
    kills: usize,
    /// When to kill: `running` (a random process once the pipeline is up, after --kill-after),
    /// `save` (the trainer aborts at a random step inside its first checkpoint save after the
    /// resume), `startup` (a random process within --startup-window seconds of the resume,
    /// before the pipeline is up) or `all` (the three in turn). The first kill is always
    /// `running`, so the run has a checkpoint to resume from.
    #[arg(long, default_value = "running")]
    mode: lmac_benches::faults::ChaosMode,
    /// Seconds after a resume within which `startup` kills land (uniformly).
    #[arg(long, default_value_t = 1.5)]
    startup_window: f64,
    #[arg(long, default_value = "lbf:8x8-2p-2f-s1-coop")]
    env: String,
    /// Env steps between checkpoints (at most this many are lost per crash).
    #[arg(long, default_value_t = 5000)]
    checkpoint_interval: u64,
    /// Seconds from each start or resume to the kill: drawn uniformly from MIN,MAX.
    #[arg(long, value_delimiter = ',', default_value = "3,12")]
    kill_after: Vec<f64>,
    /// Environments per env server and env servers.
    #[arg(long, default_value_t = 8)]
    envs: usize,
    #[arg(long, default_value_t = 2)]
    servers: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Where the run goes (must be empty or absent; default: a temporary folder, removed after).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
    /// Write the report (JSON) here.
    #[arg(long)]
    report: Option<std::path::PathBuf>,
}

#[derive(Args)]
pub(crate) struct SoakArgs {
    /// How long to train, e.g. 2h, 30m, 90s.
    #[arg(long, default_value = "2h", value_parser = parse_duration)]
    duration: f64,
    /// Seconds between samples.
    #[arg(long, default_value_t = 30.0)]
    interval: f64,
    #[arg(long, default_value = "lbf:8x8-2p-2f-s1-coop")]
    env: String,
    #[arg(long, default_value_t = 16)]
    envs: usize,
    #[arg(long, default_value_t = 2)]
    servers: usize,
    /// Store the replay buffer in checkpoints too (the largest thing a run writes).
    #[arg(long)]
    save_buffer: bool,
    /// Where the run goes (default: a temporary folder, removed after).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
    /// Write the report (JSON, with every sample) here.
    #[arg(long)]
    report: Option<std::path::PathBuf>,
}

pub(crate) fn chaos(a: ChaosArgs) -> Result<i32> {
    use lmac_benches::faults::{chaos, ChaosOptions};
    let [lo, hi] = a.kill_after[..] else { bail!("--kill-after: give MIN,MAX seconds, e.g. 3,12") };
    if !(lo > 0.0 && hi >= lo) {
        bail!("--kill-after: need 0 < MIN <= MAX, got {lo},{hi}");
    }
    // Without --out: a private directory (removed with `scratch`), not a guessable name in /tmp.
    let scratch = match &a.out {
        Some(_) => None,
        None => Some(lmac_run::safe_fs::PrivateDir::new("chaos").context("creating a private temporary directory")?),
    };
    let out = a.out.clone().unwrap_or_else(|| scratch.as_ref().expect("made without --out").path().to_path_buf());
    if !(a.startup_window > 0.0 && a.startup_window.is_finite()) {
        bail!("--startup-window: need a positive number of seconds, got {}", a.startup_window);
    }
    let o = ChaosOptions {
        mode: a.mode,
        startup_window: a.startup_window,
        kills: a.kills,
        seed: a.seed,
        out: out.clone(),
        env: a.env,
        checkpoint_interval: a.checkpoint_interval,
        kill_after: (lo, hi),
        envs: a.envs,
        servers: a.servers,
    };
    let bar = indicatif::ProgressBar::new(a.kills as u64);
    bar.set_style(indicatif::ProgressStyle::with_template("[{elapsed_precise}] {bar:30} {pos}/{len} kills {msg}").expect("template"));
    let r = chaos(&o, |_, k| {
        bar.inc(1);
        bar.set_message(format!(
            "last: {} after {:.1} s, noticed in {}",
            k.victim.name(),
            k.after_s,
            k.detect_s.map_or("-".into(), |d| format!("{d:.2} s"))
        ));
    });
    bar.finish_and_clear();
    drop(scratch);
    let r = r?;
    let text = serde_json::to_string_pretty(&r)?;
    if let Some(p) = &a.report {
        std::fs::write(p, &text).with_context(|| format!("writing {}", p.display()))?;
    }
    println!(
        "{} kills in {:.0} s: deaths noticed in p50 {:.2} s, p99 {:.2} s (max {:.2} s, {} unnoticed); resumes that continued {}/{}; \
         checkpoints that failed to load {}; env steps lost per crash max {} (mean {:.0}, checkpoint interval {}); shared-memory files left {}; metrics monotone {}",
        r.kills, r.seconds, r.detect_p50_s, r.detect_p99_s, r.detect_max_s, r.undetected, r.resumes_continued, r.kills,
        r.checkpoint_load_failures, r.steps_lost_max, r.steps_lost_mean, r.checkpoint_interval, r.shm_files_left, r.metrics_monotone
    );
    for v in &r.by_victim {
        println!(
            "  {}: {} kills, noticed in p50 {:.2} s (max {:.2} s), steps lost max {}",
            v["victim"].as_str().unwrap_or(""),
            v["kills"],
            v["detect_p50_s"].as_f64().unwrap_or(f64::NAN),
            v["detect_max_s"].as_f64().unwrap_or(f64::NAN),
            v["steps_lost_max"]
        );
    }
    for m in &r.by_mode {
        println!(
            "  mode {}: {} kills, noticed in p50 {:.2} s (max {:.2} s), resumes that continued {}, checkpoint load failures {}, steps lost max {}{}",
            m["mode"].as_str().unwrap_or(""),
            m["kills"],
            m["detect_p50_s"].as_f64().unwrap_or(f64::NAN),
            m["detect_max_s"].as_f64().unwrap_or(f64::NAN),
            m["resumes_continued"],
            m["checkpoint_load_failures"],
            m["steps_lost_max"],
            if m["mode"] == "save" { format!(", {} distinct save steps", m["save_steps"]) } else { String::new() }
        );
    }
    let ok = r.undetected == 0
        && r.checkpoint_load_failures == 0
        && r.resumes_continued == r.kills
        && r.shm_files_left == 0
        && r.metrics_monotone;
    Ok(if ok { 0 } else { 1 })
}

pub(crate) fn soak(a: SoakArgs) -> Result<i32> {
    // Without --out: a private directory (removed with `scratch`), not a guessable name in /tmp.
    let scratch = match &a.out {
        Some(_) => None,
        None => Some(lmac_run::safe_fs::PrivateDir::new("soak").context("creating a private temporary directory")?),
    };
    let out = a.out.clone().unwrap_or_else(|| scratch.as_ref().expect("made without --out").path().to_path_buf());
    let mut args: Vec<String> = ["--env", &a.env, "--algo", "qmix", "--steps", "1000000000000"].iter().map(|s| s.to_string()).collect();
    for kv in [format!("run.envs={}", a.envs), format!("run.servers={}", a.servers), format!("run.save_buffer={}", a.save_buffer)] {
        args.extend(["--set".to_string(), kv]);
    }
    args.extend(["--out".to_string(), out.display().to_string()]);
    let buffer = lmac_run::learn::LearnConfig::default().buffer_size as u64;
    let bar = indicatif::ProgressBar::new(a.duration as u64);
    bar.set_style(indicatif::ProgressStyle::with_template("[{elapsed_precise}] {bar:30} {pos}/{len} s {msg}").expect("template"));
    let r = lmac_benches::faults::soak(&args, &out, &a.env, a.duration, a.interval, buffer, |s| {
        bar.set_position(s.wall_s as u64);
        bar.set_message(format!("t_env {} RSS {:.0} MiB, {} fds, {} shm mappings", s.t_env, s.rss_mib, s.open_fds, s.shm_mappings));
    });
    bar.finish_and_clear();
    drop(scratch);
    let r = r?;
    if let Some(p) = &a.report {
        std::fs::write(p, serde_json::to_string_pretty(&r)?).with_context(|| format!("writing {}", p.display()))?;
    }
    println!(
        "{:.0} s, {} env steps: RSS {:.0} MiB when the buffer filled (at {:.0} s), {:.0} MiB at the end (max {:.0}); after it filled: \
         RSS {:+.1} MiB/h, open fds {:+.2}/h (range {}-{}), shm mappings {:+.2}/h (range {}-{})",
        r.seconds,
        r.t_env,
        r.rss_mib_at_buffer_full.unwrap_or(f64::NAN),
        r.buffer_full_at_s.unwrap_or(f64::NAN),
        r.rss_mib_end,
        r.rss_mib_max,
        r.rss_mib_per_hour,
        r.open_fds_per_hour,
        r.open_fds_range.0,
        r.open_fds_range.1,
        r.shm_mappings_per_hour,
        r.shm_mappings_range.0,
        r.shm_mappings_range.1
    );
    Ok(0)
}
