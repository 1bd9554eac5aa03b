//! The `lmac` parent process: starts the env servers (Python), the protocol runner and the
//! trainer as child processes, watches them, and on Ctrl-C or a dead child stops the rest and
//! removes the run's shared memory. A child that dies is reported by name.

use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Everything a pipeline run needs to start its processes.
#[derive(Clone, Debug)]
pub struct RunPlan {
    pub run: String,
    pub env: String,
    /// Env server processes.
    pub servers: usize,
    /// Environments each env server process steps.
    pub envs_per_server: usize,
    /// Each process splits its environments into this many sub-batches, one slab and one ring
    /// index each, and steps them in turn: with 2, one half steps while the other half's slot is
    /// with the protocol runner and the trainer (double buffering, as in Sample Factory).
    pub sub_batches: usize,
    pub slots: usize,
    /// Message columns reserved in the slab.
    pub msg_dim: usize,
    pub protocol: lmac_protocol_runner::ProtocolSpec,
    pub seed: u64,
    pub startup_timeout_s: f64,
    /// Env steps the trainer takes (after warm-up).
    pub steps: u64,
    /// What the trainer child does; handed to it as a typed file ([`TrainerJobFile`]).
    pub trainer: TrainerJob,
    /// Extra arguments for every env server (after `python -m lmac_env.server ...`).
    pub env_server_args: Vec<String>,
}

/// What the trainer child of a pipeline run does besides stepping the ring.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct TrainerJob {
    /// Slots taken before env steps are counted.
    pub warmup: u64,
    /// Check every slot's message columns, episode ids, steps and boundaries.
    pub verify: bool,
    /// Write one JSON line per finished episode here (random acting only).
    pub episodes_out: Option<PathBuf>,
    /// Show a progress bar.
    pub progress: bool,
    pub work: TrainerWork,
}

impl Default for TrainerJob {
    fn default() -> Self {
        TrainerJob { warmup: 10, verify: false, episodes_out: None, progress: false, work: TrainerWork::Random }
    }
}

/// The trainer child's work.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrainerWork {
    /// Act randomly (`lmac run`, the pipeline benchmarks).
    Random,
    /// Train the run directory (a `config.toml` inside) from its checkpoint or from scratch.
    Train { dir: PathBuf },
    /// Evaluate the run directory's checkpoint as the spec file says.
    Evaluate { dir: PathBuf, spec: PathBuf },
}

/// The file the parent writes for its trainer child (`lmac child trainer --job FILE`), in the
/// run's private scratch directory: the job and what the plan fixes for it.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct TrainerJobFile {
    pub steps: u64,
    pub seed: u64,
    /// Where the child writes its report for the parent.
    pub report: PathBuf,
    pub job: TrainerJob,
}

impl TrainerJobFile {
    /// Read the job file, naming it in any error.
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = crate::safe_fs::read_capped(path, crate::safe_fs::TEXT_CAP).context("reading the trainer job")?;
        serde_json::from_slice(&bytes).with_context(|| format!("the trainer job {} is not a job file", path.display()))
    }
}

/// The repository root (the folder holding `env-server/lmac_env`): `$LMAC_ROOT`, else found by
/// walking up from the executable and from the current directory.
pub fn repo_root() -> Result<PathBuf> {
    if let Ok(r) = std::env::var("LMAC_ROOT") {
        return Ok(PathBuf::from(r));
    }
    let starts = [std::env::current_exe().ok(), std::env::current_dir().ok()];
    starts
        .into_iter()
        .flatten()
        .find_map(|s| s.ancestors().find(|d| d.join("env-server/lmac_env").is_dir()).map(Path::to_path_buf))
        .context("cannot find the lmac repository (env-server/lmac_env); set LMAC_ROOT")
}

/// The Python that runs env servers: $LMAC_PYTHON, else the project's .venv, else python3.
pub fn python() -> Result<PathBuf> {
    if let Ok(p) = std::env::var("LMAC_PYTHON") {
        return Ok(PathBuf::from(p));
    }
    let venv = repo_root()?.join(".venv/bin/python");
    if venv.exists() {
        return Ok(venv);
    }
    Ok(PathBuf::from("python3"))
}

