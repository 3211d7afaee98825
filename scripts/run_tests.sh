#!/usr/bin/env bash
# Set up (idempotent) and run the unit suite. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"  # see recon/__init__.py
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"  # see tests/conftest.py
# The tests run in parallel processes (pytest-xdist), one test file per process at a time, so a
# file's module fixtures are made once and its tests run in order; inputs shared between files are
# made once per run (tests/_shared.py). One process per core, at most 4: many tests are
# single-threaded (SfM on one thread, drjit on one thread where bit equality is tested, Snakemake
# and its stage processes). RECON_TEST_WORKERS=0 runs them in this process.
workers="${RECON_TEST_WORKERS:-$(( $(nproc) < 4 ? $(nproc) : 4 ))}"
exec .venv/bin/python -m pytest -q -m "not slow and not slurm" -p no:cacheprovider -n "$workers" --dist loadfile "$@"
