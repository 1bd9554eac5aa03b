//! `lmac clean`: list and remove what dead lmac runs left in shared memory (this user's only,
//! never a live run's); `lmac_shm_schema::leftovers` decides what is dead.

use anyhow::Result;
use clap::Args;
use lmac_shm_schema::leftovers::{self, Found, Kind};

#[derive(Args)]
pub(crate) struct CleanArgs {
    /// Only list what would be removed and what is kept, and why.
    #[arg(long)]
    dry_run: bool,
}

fn line(f: &Found) -> String {
    let kind = match f.kind {
        Kind::Slab => "slab",
        Kind::Node => "iceoryx2 node",
    };
    format!("{kind} {} (run {}): {}", f.name, f.run, f.why)
}

pub(crate) fn clean(a: CleanArgs) -> Result<i32> {
    let survey = leftovers::survey();
    for f in &survey.kept {
        println!("kept     {}", line(f));
    }
    if a.dry_run {
        for f in &survey.dead {
            println!("would remove {}", line(f));
        }
        return Ok(0);
    }
    let done = survey.remove();
    for f in &done.removed {
        println!("removed  {}", line(f));
    }
    for (f, e) in &done.failed {
        eprintln!("lmac: could not remove {}: {e}", line(f));
    }
    println!("{} removed, {} kept, {} failed", done.removed.len(), leftovers::survey().kept.len(), done.failed.len());
    Ok(if done.failed.is_empty() { 0 } else { 1 })
}