/// A Python command with env-server/ on its path.
pub fn python_command() -> Result<Command> {
    let mut c = Command::new(python()?);
    let root = repo_root()?;
    let mut pp = root.join("env-server").into_os_string();
    if let Some(old) = std::env::var_os("PYTHONPATH") {
        pp.push(":");
        pp.push(old);
    }
    c.env("PYTHONPATH", pp);
    // One rule for where schemas live (`schema::schema_dir`), used by both sides: the Python
    // side reads $LMAC_SCHEMA_DIR, so it reads the files this process validated.
    if let Some(dir) = lmac_shm_schema::schema::schema_dir() {
        c.env("LMAC_SCHEMA_DIR", dir);
    }
    Ok(c)
}

pub struct Proc {
    pub name: String,
    pub child: Child,
    pub status: Option<ExitStatus>,
}

fn describe(status: &ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    match (status.code(), status.signal()) {
        (Some(c), _) => format!("exit code {c}"),
        (None, Some(s)) => format!(
            "killed by signal {s}{}",
            if s == libc::SIGKILL {
                " (SIGKILL)"
            } else if s == libc::SIGSEGV {
                " (SIGSEGV)"
            } else {
                ""
            }
        ),
        _ => "unknown status".into(),
    }
}

impl RunPlan {
    /// The ring members the protocol runner and the trainer serve: one per sub-batch of each env
    /// server process.
    pub fn ring_members(&self) -> usize {
        self.servers * self.sub_batches
    }
}

/// The default split of `envs` environments per process: two sub-batches when they halve evenly,
/// unless the schema turns double buffering off.
pub fn default_sub_batches(schema: &lmac_shm_schema::EnvSchema, envs: usize) -> usize {
    if schema.double_buffer && envs >= 2 && envs % 2 == 0 {
        2
    } else {
        1
    }
}

/// Remove what a run may leave in shared memory: its slabs and dead iceoryx2 nodes.
pub fn cleanup_run(run: &str, servers: usize) {
    for s in 0..servers {
        lmac_shm_schema::slab::unlink(&lmac_protocol_runner::runner::slab_name(run, s));
    }
    lmac_shm_schema::ring::cleanup_dead_nodes(run);
}

/// The outcome of a run that ended well: the trainer's report.
pub struct RunOutcome {
    pub report: crate::pipeline::TrainerReport,
}

/// Where the trainer writes its report (a file of its own, not its stdout): inside a private
/// directory of this run, never at a name in the shared temp directory that another user could
/// predict (the run id is in every child's argv) and plant a symlink at.
fn report_path(scratch: &crate::safe_fs::PrivateDir) -> PathBuf {
    scratch.path().join("report.json")
}

/// Ask the kernel to send the child SIGTERM when this process dies (even by SIGKILL), so a dead
/// parent never leaves its pipeline running: the children then stop as on Ctrl-C (the trainer
/// writes a last checkpoint). Linux `PR_SET_PDEATHSIG`; it fires when the spawning thread ends,
/// and every pipeline is started and supervised from one thread until its children are gone.
fn stop_with_parent(c: &mut Command) {
    use std::os::unix::process::CommandExt;
    let parent = std::process::id() as libc::pid_t;
    // Also told by pid, so the child's own waits notice a dead parent without the signal
    // (`ring::stop_requested`).
    c.env(lmac_shm_schema::ring::PARENT_PID_VAR, parent.to_string());
    // SAFETY: only async-signal-safe calls (signal, prctl, getppid, raise) between fork and exec.
    unsafe {
        c.pre_exec(move || {
            // Between fork and exec the child still runs this process's SIGTERM handler, which
            // only sets a flag in memory that exec discards: a parent dying in that window would
            // leave the child running on, waiting out its start-up timeout as an orphan
            // (`lmac chaos --mode startup` found it: 60 s). With the default action the signal
            // ends the child before exec; after exec the program's own handler takes over.
            libc::signal(libc::SIGTERM, libc::SIG_DFL);
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The parent may have died before the prctl took effect.
            if libc::getppid() != parent {
                libc::raise(libc::SIGTERM);
            }
            Ok(())
        });
    }
}

/// The executable a child of this process runs: this very build. `/proc/self/exe` names the
/// running binary's inode even after a rebuild has replaced or removed its file (the path
/// `current_exe` gives then ends in " (deleted)" and cannot be started), so a long `lmac
/// experiment` survives a `cargo build` beside it and never mixes two builds in one run.
pub fn self_exe() -> Result<PathBuf> {
    let running = Path::new("/proc/self/exe");
    if running.exists() {
        Ok(running.to_path_buf())
    } else {
        std::env::current_exe().context("locating the lmac executable")
    }
}

