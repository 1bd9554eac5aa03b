//! `lmac-fuzz`: feeds N seeded hostile inputs to each of lmac's parsers and reports per parser
//! the cases, panics, crashes (aborts), hangs, distinct errors and time; exits non-zero when any
//! parser panicked, crashed, hung or gave an error that does not name its file. Failing inputs
//! are saved under `--out`.
//!
//! `cargo run --release -p lmac-e2e --bin lmac-fuzz -- --parser all --cases 1000000`
//!
//! Each parser runs in a child process (this binary with `--child`) watched by the parent, so an
//! abort or a hang is caught too. Allocations over `--alloc-cap-mib` are refused (the child then
//! aborts, and the parent reports the case): a reader must check sizes before it allocates.

use clap::Parser;
use lmac_e2e::fuzz::{self, targets};
use std::alloc::{GlobalAlloc, Layout, System};
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

/// The system allocator with a ceiling per allocation: past it, allocation fails (and Rust
/// aborts), which turns "allocates what a corrupt header says" into a reported crash instead of a
/// machine brought to its knees.
struct CappedAlloc;

static ALLOC_CAP: AtomicUsize = AtomicUsize::new(usize::MAX);

unsafe impl GlobalAlloc for CappedAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if layout.size() > ALLOC_CAP.load(Ordering::Relaxed) {
            return std::ptr::null_mut();
        }
        System.alloc(layout)
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if layout.size() > ALLOC_CAP.load(Ordering::Relaxed) {
            return std::ptr::null_mut();
        }
        System.alloc_zeroed(layout)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > ALLOC_CAP.load(Ordering::Relaxed) {
            return std::ptr::null_mut();
        }
        System.realloc(ptr, layout, new_size)
    }
}

#[global_allocator]
static GLOBAL: CappedAlloc = CappedAlloc;

#[derive(Parser, Debug)]
#[command(about = "Fuzz lmac's parsers with seeded hostile inputs")]
struct Args {
    /// A parser (schema, config, protocol, llm_reply, dataset, checkpoint) or `all`; repeatable
    /// or comma-separated.
    #[arg(long, default_value = "all", value_delimiter = ',')]
    parser: Vec<String>,
    /// Inputs per parser.
    #[arg(long, default_value_t = 1_000_000)]
    cases: u64,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Time budget per parser in seconds (the run stops a parser early and reports the cases run).
    #[arg(long)]
    seconds: Option<f64>,
    /// An input that takes longer than this is a hang.
    #[arg(long, default_value_t = 2.0)]
    hang_secs: f64,
    /// Largest single allocation allowed, MiB.
    #[arg(long, default_value_t = 1024)]
    alloc_cap_mib: usize,
    /// Where failing inputs (and the JSON report, unless --json says otherwise) go.
    #[arg(long, default_value = "fuzz-out")]
    out: PathBuf,
    /// Write the JSON report here.
    #[arg(long)]
    json: Option<PathBuf>,
    #[arg(long, hide = true)]
    child: bool,
    #[arg(long, hide = true, default_value_t = 0)]
    from: u64,
    #[arg(long, hide = true)]
    progress: Option<PathBuf>,
    #[arg(long, hide = true)]
    stats: Option<PathBuf>,
}

fn main() {
    let a = Args::parse();
    ALLOC_CAP.store(a.alloc_cap_mib.saturating_mul(1 << 20), Ordering::Relaxed);
    if std::env::var_os("LMAC_SCHEMA_DIR").is_none() {
        std::env::set_var("LMAC_SCHEMA_DIR", concat!(env!("CARGO_MANIFEST_DIR"), "/../env-server/schemas"));
    }
    std::fs::create_dir_all(&a.out).unwrap_or_else(|e| panic!("cannot create {}: {e}", a.out.display()));
    let names: Vec<String> =
        if a.parser.iter().any(|p| p == "all") { targets::PARSERS.iter().map(|s| s.to_string()).collect() } else { a.parser.clone() };
    let budget = a.seconds.map(Duration::from_secs_f64);

    if a.child {
        let mut target = targets::make(&names[0]).unwrap_or_else(|e| panic!("setting up {}: {e}", names[0]));
        fuzz::silence_panics();
        let stats = a.stats.expect("--stats with --child");
        fuzz::run_range(target.as_mut(), a.seed, a.from, a.cases, budget, a.progress.as_deref(), &a.out, Some(&stats));
        return;
    }

    let exe = std::env::current_exe().expect("own path");
    let started = std::time::Instant::now();
    let mut all = Vec::new();
    for name in &names {
        let mut target = match targets::make(name) {
            Ok(t) => t,
            Err(e) => {
                eprintln!("lmac-fuzz: {e}");
                std::process::exit(2);
            }
        };
        let o = fuzz::Supervise {
            exe: &exe,
            parser: name,
            seed: a.seed,
            cases: a.cases,
            budget,
            hang: Duration::from_secs_f64(a.hang_secs),
            out: &a.out,
        };
        let st = fuzz::supervise(&o, target.as_mut());
        eprintln!("lmac-fuzz: {name}: {} cases in {:.1}s", st.cases, st.seconds);
        all.push(st);
    }
    // The parent's own targets (kept to rebuild failing cases) made scratch directories too.
    fuzz::remove_scratch_dirs(std::process::id());
    fuzz::print_table(&mut std::io::stdout(), &all).unwrap();
    // The distinct error kinds travelled from the children for counting; the report keeps counts.
    all.iter_mut().for_each(|s| s.error_kinds.clear());
    let report = serde_json::json!({
        "command": format!("lmac-fuzz --parser {} --cases {} --seed {}{}", names.join(","), a.cases, a.seed,
            a.seconds.map_or(String::new(), |s| format!(" --seconds {s}"))),
        "seed": a.seed,
        "cases_per_parser": a.cases,
        "seconds_budget_per_parser": a.seconds,
        "hang_secs": a.hang_secs,
        "alloc_cap_mib": a.alloc_cap_mib,
        "total_seconds": started.elapsed().as_secs_f64(),
        "parsers": all,
        "ring": "not fuzzed: the 24-byte slot message is a #[repr(C)] struct handed over by iceoryx2 as it is; there is no decoder",
    });
    let json_path = a.json.clone().unwrap_or_else(|| a.out.join("fuzz.json"));
    std::fs::write(&json_path, serde_json::to_string_pretty(&report).unwrap()).unwrap_or_else(|e| panic!("{}: {e}", json_path.display()));
    println!("report: {}", json_path.display());
    if !all.iter().all(fuzz::clean) {
        println!("FAILED: a parser panicked, crashed, hung or gave an error without its file name (inputs under {})", a.out.display());
        std::process::exit(1);
    }
}
