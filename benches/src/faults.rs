//! Faults measured, not hoped: `lmac chaos` kills a random process of a real training run with
//! SIGKILL at a random moment, resumes the run and repeats, measuring how fast each death is
//! noticed, whether every resume continues, how many env steps each crash costs and what is
//! left in shared memory; `lmac soak` samples a long run's memory, file descriptors and shared
//! memory mappings, so leaks show as slopes.
//!
//! Both drive `lmac train` (this executable) as a subprocess, exactly as a user would.

use anyhow::{bail, Context, Result};
use lmac_run::stats::quantile;
use rand::{Rng, SeedableRng};
use serde::Serialize;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// A process of a pipeline run, as found in /proc.
#[derive(Clone, Debug)]
pub struct RunProc {
    pub pid: i32,
    pub role: Role,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, PartialOrd, Ord)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    Parent,
    EnvServer,
    ProtocolRunner,
    Trainer,
}

impl Role {
    pub fn name(self) -> &'static str {
        match self {
            Role::Parent => "parent",
            Role::EnvServer => "env server",
            Role::ProtocolRunner => "protocol runner",
            Role::Trainer => "trainer",
        }
    }
}

fn ppid_of(pid: i32) -> Option<i32> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The 4th field, after the parenthesised command name (which may hold spaces).
    stat.rsplit_once(')')?.1.split_whitespace().nth(1)?.parse().ok()
}

/// Whether process `pid` lives (a zombie does not).
pub fn alive(pid: i32) -> bool {
    // A zombie is dead for our purposes: it only waits to be reaped.
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .ok()
        .and_then(|s| s.rsplit_once(')').map(|(_, rest)| rest.split_whitespace().next() != Some("Z")))
        .unwrap_or(false)
}

/// The children of `parent` that belong to its pipeline, by their command lines.
pub fn pipeline_children(parent: i32) -> Vec<RunProc> {
    let mut out = Vec::new();
    for e in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<i32>() else { continue };
        if ppid_of(pid) != Some(parent) || !alive(pid) {
            continue;
        }
        let cmd = String::from_utf8_lossy(&std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default()).into_owned();
        let role = if cmd.contains("lmac_env.server") {
            Role::EnvServer
        } else if cmd.contains("child\0runner") {
            Role::ProtocolRunner
        } else if cmd.contains("child\0trainer") {
            Role::Trainer
        } else {
            continue;
        };
        out.push(RunProc { pid, role });
    }
    out
}

/// The pipeline run id a child was started with (`--run ID`), from its command line.
fn run_id_of(pid: i32) -> Option<String> {
    let cmd = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
    let args: Vec<String> = cmd.split(|&b| b == 0).map(|a| String::from_utf8_lossy(a).into_owned()).collect();
    args.iter().position(|a| a == "--run").and_then(|i| args.get(i + 1).cloned())
}

/// Files in /dev/shm that a run can leave: lmac's slabs and iceoryx2's resources (except its
/// machine-wide node-id counter, kept across runs by design).
fn shm_files() -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir("/dev/shm")
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| (n.starts_with("lmac-") || n.starts_with("iox2")) && !n.ends_with("global_mgmt"))
        .collect();
    v.sort();
    v
}

/// What a killed run left in shared memory before anything cleaned up after it: its slabs
/// (named by `run_id`) and the iceoryx2 nodes of its dead processes (by the run id in their
/// name). Counted by owner, not as new files since the start: other runs on the machine (an
/// experiment beside the chaos) create and remove iceoryx2 files all the time.
fn leftovers(run_id: &str) -> Vec<String> {
    if run_id.is_empty() {
        return Vec::new();
    }
    let mut v: Vec<String> = shm_files().into_iter().filter(|f| f.starts_with(&format!("lmac-{run_id}-"))).collect();
    use lmac_shm_schema::leftovers::{survey, Kind};
    v.extend(survey().dead.into_iter().filter(|f| f.kind == Kind::Node && f.run == run_id).map(|f| format!("iceoryx2 node {}", f.name)));
    v
}

