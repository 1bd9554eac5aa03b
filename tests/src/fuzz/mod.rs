//! The engine of `lmac-fuzz`: seeded random inputs per parser, panics caught per case, and a
//! supervisor that runs each parser in a child process so that what cannot be caught in-process
//! (an abort from a refused huge allocation, a stack overflow, a hang) is still found, saved and
//! reported, after which the child is restarted past the failing case.
//!
//! Every case is a pure function of (seed, parser, case index), so the supervisor can rebuild the
//! input of a case that killed its child without the child having written it anywhere.

pub mod mutate;
pub mod targets;

use std::collections::BTreeSet;
use std::io::Write;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// splitmix64: small, fast, and the same on every machine.
#[derive(Clone, Debug)]
pub struct Rng(pub u64);

impl Rng {
    /// The generator of one case: independent streams per parser and case index.
    pub fn for_case(seed: u64, parser: &str, case: u64) -> Rng {
        let mut h = 0xcbf2_9ce4_8422_2325u64;
        for b in parser.bytes() {
            h = (h ^ b as u64).wrapping_mul(0x100_0000_01b3);
        }
        let mut r = Rng(seed ^ h ^ case.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        r.next();
        r
    }
    pub fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    pub fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
    pub fn index(&mut self, n: usize) -> usize {
        self.below(n as u64) as usize
    }
    pub fn chance(&mut self, p: f64) -> bool {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64 <= p
    }
    pub fn pick<'a, T>(&mut self, xs: &'a [T]) -> &'a T {
        &xs[self.index(xs.len())]
    }
}

/// One input: the files a parser reads (a single file for the text parsers).
#[derive(Clone, Debug, Default)]
pub struct Case {
    pub files: Vec<(String, Vec<u8>)>,
    /// What was done to the valid input, for the failure report.
    pub note: String,
}

impl Case {
    pub fn text(name: &str, text: impl Into<Vec<u8>>, note: impl Into<String>) -> Case {
        Case { files: vec![(name.to_string(), text.into())], note: note.into() }
    }
    /// Write the files into `dir` (replacing what is there).
    pub fn write_to(&self, dir: &Path) -> std::io::Result<()> {
        std::fs::create_dir_all(dir)?;
        for (name, bytes) in &self.files {
            std::fs::write(dir.join(name), bytes)?;
        }
        Ok(())
    }
}

/// A parser under test.
pub trait Target {
    fn name(&self) -> &'static str;
    /// The input of one case, from its own generator.
    fn generate(&mut self, rng: &mut Rng) -> Case;
    /// Feed the input to the parser (and to whatever uses a successful parse). Err is the
    /// parser's error text: an expected outcome for hostile input.
    fn run(&mut self, case: &Case) -> Result<(), String>;
    /// Words of which the error text of a file parser must contain one (the files' names);
    /// empty for text parsers.
    fn error_must_name(&self) -> &'static [&'static str] {
        &[]
    }
}

/// What one parser did over a run (or a part of it, in a child).
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct Stats {
    pub parser: String,
    pub cases: u64,
    pub accepted: u64,
    pub rejected: u64,
    pub panics: u64,
    /// The child died (abort: a refused huge allocation, a stack overflow, ...).
    pub crashes: u64,
    pub hangs: u64,
    /// Cases that ran in a child that then died, after its last stats snapshot: counted, their
    /// outcome unknown.
    pub outcome_lost: u64,
    /// Rejections whose error text does not name the file read.
    pub errors_not_naming_file: u64,
    pub distinct_errors: usize,
    pub seconds: f64,
    /// The first case index not yet run (for a child's snapshots).
    #[serde(default)]
    pub next: u64,
    /// Up to 5 failures of each kind (panic, crash, hang, unnamed file): case index, kind, detail, saved input.
    pub failures: Vec<Failure>,
    /// Error texts with digits blanked (for the distinct count; not in the JSON report).
    #[serde(default, skip_serializing_if = "BTreeSet::is_empty")]
    pub error_kinds: BTreeSet<String>,
}

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct Failure {
    pub case: u64,
    pub kind: String,
    pub detail: String,
    pub note: String,
    pub saved: String,
}

/// An error text as an error kind: digits and quoted values blanked, first 160 characters.
fn error_kind(e: &str) -> String {
    let mut out = String::new();
    let mut last_digit = false;
    for c in e.chars().take(400) {
        if c.is_ascii_digit() {
            if !last_digit {
                out.push('#');
            }
            last_digit = true;
        } else {
            last_digit = false;
            out.push(c);
        }
    }
    // Paths of per-case temporary directories differ; keep the file name only.
    out.chars().take(160).collect()
}

