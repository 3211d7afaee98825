"""recon: flash photos of an object to a relightable 3D asset.

Analysis by synthesis after Luan, Zhao, Bala, Dong, "Unified Shape and SVBRDF Recovery
using Differentiable Monte Carlo Rendering" (EGSR 2021). Each pipeline stage is a plain
function in a submodule taking paths and a frozen settings dataclass; the Snakemake
workflow only adapts them.
"""

__version__ = "0.1.0"