/// A running `lmac train` with its stderr read line by line on a thread, each line stamped.
struct Training {
    child: Child,
    lines: Arc<Mutex<Vec<(Instant, String)>>>,
    reader: Option<std::thread::JoinHandle<()>>,
}

impl Training {
    /// `lmac train ARGS`, with `fault` (name, value) in its environment (and so its children's).
    fn start(args: &[String], fault: Option<(&str, String)>) -> Result<Training> {
        let exe = lmac_run::supervisor::self_exe()?;
        let mut cmd = Command::new(exe);
        if let Some((k, v)) = fault {
            cmd.env(k, v);
        }
        let mut child = cmd
            .arg("train")
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .context("starting lmac train")?;
        let lines = Arc::new(Mutex::new(Vec::new()));
        let err = child.stderr.take().expect("piped stderr");
        let sink = lines.clone();
        let reader = std::thread::spawn(move || {
            // Progress bars redraw with '\r': split on it too.
            let mut r = BufReader::new(err);
            let mut buf = Vec::new();
            while r.read_until(b'\n', &mut buf).map(|n| n > 0).unwrap_or(false) {
                let now = Instant::now();
                let text = String::from_utf8_lossy(&buf).into_owned();
                let mut s = sink.lock().unwrap_or_else(|e| e.into_inner());
                s.extend(text.split('\r').map(|l| l.trim().to_string()).filter(|l| !l.is_empty() && !l.starts_with('[')).map(|l| (now, l)));
                buf.clear();
            }
        });
        Ok(Training { child, lines, reader: Some(reader) })
    }

    fn first_line_after(&self, t: Instant, pred: impl Fn(&str) -> bool) -> Option<Instant> {
        self.lines.lock().unwrap_or_else(|e| e.into_inner()).iter().find(|(at, l)| *at >= t && pred(l)).map(|(at, _)| *at)
    }

    fn text(&self) -> String {
        self.lines.lock().unwrap_or_else(|e| e.into_inner()).iter().map(|(_, l)| l.as_str()).collect::<Vec<_>>().join("\n")
    }

    /// Wait for the process to exit (up to `timeout`); then the rest of its stderr.
    fn wait(&mut self, timeout: Duration) -> Result<std::process::ExitStatus> {
        let t0 = Instant::now();
        loop {
            if let Some(st) = self.child.try_wait()? {
                if let Some(r) = self.reader.take() {
                    let _ = r.join();
                }
                return Ok(st);
            }
            if t0.elapsed() > timeout {
                let _ = self.child.kill();
                bail!("lmac train (pid {}) did not exit within {timeout:?}", self.child.id());
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

/// The `t_env` column of a run's `metrics.csv` (what its plots draw), in file order.
pub fn metrics_t_env(dir: &Path) -> Vec<u64> {
    std::fs::read_to_string(dir.join("metrics.csv"))
        .unwrap_or_default()
        .lines()
        .skip(1)
        .filter_map(|l| l.split(',').next()?.parse().ok())
        .collect()
}

/// The step a resumed run continues from, from its "resuming from ... at t_env N" line.
fn resumed_at(stderr: &str) -> Option<u64> {
    let line = stderr.lines().find(|l| l.contains("resuming from"))?;
    line.split("at t_env ").nth(1)?.split_whitespace().next()?.parse().ok()
}

/// When in a run's life `lmac chaos` kills.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ChaosMode {
    /// A random process at a random moment once the pipeline is up (`--kill-after`).
    Running,
    /// The trainer inside a checkpoint save: it aborts at a random step of the save protocol
    /// (`learn::checkpoint::fault::EVERY_SAVE`, through `LMAC_FAULT_CHECKPOINT`), at the first
    /// save after the resume.
    Save,
    /// A random process that exists in the first `--startup-window` seconds of a resume, before
    /// the pipeline is up: handshakes, slab creation, the checkpoint load.
    Startup,
    /// The three in turn, kill by kill.
    All,
}

impl std::str::FromStr for ChaosMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "running" => Ok(ChaosMode::Running),
            "save" => Ok(ChaosMode::Save),
            "startup" => Ok(ChaosMode::Startup),
            "all" => Ok(ChaosMode::All),
            _ => Err(format!("{s:?}: use running, save, startup or all")),
        }
    }
}

