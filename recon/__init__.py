"""recon: flash photos of an object to a relightable 3D asset.

Analysis by synthesis after Luan, Zhao, Bala, Dong, "Unified Shape and SVBRDF Recovery
using Differentiable Monte Carlo Rendering" (EGSR 2021). Each pipeline stage is a plain
function in a submodule taking paths and a frozen settings dataclass; the Snakemake
workflow only adapts them.
"""

__version__ = "0.1.0"

import os as _os

# The optimizer alternates drjit (its own thread pool) and torch (OpenMP) on the same cores.
# libgomp's default "active" wait makes idle OpenMP threads spin, and with any other load on
# the machine torch's parallel regions then stall on descheduled threads: measured on 2 cores
# under load, a 30-iteration optimize took 91.5 s with the default and 9.9 s with PASSIVE (the
# "loss" phase 58.8 s -> 0.3 s). Must be set before torch is imported; a user's setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
