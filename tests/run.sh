#!/usr/bin/env bash
# The README's test command. On a fresh clone it builds the CLI, lets `hifar setup` create the
# pinned Python environment, then runs the Python tests and the CLI's integration tests.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD

# JAX's persistent compilation cache lives in a directory the tests own, so a second run of the
# suite skips most XLA compiles.
export JAX_COMPILATION_CACHE_DIR="$root/tests/.cache/jax"
export JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0
export JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES=0
export HIFAR_VENV="${HIFAR_VENV:-$root/.venv}"
mkdir -p "$JAX_COMPILATION_CACHE_DIR"

cargo build --release --locked
"$root/target/release/hifar" setup

# Most of the Python suite's time is XLA compiling, one core per compile: one pytest worker per
# core (at most 4, each holds its own JAX). On two idle cores: 7 min against 23 min with one
# worker. --dist loadfile keeps a file's tests in one worker, so its module
# fixtures are built once.
"$HIFAR_VENV/bin/python" -m pytest -q -n auto --maxprocesses 4 --dist loadfile --durations=10 \
  tests/python
cargo test --release --locked