/// The last panic's message and location, recorded by the quiet hook instead of printed.
static LAST_PANIC: Mutex<Option<String>> = Mutex::new(None);

/// Replace the panic hook with one that only records (cases would otherwise flood stderr).
pub fn silence_panics() {
    std::panic::set_hook(Box::new(|info| {
        let msg = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "(non-string panic payload)".into());
        let at = info.location().map_or(String::new(), |l| format!(" at {}:{}:{}", l.file(), l.line(), l.column()));
        // A panic inside std (capacity overflow, slice index) says little: add lmac's frames.
        let bt = std::backtrace::Backtrace::force_capture().to_string();
        let frames: Vec<&str> = bt
            .lines()
            .map(str::trim)
            .filter(|l| l.contains("lmac_") && !l.contains("lmac_e2e") && !l.contains("lmac_fuzz"))
            .take(3)
            .collect();
        let at = if frames.is_empty() { at } else { format!("{at} | {}", frames.join(" | ")) };
        if let Ok(mut last) = LAST_PANIC.lock() {
            *last = Some(format!("{msg}{at}"));
        }
    }));
}

/// Save a failing case under `out/<parser>-case<i>/` and describe it.
pub fn save_failure(out: &Path, parser: &str, index: u64, kind: &str, detail: String, case: &Case) -> Failure {
    let dir = out.join(format!("{parser}-case{index}"));
    let saved = match case.write_to(&dir) {
        Ok(()) => {
            let _ = std::fs::write(dir.join("NOTE.txt"), format!("{kind}: {detail}\nmutation: {}\n", case.note));
            dir.display().to_string()
        }
        Err(e) => format!("(not saved: {e})"),
    };
    Failure { case: index, kind: kind.into(), detail, note: case.note.clone(), saved }
}

/// Run cases `from..to` in this process, writing the index of the case under way to `progress`
/// (8 bytes, little-endian) before each, so a supervisor knows which case killed or hung us.
pub fn run_range(
    target: &mut dyn Target,
    seed: u64,
    from: u64,
    to: u64,
    budget: Option<Duration>,
    progress: Option<&Path>,
    out: &Path,
    snapshot: Option<&Path>,
) -> Stats {
    use std::os::unix::fs::FileExt;
    let progress = progress.map(|p| std::fs::OpenOptions::new().create(true).write(true).truncate(false).open(p).expect("progress file"));
    let mut st = Stats { parser: target.name().to_string(), ..Default::default() };
    let started = Instant::now();
    let mut last_snapshot = Instant::now();
    st.next = from;
    for i in from..to {
        if budget.is_some_and(|b| started.elapsed() > b) {
            break;
        }
        // The stats so far, so a supervisor keeps them when a later case kills us.
        if let Some(p) = snapshot.filter(|_| last_snapshot.elapsed() > Duration::from_millis(20)) {
            write_stats(p, &mut st, started);
            last_snapshot = Instant::now();
        }
        // Generating is not the parser's time: the watchdog ignores it.
        if let Some(f) = &progress {
            let _ = f.write_at(&((i + 1) | GENERATING).to_le_bytes(), 0);
        }
        let mut rng = Rng::for_case(seed, target.name(), i);
        let case = target.generate(&mut rng);
        if let Some(f) = &progress {
            let _ = f.write_at(&(i + 1).to_le_bytes(), 0);
        }
        st.cases += 1;
        let outcome = catch_unwind(AssertUnwindSafe(|| target.run(&case)));
        match outcome {
            Ok(Ok(())) => st.accepted += 1,
            Ok(Err(e)) => {
                st.rejected += 1;
                let words = target.error_must_name();
                if !words.is_empty() && !words.iter().any(|w| e.contains(w)) {
                    st.errors_not_naming_file += 1;
                    if keep(&st.failures, "error does not name the file") {
                        st.failures.push(save_failure(out, target.name(), i, "error does not name the file", e.clone(), &case));
                    }
                }
                if st.error_kinds.len() < 100_000 {
                    st.error_kinds.insert(error_kind(&e));
                }
            }
            Err(_) => {
                st.panics += 1;
                let detail = LAST_PANIC.lock().ok().and_then(|mut l| l.take()).unwrap_or_default();
                if keep(&st.failures, "panic") {
                    st.failures.push(save_failure(out, target.name(), i, "panic", detail, &case));
                }
            }
        }
        st.next = i + 1;
    }
    if let Some(p) = snapshot {
        write_stats(p, &mut st, started);
    }
    st
}

