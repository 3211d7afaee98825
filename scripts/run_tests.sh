#!/usr/bin/env bash
# Set up (idempotent) and run the unit suite. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"  # see recon/__init__.py
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"  # see tests/conftest.py
exec .venv/bin/python -m pytest -q -m "not slow and not slurm" -p no:cacheprovider "$@"
