//! End-to-end tests: see pipeline.rs and schemas.rs; Python tests in tests/python.
