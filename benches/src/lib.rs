//! lmac's development tools, outside the library crates: the learner's benchmark (`learner`:
//! `lmac bench learner`, its shape ceiling and the PyTorch anchor), fault injection and
//! endurance runs (`faults`: `lmac chaos`, `lmac soak` and the process-tree helpers the
//! end-to-end tests use). The criterion benchmarks live in `benches/benches/`.

pub mod faults;
pub mod learner;
