//! End-to-end tests: see pipeline.rs and schemas.rs; Python tests in tests/python. The parser
//! fuzzer `lmac-fuzz` (src/bin) is built on [`fuzz`].

pub mod fuzz;
