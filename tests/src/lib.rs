//! End-to-end tests: see pipeline.rs, train_resume.rs and schemas.rs ([`harness`] is what they share); Python tests in tests/python. The parser
//! fuzzer `lmac-fuzz` (src/bin) is built on [`fuzz`].

pub mod fuzz;
pub mod harness;