impl ChaosMode {
    /// The mode of kill `k`. The first kill is always `Running`: the run needs a checkpoint
    /// before a crash inside a save or at start-up can be resumed (a run with no checkpoint
    /// and metrics beyond step 0 refuses to restart, by design).
    fn of_kill(self, k: usize) -> ChaosMode {
        match (self, k) {
            (_, 0) => ChaosMode::Running,
            (ChaosMode::All, k) => [ChaosMode::Running, ChaosMode::Save, ChaosMode::Startup][k % 3],
            (m, _) => m,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            ChaosMode::Running => "running",
            ChaosMode::Save => "save",
            ChaosMode::Startup => "startup",
            ChaosMode::All => "all",
        }
    }
}

/// Record on `kills` the resume that followed them, when it can be judged: it did not load a
/// checkpoint (`resumed` None: judged, failed) or its metrics went on past the step it resumed
/// from (judged, continued). A resume killed before its first metrics row past that step (a
/// loaded machine can take seconds) says nothing yet: the kills stay pending (false) and the
/// next resume judges them, the last one by a graceful run.
fn judge(kills: &mut [Kill], resumed: Option<u64>, dir: &Path) -> bool {
    let continued = resumed.is_some_and(|r| metrics_t_env(dir).last().is_some_and(|&t| t > r));
    if resumed.is_some() && !continued {
        return false;
    }
    record_resume(kills, resumed, continued);
    true
}

/// Write on `kills` what the resume after them did.
fn record_resume(kills: &mut [Kill], resumed: Option<u64>, continued: bool) {
    for k in kills {
        k.resumed_t_env = resumed;
        k.steps_lost = resumed.map(|r| k.reached_t_env.saturating_sub(r));
        k.resume_continued = continued;
        k.checkpoint_load_failed = resumed.is_none();
    }
}

/// Wait (up to 90 s) until none of `pids` is alive.
fn wait_gone(pids: impl Iterator<Item = i32> + Clone) {
    let t0 = Instant::now();
    while pids.clone().any(alive) && t0.elapsed() < Duration::from_secs(90) {
        std::thread::sleep(Duration::from_millis(20));
    }
}

impl Kill {
    /// A kill whose resume is not judged yet.
    fn new(mode: ChaosMode, victim: Role, after_s: f64, detect_s: Option<f64>, reached_t_env: u64, shm_left: Vec<String>) -> Kill {
        Kill {
            mode,
            save_step: None,
            slow_to_stop: Vec::new(),
            victim,
            after_s,
            detect_s,
            reached_t_env,
            resumed_t_env: None,
            steps_lost: None,
            resume_continued: false,
            checkpoint_load_failed: false,
            shm_left,
        }
    }
}

/// Counts and figures over some kills, for the report's breakdowns.
fn kill_stats(of: &[&Kill]) -> serde_json::Value {
    let d: Vec<f64> = of.iter().filter_map(|k| k.detect_s).collect();
    serde_json::json!({
        "kills": of.len(), "detect_p50_s": quantile(&d, 0.5), "detect_max_s": d.iter().cloned().fold(f64::NAN, f64::max),
        "steps_lost_max": of.iter().filter_map(|k| k.steps_lost).max(),
    })
}

/// What `lmac chaos` is asked to do.
#[derive(Clone, Debug)]
pub struct ChaosOptions {
    pub mode: ChaosMode,
    /// [`ChaosMode::Startup`]: kills land uniformly in this many seconds after the resume.
    pub startup_window: f64,
    pub kills: usize,
    pub seed: u64,
    /// Where the training group is written (a fresh folder).
    pub out: PathBuf,
    pub env: String,
    /// Env steps between checkpoints.
    pub checkpoint_interval: u64,
    /// Seconds after the run starts (or resumes) before the kill, drawn uniformly.
    pub kill_after: (f64, f64),
    pub envs: usize,
    pub servers: usize,
}