/// Start all processes and supervise them until the trainer finishes, a child dies, or
/// `interrupted` is set (Ctrl-C).
pub fn run_pipeline(plan: &RunPlan, interrupted: Arc<AtomicBool>) -> Result<RunOutcome> {
    let exe = self_exe()?;
    // Removed (with the report) when this function returns, after every child has ended.
    let scratch =
        crate::safe_fs::PrivateDir::new(&format!("{}-run", plan.run)).context("creating the run's private temporary directory")?;
    // Runs killed whole (kill -9 of the process group, the OOM killer) could not clean up after
    // themselves: remove this user's dead leftovers before adding to shared memory.
    let reclaimed = lmac_shm_schema::leftovers::reclaim();
    if !reclaimed.removed.is_empty() {
        let runs: std::collections::BTreeSet<&str> = reclaimed.removed.iter().map(|f| f.run.as_str()).collect();
        eprintln!(
            "lmac: removed {} shared-memory leftovers of dead runs ({})",
            reclaimed.removed.len(),
            runs.into_iter().collect::<Vec<_>>().join(", ")
        );
    }
    let mut procs: Vec<Proc> = Vec::new();
    let spawn_all = |procs: &mut Vec<Proc>| -> Result<()> {
        let h = plan.sub_batches;
        for s in 0..plan.servers {
            let mut c = python_command()?;
            c.args(["-m", "lmac_env.server", "--env", &plan.env, "--run", &plan.run])
                .args(["--envs", &plan.envs_per_server.to_string(), "--sub-batches", &h.to_string()])
                .args(["--first-member", &(s * h).to_string(), "--members", &plan.ring_members().to_string()])
                .args(["--slots", &plan.slots.to_string()])
                .args(["--msg-dim", &plan.msg_dim.to_string(), "--seed", &plan.seed.to_string()])
                .args(["--startup-timeout", &plan.startup_timeout_s.to_string()])
                .args(&plan.env_server_args)
                .stdin(Stdio::null());
            stop_with_parent(&mut c);
            let child = c.spawn().with_context(|| {
                format!(
                    "starting an env server with {} (the Python: $LMAC_PYTHON, else .venv, else python3)",
                    c.get_program().to_string_lossy()
                )
            })?;
            let name = if h == 1 {
                format!("env server {s} ({})", plan.env)
            } else {
                format!("env server {s} (sub-batches {}-{}, {})", s * h, s * h + h - 1, plan.env)
            };
            procs.push(Proc { name, child, status: None });
        }
        let common = |c: &mut Command| {
            // `ps` shows `lmac child ...`, not the /proc path the binary is started by.
            std::os::unix::process::CommandExt::arg0(c, "lmac");
            c.args(["--run", &plan.run, "--env", &plan.env, "--members", &plan.ring_members().to_string()])
                .args(["--slots", &plan.slots.to_string(), "--protocol", &plan.protocol.to_string()])
                .args(["--startup-timeout", &plan.startup_timeout_s.to_string()])
                .stdin(Stdio::null());
            stop_with_parent(c);
        };
        let mut r = Command::new(&exe);
        r.args(["child", "runner"]);
        common(&mut r);
        procs.push(Proc { name: "protocol runner".into(), child: r.spawn().context("starting the protocol runner")?, status: None });
        let mut t = Command::new(&exe);
        t.args(["child", "trainer"]);
        common(&mut t);
        let job = TrainerJobFile { steps: plan.steps, seed: plan.seed, report: report_path(&scratch), job: plan.trainer.clone() };
        let job_path = scratch.path().join("trainer_job.json");
        crate::safe_fs::write_replace(&job_path, &serde_json::to_vec_pretty(&job)?)
            .with_context(|| format!("writing the trainer job {}", job_path.display()))?;
        t.arg("--job").arg(&job_path);
        procs.push(Proc { name: TRAINER.into(), child: t.spawn().context("starting the trainer")?, status: None });
        Ok(())
    };
    let started = spawn_all(&mut procs);
    let trainer_idx = procs.len().saturating_sub(1);
    let result = match started {
        Err(e) => Err(e),
        Ok(()) => supervise(&mut procs, trainer_idx, &interrupted),
    };
    stop_all(&mut procs);
    cleanup_run(&plan.run, plan.ring_members());
    let path = report_path(&scratch);
    let report = std::fs::read(&path);
    result?;
    let report = report.with_context(|| format!("the trainer wrote no report ({})", path.display()))?;
    let report = serde_json::from_slice(&report).with_context(|| format!("the trainer's report {}", path.display()))?;
    Ok(RunOutcome { report })
}

