#!/usr/bin/env bash
# Run by `snakemake --use-conda` inside the environment it has just made from recon.yaml, from
# Snakemake's working directory: installs this checkout's recon package into it (editable, so
# the environment follows the checkout). The dependencies came pinned with recon.yaml.
set -euo pipefail
if ! grep -qs '^name = "recon"$' pyproject.toml; then
  echo "recon.post-deploy.sh: $(pwd) is not the recon repository (no pyproject.toml naming recon);" \
    "run snakemake from the repository root" >&2
  exit 1
fi
python -m pip install --no-deps -e .
