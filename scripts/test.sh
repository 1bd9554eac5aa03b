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
# The guide is an mdBook (docs/); tests/python/test_docs.py builds it and checks its links.
if ! command -v mdbook >/dev/null 2>&1 && [ ! -x "$HOME/.cargo/bin/mdbook" ]; then
  echo "[test] installing mdbook (cargo install, about 5 minutes)"
  cargo install mdbook --version 0.5.4 --locked --no-default-features -q
fi
echo "[test] pytest"
PYTHONPATH="$ROOT/env-server" "$ROOT/.venv/bin/python" -m pytest tests/python -q