fn supervise(procs: &mut [Proc], trainer_idx: usize, interrupted: &AtomicBool) -> Result<()> {
    loop {
        if interrupted.load(Ordering::SeqCst) {
            bail!("interrupted: stopped all processes and removed the run's shared memory");
        }
        let mut newly_dead = Vec::new();
        for (i, p) in procs.iter_mut().enumerate() {
            if p.status.is_none() {
                if let Some(st) = p.child.try_wait()? {
                    p.status = Some(st);
                    newly_dead.push(i);
                }
            }
        }
        if let Some(st) = procs[trainer_idx].status {
            if st.success() {
                // The trainer said goodbye; give the others a moment to finish cleanly.
                let t0 = Instant::now();
                while t0.elapsed() < Duration::from_secs(5)
                    && procs.iter_mut().any(|p| p.status.is_none() && p.child.try_wait().ok().flatten().is_none())
                {
                    std::thread::sleep(Duration::from_millis(20));
                }
                return Ok(());
            }
        }
        // A child that ended before the trainer finished is a failure. Prefer reporting one
        // that was killed or crashed over the peers that exited because they noticed it.
        // Children exit 0 only after a goodbye or a stop request; an unexpected clean exit is
        // noticed by the trainer's liveness check (which then fails with exit code 3).
        let failed: Vec<usize> = procs.iter().enumerate().filter(|(_, p)| p.status.is_some_and(|s| !s.success())).map(|(i, _)| i).collect();
        if !failed.is_empty() {
            let culprit = failed
                .iter()
                .copied()
                .find(|&i| procs[i].status.is_some_and(|s| s.code().is_none()))
                .or_else(|| failed.iter().copied().find(|&i| procs[i].status.is_some_and(|s| s.code() != Some(3))))
                .unwrap_or(failed[0]);
            let p = &procs[culprit];
            let what = format!("{} (pid {}) died: {}", p.name, p.child.id(), describe(p.status.as_ref().expect("exited")));
            // Said at once (stopping the rest can take a while: the trainer writes a checkpoint).
            eprintln!("lmac: {what}; stopping the other processes");
            bail!("{what}");
        }
        let _ = newly_dead;
        std::thread::sleep(Duration::from_millis(25));
    }
}

/// SIGTERM every live child, wait up to 3 s (the trainer up to 60 s: it writes a last
/// checkpoint when asked to stop, with the replay buffer if the run saves it), then SIGKILL.
fn stop_all(procs: &mut [Proc]) {
    for p in procs.iter_mut() {
        if p.status.is_none() && p.child.try_wait().ok().flatten().is_none() {
            unsafe { libc::kill(p.child.id() as i32, libc::SIGTERM) };
        }
    }
    let t0 = Instant::now();
    let grace = |p: &Proc| Duration::from_secs(if p.name == TRAINER { 60 } else { 3 });
    loop {
        let mut waiting = false;
        for p in procs.iter_mut() {
            if p.status.is_none() && p.child.try_wait().ok().flatten().is_none() {
                if t0.elapsed() < grace(p) {
                    waiting = true;
                } else {
                    let _ = p.child.kill();
                    let _ = p.child.wait();
                }
            }
        }
        if !waiting {
            return;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The trainer child's name in messages and in `Proc::name`.
const TRAINER: &str = "trainer";

#[cfg(test)]
mod tests {
    use super::default_sub_batches;
    use lmac_shm_schema::schema::load_env;

    #[test]
    fn double_buffering_by_default_unless_the_schema_turns_it_off() {
        let lbf = load_env("lbf:8x8-2p-2f-s1-coop").unwrap();
        assert!(lbf.double_buffer, "default");
        assert_eq!(default_sub_batches(&lbf, 32), 2);
        assert_eq!(default_sub_batches(&lbf, 7), 1, "an odd batch does not halve");
        let fast = load_env("smaclite:5z_vs_1ul").unwrap();
        assert!(!fast.double_buffer);
        assert_eq!(default_sub_batches(&fast, 32), 1);
        assert_eq!(default_sub_batches(&load_env("smaclite:2o_20b_vs_2r").unwrap(), 32), 2);
    }
}