/// Write the stats atomically (a reader never sees half a file).
fn write_stats(p: &Path, st: &mut Stats, started: Instant) {
    st.seconds = started.elapsed().as_secs_f64();
    st.distinct_errors = st.error_kinds.len();
    let tmp = p.with_extension("tmp");
    if std::fs::write(&tmp, serde_json::to_vec(st).unwrap()).is_ok() {
        let _ = std::fs::rename(&tmp, p);
    }
}

/// Options of a supervised run of one parser.
pub struct Supervise<'a> {
    pub exe: &'a Path,
    pub parser: &'a str,
    pub seed: u64,
    pub cases: u64,
    pub budget: Option<Duration>,
    pub hang: Duration,
    pub out: &'a Path,
}

/// Run one parser's cases in child processes (`exe --child ...`), restarting past any case that
/// crashed or hung the child; the parent rebuilds such a case's input to save it.
pub fn supervise(o: &Supervise, target: &mut dyn Target) -> Stats {
    let mut total = Stats { parser: o.parser.to_string(), ..Default::default() };
    let started = Instant::now();
    let progress = o.out.join(format!(".{}.progress", o.parser));
    let stats_path = o.out.join(format!(".{}.stats.json", o.parser));
    let stderr_path = o.out.join(format!("{}.child-stderr.txt", o.parser));
    let mut from = 0u64;
    while from < o.cases {
        let left = o.budget.map(|b| b.saturating_sub(started.elapsed()));
        if left.is_some_and(|l| l.is_zero()) {
            break;
        }
        let _ = std::fs::write(&progress, 0u64.to_le_bytes());
        let _ = std::fs::remove_file(&stats_path);
        let mut cmd = std::process::Command::new(o.exe);
        cmd.args(["--child", "--parser", o.parser, "--seed", &o.seed.to_string()]);
        cmd.args(["--from", &from.to_string(), "--cases", &o.cases.to_string()]);
        cmd.arg("--out").arg(o.out).arg("--progress").arg(&progress).arg("--stats").arg(&stats_path);
        if let Some(l) = left {
            cmd.args(["--seconds", &format!("{:.3}", l.as_secs_f64())]);
        }
        let stderr = std::fs::File::create(&stderr_path).expect("child stderr file");
        cmd.stdout(std::process::Stdio::null()).stderr(stderr);
        let mut child = cmd.spawn().expect("cannot start the fuzz child");
        // Watchdog: the case under way must change at least every `hang`.
        let (mut seen, mut since) = (u64::MAX, Instant::now());
        let (status, hung) = loop {
            if let Some(s) = child.try_wait().expect("waiting for the child") {
                break (Some(s), false);
            }
            let now = read_progress_raw(&progress);
            if now != seen || now & GENERATING != 0 {
                (seen, since) = (now, Instant::now());
            } else if since.elapsed() > o.hang {
                let _ = child.kill();
                let _ = child.wait();
                break (None, true);
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        remove_scratch_dirs(child.id());
        let part: Option<Stats> = std::fs::read(&stats_path).ok().and_then(|b| serde_json::from_slice(&b).ok());
        let done_to = part.as_ref().map_or(from, |p| p.next);
        if let Some(p) = part {
            merge(&mut total, p);
        }
        if status.is_some_and(|s| s.success()) {
            break;
        }
        if !hung && read_progress(&progress) == 0 {
            // Died before its first case: its set-up is broken, and restarting cannot help.
            let tail = std::fs::read_to_string(&stderr_path).unwrap_or_default();
            total.crashes += 1;
            total.failures.push(Failure {
                case: from,
                kind: "crash".into(),
                detail: format!("the child died before its first case: {}", tail.trim()),
                note: String::new(),
                saved: String::new(),
            });
            break;
        }
        // The child died or hung in case `bad`: rebuild, save and count it, go on after it.
        let bad = read_progress(&progress).saturating_sub(1).max(done_to);
        // Cases after the last snapshot and before the bad one ran, but their outcome is lost.
        total.cases += bad - done_to;
        total.outcome_lost += bad - done_to;
        let mut rng = Rng::for_case(o.seed, o.parser, bad);
        let case = target.generate(&mut rng);
        let tail = stderr_summary(&std::fs::read_to_string(&stderr_path).unwrap_or_default());
        let (kind, detail) = if hung {
            total.hangs += 1;
            ("hang", format!("no progress for {:.1}s", o.hang.as_secs_f64()))
        } else {
            total.crashes += 1;
            ("crash", format!("child exited with {} ; stderr: {tail}", status.map_or("?".into(), |s| s.to_string())))
        };
        total.cases += 1;
        if keep(&total.failures, kind) {
            total.failures.push(save_failure(o.out, o.parser, bad, kind, detail, &case));
        }
        from = bad + 1;
    }
    let _ = std::fs::remove_file(&progress);
    let _ = std::fs::remove_file(&stats_path);
    if std::fs::metadata(&stderr_path).is_ok_and(|m| m.len() == 0) {
        let _ = std::fs::remove_file(&stderr_path);
    }
    total.seconds = started.elapsed().as_secs_f64();
    total.distinct_errors = total.error_kinds.len();
    total
}

/// The gist of a dead child's stderr: its message (e.g. "memory allocation of N bytes failed")
/// and the first lmac frames of the backtrace.
fn stderr_summary(text: &str) -> String {
    let mut parts: Vec<String> = text
        .lines()
        .filter(|l| !l.starts_with(' ') && !l.starts_with("note:") && !l.starts_with("stack backtrace"))
        .take(2)
        .map(str::to_string)
        .collect();
    let frames: Vec<&str> = text
        .lines()
        .map(str::trim)
        .filter(|l| l.contains("lmac_") && !l.contains("lmac_e2e") && !l.contains("lmac_fuzz"))
        .take(3)
        .collect();
    parts.extend(frames.iter().map(|f| f.to_string()));
    parts.join(" | ")
}

/// Set in the progress word while a case's input is being generated.
const GENERATING: u64 = 1 << 63;

fn read_progress_raw(p: &Path) -> u64 {
    std::fs::read(p).ok().and_then(|b| b.get(..8).map(|b| u64::from_le_bytes(b.try_into().unwrap()))).unwrap_or(0)
}

/// The 1-based index of the case under way (0: none yet).
fn read_progress(p: &Path) -> u64 {
    read_progress_raw(p) & !GENERATING
}

fn merge(total: &mut Stats, p: Stats) {
    total.cases += p.cases;
    total.accepted += p.accepted;
    total.rejected += p.rejected;
    total.panics += p.panics;
    total.errors_not_naming_file += p.errors_not_naming_file;
    total.outcome_lost += p.outcome_lost;
    for f in p.failures {
        if keep(&total.failures, &f.kind) {
            total.failures.push(f);
        }
    }
    total.error_kinds.extend(p.error_kinds);
}

/// Up to 5 failures of each kind are kept (and saved).
fn keep(failures: &[Failure], kind: &str) -> bool {
    failures.iter().filter(|f| f.kind == kind).count() < 5
}

/// Whether the parser's run found nothing wrong.
pub fn clean(s: &Stats) -> bool {
    s.panics == 0 && s.crashes == 0 && s.hangs == 0 && s.errors_not_naming_file == 0
}

/// The per-parser table.
pub fn print_table(out: &mut impl Write, all: &[Stats]) -> std::io::Result<()> {
    writeln!(
        out,
        "{:<11} {:>9} {:>9} {:>9} {:>7} {:>7} {:>6} {:>9} {:>9} {:>9}",
        "parser", "cases", "accepted", "rejected", "panics", "crashes", "hangs", "unnamed", "distinct", "seconds"
    )?;
    for s in all {
        writeln!(
            out,
            "{:<11} {:>9} {:>9} {:>9} {:>7} {:>7} {:>6} {:>9} {:>9} {:>9.1}",
            s.parser, s.cases, s.accepted, s.rejected, s.panics, s.crashes, s.hangs, s.errors_not_naming_file, s.distinct_errors, s.seconds
        )?;
        for f in &s.failures {
            writeln!(out, "  {} case {}: {}: {} (input saved in {})", s.parser, f.case, f.kind, f.detail, f.saved)?;
        }
    }
    Ok(())
}

/// Remove the scratch directories of a (finished or killed) child.
pub fn remove_scratch_dirs(pid: u32) {
    let suffix = format!("-{pid}");
    if let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            if name.starts_with("lmac-fuzz-") && name.ends_with(&suffix) {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
    }
}

/// A scratch directory for one parser's per-case files (removed by the supervisor).
pub fn scratch_dir(tag: &str) -> PathBuf {
    use std::os::unix::fs::DirBuilderExt;
    let d = std::env::temp_dir().join(format!("lmac-fuzz-{tag}-{}", std::process::id()));
    // A leftover of an earlier process with this pid goes (a symlink itself, not its target);
    // then one mkdir, 0700, which fails rather than reuse a name another user planted meanwhile.
    let _ = std::fs::remove_dir_all(&d);
    if let Err(e) = std::fs::DirBuilder::new().mode(0o700).create(&d) {
        panic!("creating the scratch directory {}: {e}", d.display());
    }
    d
}
