#!/usr/bin/env bash
# The checks the field's model projects run (CI calls this after set-up): ruff on the Python,
# snakefmt on the Snakemake files, and Snakemake's own linter on the workflow (which needs a
# config: the bundled captures, and a results folder that is removed afterwards).
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check recon tests bench workflow tools
.venv/bin/snakefmt --check Snakefile workflow/rules/
results=$(mktemp -d -t recon-lint.XXXXXX)
trap 'rm -rf "$results"' EXIT
out=$(.venv/bin/snakemake --lint --config captures=captures results="$results" 2>&1) || { echo "$out"; exit 1; }
echo "$out" | grep -q "Congratulations, your workflow is in a good condition" || { echo "$out"; exit 1; }
echo "[lint] ruff, snakefmt and snakemake --lint clean"
