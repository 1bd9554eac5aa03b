//! lmac trainer: episode assembly from shared-memory slots, acting, learning, and the CLI.
pub mod dataset;
pub mod design;
pub mod episode;
pub mod faults;
pub mod learn;
pub mod pipeline;
pub mod run_dir;
pub mod safe_fs;
pub mod stats;
pub mod supervisor;
pub mod tensorboard;
pub mod train;

/// Keep freed memory in the heap instead of handing it back to the kernel (glibc `mallopt`).
///
/// An update allocates and frees tens of megabytes of tensors; with glibc's defaults, blocks
/// above the mmap threshold come back as fresh pages that fault and get zeroed on first write
/// every update. Measured on the learner bench (issue 16, 1o_10b_vs_1r's shape, VDN): 82 -> 71
/// ms per update; the fused GRU's forward alone 21 -> 10 ms. Costs resident memory (up to the
/// trim threshold, 1 GiB, stays mapped). Called once at start by the `lmac` binary and the
/// learner benches; a no-op off glibc.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters; called before heavy allocation starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 256 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
        libc::mallopt(libc::M_TOP_PAD, 64 << 20);
    }
}