/// One kill and what followed.
#[derive(Clone, Debug, Serialize)]
pub struct Kill {
    pub mode: ChaosMode,
    /// [`ChaosMode::Save`]: the save step the trainer aborted at.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub save_step: Option<&'static str>,
    /// A killed parent's children still alive 5 s after the kill (each should stop at once).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub slow_to_stop: Vec<Role>,
    pub victim: Role,
    pub after_s: f64,
    /// From the SIGKILL to the first sign the death was noticed: the parent naming the dead
    /// child, or, for the parent, every child gone.
    pub detect_s: Option<f64>,
    /// The last metrics row before the kill, and the step the resume continued from.
    pub reached_t_env: u64,
    pub resumed_t_env: Option<u64>,
    pub steps_lost: Option<u64>,
    pub resume_continued: bool,
    pub checkpoint_load_failed: bool,
    pub shm_left: Vec<String>,
}

#[derive(Debug, Serialize)]
pub struct ChaosReport {
    pub env: String,
    pub kills: usize,
    pub checkpoint_interval: u64,
    pub detect_p50_s: f64,
    pub detect_p99_s: f64,
    pub detect_max_s: f64,
    pub undetected: usize,
    pub resumes_continued: usize,
    pub checkpoint_load_failures: usize,
    pub steps_lost_max: u64,
    pub steps_lost_mean: f64,
    pub shm_files_left: usize,
    pub metrics_monotone: bool,
    pub by_victim: Vec<serde_json::Value>,
    pub by_mode: Vec<serde_json::Value>,
    pub runs: Vec<Kill>,
    pub seconds: f64,
}

