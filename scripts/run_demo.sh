#!/usr/bin/env bash
# Set up (idempotent) and run the whole pipeline over the bundled demo capture(s).
# Extra arguments go to snakemake, e.g. `bash scripts/run_demo.sh --config preset=balanced`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"  # see recon/__init__.py
exec .venv/bin/snakemake --cores 2 all --config captures=captures results=results preset=draft "$@"
