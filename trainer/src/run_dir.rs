//! Names of runs: the time stamp of a run directory and the short id of a pipeline run (its
//! shared memory and iceoryx2 services carry it).

/// UTC time as `YYYYMMDD-HHMMSS`, the name of a training group or design directory.
pub fn stamp() -> String {
    chrono::Utc::now().format("%Y%m%d-%H%M%S").to_string()
}

/// 8 hex digits from the clock and the process id: unique among the runs of one machine.
pub fn run_id() -> String {
    let t = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
    format!("{:08x}", (t as u64 ^ ((std::process::id() as u64) << 32)) as u32)
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_stamp_is_a_sortable_utc_time() {
        let s = super::stamp();
        assert_eq!(s.len(), 15, "{s}");
        assert_eq!(&s[8..9], "-");
        assert!(s[..8].chars().chain(s[9..].chars()).all(|c| c.is_ascii_digit()), "{s}");
        assert!(s.as_str() > "20260101-000000");
    }
}
