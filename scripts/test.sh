#!/usr/bin/env bash
# Set up everything (idempotent) and run the whole test suite: Rust unit, integration and
# end-to-end tests (real processes, real shared memory, real environments), then the Python tests.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
export LMAC_WITH_GRF="${LMAC_WITH_GRF:-1}"
bash scripts/setup.sh
echo "[test] cargo test (release)"
cargo test --release --workspace -q 2>&1 | grep -v '^\s*$' | grep -v '^running 0 tests' | grep -v 'test result: ok. 0 passed'
echo "[test] pytest"
PYTHONPATH="$ROOT/env-server" "$ROOT/.venv/bin/python" -m pytest tests/python -q
