"""Synthetic captures: procedural objects, baked SVBRDF maps, rendered views, sensor model."""