/// `lmac chaos`: see the module documentation.
pub fn chaos(o: &ChaosOptions, mut progress: impl FnMut(usize, &Kill)) -> Result<ChaosReport> {
    let started = Instant::now();
    let mut rng = rand::rngs::StdRng::seed_from_u64(o.seed);
    if o.out.exists() && std::fs::read_dir(&o.out)?.next().is_some() {
        bail!("--out {}: not empty (chaos starts a fresh run there)", o.out.display());
    }
    // Long enough never to finish: the kills end it.
    let fresh: Vec<String> = [
        "--env",
        &o.env,
        "--algo",
        "qmix",
        "--steps",
        "1000000000",
        "--set",
        &format!("run.checkpoint_interval={}", o.checkpoint_interval),
        "--set",
        &format!("run.envs={}", o.envs),
        "--set",
        &format!("run.servers={}", o.servers),
        "--set",
        "run.log_interval=500",
        "--set",
        "run.test_interval=1000000000",
        "--out",
    ]
    .iter()
    .map(|s| s.to_string())
    .chain([o.out.display().to_string()])
    .collect();
    let mut seed_dir: Option<PathBuf> = None;
    let mut kills: Vec<Kill> = Vec::new();
    // kills[pending..] wait for a resume to say where it continued.
    let mut pending = 0;
    for k in 0..o.kills {
        let args = match &seed_dir {
            None => fresh.clone(),
            Some(d) => vec!["--resume".to_string(), d.display().to_string()],
        };
        let mode = o.mode.of_kill(k);
        use lmac_run::learn::checkpoint::fault;
        let save_step = (mode == ChaosMode::Save).then(|| fault::EVERY_SAVE[rng.random_range(0..fault::EVERY_SAVE.len())]);
        let mut run = Training::start(&args, save_step.map(|s| (fault::ENV, format!("{s}@1"))))?;
        let t_start = Instant::now();
        // Wait until the pipeline is up: every role present (not for a start-up kill).
        let mut exited_early = None;
        loop {
            if mode == ChaosMode::Startup {
                break;
            }
            let roles: std::collections::BTreeSet<Role> = pipeline_children(run.child.id() as i32).iter().map(|r| r.role).collect();
            if roles.len() == 3 {
                break;
            }
            if let Some(st) = run.child.try_wait()? {
                exited_early = Some(st);
                break;
            }
            if t_start.elapsed() > Duration::from_secs(120) {
                bail!("kill {k}: the pipeline did not come up within 120 s:\n{}", run.text());
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let dir = match &seed_dir {
            Some(d) => d.clone(),
            None => {
                let group = std::fs::read_dir(o.out.join(lmac_run::run_dir::env_dir_name(&o.env)).join("qmix"))?
                    .flatten()
                    .map(|e| e.path())
                    .next()
                    .context("the run's group directory")?;
                group.join("seed0")
            }
        };
        let wait = match mode {
            ChaosMode::Startup => rng.random_range(0.0..=o.startup_window),
            // The trainer aborts by itself inside its first save; this is the most to wait.
            ChaosMode::Save => 60.0,
            _ => rng.random_range(o.kill_after.0..=o.kill_after.1),
        };
        let deadline = t_start + Duration::from_secs_f64(wait);
        // The previous run's children (by their parent) while this one is alive: the save
        // mode's victim dies by itself, so they are read before it does.
        let mut seen: Vec<RunProc> = Vec::new();
        // The first kill waits for the run's first checkpoint too: a run killed before it has
        // one but after logging metrics refuses to restart from step 0 (by design), which
        // would end the chaos on a loaded machine rather than test anything.
        let has_checkpoint = || lmac_run::learn::checkpoint::checkpoint_exists(lmac_run::train::checkpoint_dir(&dir));
        while exited_early.is_none()
            && (Instant::now() < deadline || (k == 0 && !has_checkpoint() && t_start.elapsed() < Duration::from_secs(300)))
        {
            if mode == ChaosMode::Save {
                let now = pipeline_children(run.child.id() as i32);
                if !now.is_empty() {
                    seen = now;
                }
                if run.first_line_after(t_start, |l| l.contains(fault::ENV)).is_some() {
                    break;
                }
            }
            exited_early = run.child.try_wait()?;
            std::thread::sleep(Duration::from_millis(10));
        }
        if mode == ChaosMode::Save {
            // The trainer aborted inside its save (or, past the deadline, never saved: then it
            // is killed like a running one and the round says so).
            let reached = metrics_t_env(&dir).last().copied().unwrap_or(0);
            let run_id = seen.iter().find_map(|p| run_id_of(p.pid)).unwrap_or_default();
            if run.first_line_after(t_start, |l| l.contains(fault::ENV)).is_none() && run.child.try_wait()?.is_none() {
                let _ = run.child.kill();
            }
            let _ = run.wait(Duration::from_secs(90));
            // Read after the wait, which drains the rest of the run's stderr.
            let aborted = run.first_line_after(t_start, |l| l.contains(fault::ENV));
            let detect_s = aborted.and_then(|t| run.first_line_after(t, |l| l.contains("died")).map(|d| d.duration_since(t).as_secs_f64()));
            wait_gone(seen.iter().map(|p| p.pid));
            if judge(&mut kills[pending..], resumed_at(&run.text()), &dir) {
                pending = kills.len();
            }
            let mut kill = Kill::new(mode, Role::Trainer, t_start.elapsed().as_secs_f64(), detect_s, reached, leftovers(&run_id));
            kill.save_step = if aborted.is_some() { save_step } else { None };
            progress(k, &kill);
            kills.push(kill);
            seed_dir = Some(dir);
            continue;
        }
        // The earlier kills' resume: did it load its checkpoint and continue? A start-up kill
        // lands before the run can show that, so its resume is judged with the next round's.
        if mode != ChaosMode::Startup && judge(&mut kills[pending..], resumed_at(&run.text()), &dir) {
            pending = kills.len();
        }
        if let (Some(st), false) = (exited_early, mode == ChaosMode::Startup) {
            if k > 0 {
                eprintln!("lmac: chaos: the resume after kill {} failed ({st}):\n{}", k - 1, run.text());
                break;
            }
            bail!("lmac train exited ({st}) before the first kill:\n{}", run.text());
        }
        let victims: Vec<RunProc> = std::iter::once(RunProc { pid: run.child.id() as i32, role: Role::Parent })
            .chain(pipeline_children(run.child.id() as i32))
            .collect();
        let victim = victims[rng.random_range(0..victims.len())].clone();
        if exited_early.is_some() {
            // A start-up kill after the resume already failed by itself: that is a finding.
            bail!("kill {k} ({}): lmac train exited by itself within {wait:.2} s of the resume:\n{}", mode.name(), run.text());
        }
        let reached = metrics_t_env(&dir).last().copied().unwrap_or(0);
        let children: Vec<i32> = victims.iter().filter(|p| p.role != Role::Parent).map(|p| p.pid).collect();
        let run_id = children.iter().find_map(|&p| run_id_of(p)).unwrap_or_default();
        let t_kill = Instant::now();
        unsafe { libc::kill(victim.pid, libc::SIGKILL) };
        let mut slow_to_stop = Vec::new();
        let detect_s = if victim.role == Role::Parent {
            let _ = run.wait(Duration::from_secs(10));
            let t0 = Instant::now();
            while children.iter().any(|&p| alive(p)) && t0.elapsed() < Duration::from_secs(90) {
                if slow_to_stop.is_empty() && t_kill.elapsed() > Duration::from_secs(5) {
                    slow_to_stop = victims.iter().filter(|p| p.role != Role::Parent && alive(p.pid)).map(|p| p.role).collect();
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            // The children noticed when they began to stop; they are gone once all have exited.
            (!children.iter().any(|&p| alive(p))).then(|| t_kill.elapsed().as_secs_f64())
        } else {
            let _ = run.wait(Duration::from_secs(90))?;
            // At start-up the parent may stop on the failed handshake before naming the death.
            let exited = t_kill.elapsed().as_secs_f64();
            run.first_line_after(t_kill, |l| l.contains("died"))
                .map(|t| t.duration_since(t_kill).as_secs_f64())
                .or((mode == ChaosMode::Startup).then_some(exited))
        };
        // Orphans of a killed parent reap themselves; wait until nothing of the run is alive.
        wait_gone(children.iter().copied());
        let mut kill = Kill::new(mode, victim.role, wait, detect_s, reached, leftovers(&run_id));
        kill.slow_to_stop = slow_to_stop;
        progress(k, &kill);
        kills.push(kill);
        seed_dir = Some(dir);
    }
    // One last resume shows the last kill's recovery; it is stopped gracefully.
    if let Some(d) = &seed_dir {
        let mut run = Training::start(&["--resume".to_string(), d.display().to_string()], None)?;
        let t0 = Instant::now();
        let resumed = loop {
            if let Some(r) = resumed_at(&run.text()) {
                break Some(r);
            }
            if run.child.try_wait()?.is_some() || t0.elapsed() > Duration::from_secs(120) {
                break None;
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let t1 = Instant::now();
        let mut continued = false;
        while t1.elapsed() < Duration::from_secs(60) && run.child.try_wait()?.is_none() {
            if resumed.is_some_and(|r| metrics_t_env(d).last().is_some_and(|&t| t > r)) {
                continued = true;
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        unsafe { libc::kill(run.child.id() as i32, libc::SIGINT) };
        let _ = run.wait(Duration::from_secs(90));
        record_resume(&mut kills[pending..], resumed, continued);
    }
    let t = seed_dir.as_ref().map(|d| metrics_t_env(d)).unwrap_or_default();
    let detect: Vec<f64> = kills.iter().filter_map(|k| k.detect_s).collect();
    let lost: Vec<u64> = kills.iter().filter_map(|k| k.steps_lost).collect();
    let mut by_victim = Vec::new();
    for role in [Role::Parent, Role::EnvServer, Role::ProtocolRunner, Role::Trainer] {
        let of: Vec<&Kill> = kills.iter().filter(|k| k.victim == role).collect();
        let mut v = kill_stats(&of);
        v["victim"] = role.name().into();
        by_victim.push(v);
    }
    let mut by_mode = Vec::new();
    for mode in [ChaosMode::Running, ChaosMode::Save, ChaosMode::Startup] {
        let of: Vec<&Kill> = kills.iter().filter(|k| k.mode == mode).collect();
        if of.is_empty() {
            continue;
        }
        let mut v = kill_stats(&of);
        v["mode"] = mode.name().into();
        v["resumes_continued"] = of.iter().filter(|k| k.resume_continued).count().into();
        v["checkpoint_load_failures"] = of.iter().filter(|k| k.checkpoint_load_failed).count().into();
        v["save_steps"] = of.iter().filter_map(|k| k.save_step).collect::<std::collections::BTreeSet<_>>().len().into();
        by_mode.push(v);
    }
    Ok(ChaosReport {
        env: o.env.clone(),
        kills: kills.len(),
        checkpoint_interval: o.checkpoint_interval,
        detect_p50_s: quantile(&detect, 0.5),
        detect_p99_s: quantile(&detect, 0.99),
        detect_max_s: detect.iter().cloned().fold(f64::NAN, f64::max),
        undetected: kills.len() - detect.len(),
        resumes_continued: kills.iter().filter(|k| k.resume_continued).count(),
        checkpoint_load_failures: kills.iter().filter(|k| k.checkpoint_load_failed).count(),
        steps_lost_max: lost.iter().copied().max().unwrap_or(0),
        steps_lost_mean: if lost.is_empty() { 0.0 } else { lost.iter().sum::<u64>() as f64 / lost.len() as f64 },
        shm_files_left: kills.iter().map(|k| k.shm_left.len()).sum(),
        metrics_monotone: t.windows(2).all(|w| w[0] <= w[1]),
        by_victim,
        by_mode,
        runs: kills,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// One sample of a run's resources, summed over the parent and its pipeline children.
#[derive(Clone, Debug, Serialize)]
pub struct SoakSample {
    pub wall_s: f64,
    pub t_env: u64,
    pub processes: usize,
    pub rss_mib: f64,
    /// RSS per role (parent, env server, protocol runner, trainer), summed over its processes.
    pub rss_mib_by_role: std::collections::BTreeMap<String, f64>,
    pub open_fds: usize,
    /// Mappings of files in /dev/shm (slabs, iceoryx2 segments).
    pub shm_mappings: usize,
    pub shm_files: usize,
}

fn rss_kib(pid: i32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_default()
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:").and_then(|v| v.split_whitespace().next()?.parse().ok()))
        .unwrap_or(0)
}

fn sample(parent: i32, dir: Option<&Path>, t0: Instant) -> SoakSample {
    let procs: Vec<RunProc> = std::iter::once(RunProc { pid: parent, role: Role::Parent }).chain(pipeline_children(parent)).collect();
    let pids: Vec<i32> = procs.iter().map(|p| p.pid).collect();
    let mut rss_mib_by_role = std::collections::BTreeMap::new();
    for p in &procs {
        *rss_mib_by_role.entry(p.role.name().to_string()).or_insert(0.0) += rss_kib(p.pid) as f64 / 1024.0;
    }
    let fds = |pid: i32| std::fs::read_dir(format!("/proc/{pid}/fd")).map(|d| d.count()).unwrap_or(0);
    let maps = |pid: i32| {
        std::fs::read_to_string(format!("/proc/{pid}/maps")).unwrap_or_default().lines().filter(|l| l.contains("/dev/shm/")).count()
    };
    SoakSample {
        wall_s: t0.elapsed().as_secs_f64(),
        t_env: dir.map(|d| metrics_t_env(d).last().copied().unwrap_or(0)).unwrap_or(0),
        processes: pids.len(),
        rss_mib: rss_mib_by_role.values().sum(),
        rss_mib_by_role,
        open_fds: pids.iter().map(|&p| fds(p)).sum(),
        shm_mappings: pids.iter().map(|&p| maps(p)).sum(),
        shm_files: shm_files().len(),
    }
}

/// Least-squares slope of `y` over `x` (per unit of x).
fn slope(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len() as f64;
    if x.len() < 2 {
        return 0.0;
    }
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let sxy: f64 = x.iter().zip(y).map(|(a, b)| (a - mx) * (b - my)).sum();
    let sxx: f64 = x.iter().map(|a| (a - mx) * (a - mx)).sum();
    if sxx == 0.0 {
        0.0
    } else {
        sxy / sxx
    }
}

#[derive(Debug, Serialize)]
pub struct SoakReport {
    pub env: String,
    pub seconds: f64,
    pub interval_s: f64,
    pub t_env: u64,
    /// From this sample on the replay buffer is full (`learn.buffer_size` episodes collected).
    pub buffer_full_at_s: Option<f64>,
    pub rss_mib_at_buffer_full: Option<f64>,
    pub rss_mib_end: f64,
    pub rss_mib_max: f64,
    /// Slopes after the buffer is full, per hour.
    pub rss_mib_per_hour: f64,
    pub open_fds_per_hour: f64,
    pub shm_mappings_per_hour: f64,
    pub open_fds_range: (usize, usize),
    pub shm_mappings_range: (usize, usize),
    pub samples: Vec<SoakSample>,
}

/// `lmac soak`: train for `seconds` and sample the run's resources every `interval`.
pub fn soak(
    train_args: &[String],
    out: &Path,
    env: &str,
    seconds: f64,
    interval: f64,
    buffer_episodes: u64,
    mut progress: impl FnMut(&SoakSample),
) -> Result<SoakReport> {
    let mut run = Training::start(train_args, None)?;
    let t0 = Instant::now();
    let parent = run.child.id() as i32;
    let mut samples: Vec<SoakSample> = Vec::new();
    let mut dir: Option<PathBuf> = None;
    let mut full_at: Option<usize> = None;
    while t0.elapsed().as_secs_f64() < seconds {
        if let Some(st) = run.child.try_wait()? {
            bail!("lmac train exited ({st}) during the soak:\n{}", run.text());
        }
        if dir.is_none() {
            dir = std::fs::read_dir(out.join(lmac_run::run_dir::env_dir_name(env)).join("qmix"))
                .ok()
                .and_then(|mut d| d.next())
                .and_then(|e| e.ok())
                .map(|e| e.path().join("seed0"));
        }
        let s = sample(parent, dir.as_deref(), t0);
        // Episodes so far, from the last metrics row.
        let episodes = dir
            .as_ref()
            .and_then(|d| std::fs::read_to_string(d.join("metrics.csv")).ok())
            .and_then(|t| t.lines().last().and_then(|l| l.split(',').nth(1)?.parse::<u64>().ok()))
            .unwrap_or(0);
        if full_at.is_none() && episodes >= buffer_episodes {
            full_at = Some(samples.len());
        }
        progress(&s);
        samples.push(s);
        std::thread::sleep(Duration::from_secs_f64(interval));
    }
    unsafe { libc::kill(parent, libc::SIGINT) };
    let _ = run.wait(Duration::from_secs(120));
    let tail = &samples[full_at.unwrap_or(0)..];
    let hours: Vec<f64> = tail.iter().map(|s| s.wall_s / 3600.0).collect();
    let per_hour = |f: &dyn Fn(&SoakSample) -> f64| slope(&hours, &tail.iter().map(f).collect::<Vec<_>>());
    let range = |f: &dyn Fn(&SoakSample) -> usize| (tail.iter().map(f).min().unwrap_or(0), tail.iter().map(f).max().unwrap_or(0));
    Ok(SoakReport {
        env: env.to_string(),
        seconds: t0.elapsed().as_secs_f64(),
        interval_s: interval,
        t_env: samples.last().map_or(0, |s| s.t_env),
        buffer_full_at_s: full_at.map(|i| samples[i].wall_s),
        rss_mib_at_buffer_full: full_at.map(|i| samples[i].rss_mib),
        rss_mib_end: samples.last().map_or(0.0, |s| s.rss_mib),
        rss_mib_max: samples.iter().map(|s| s.rss_mib).fold(0.0, f64::max),
        rss_mib_per_hour: per_hour(&|s| s.rss_mib),
        open_fds_per_hour: per_hour(&|s| s.open_fds as f64),
        shm_mappings_per_hour: per_hour(&|s| s.shm_mappings as f64),
        open_fds_range: range(&|s| s.open_fds),
        shm_mappings_range: range(&|s| s.shm_mappings),
        samples,
    })
}
