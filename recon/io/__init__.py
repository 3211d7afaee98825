"""File formats and conventions shared by every stage (images, cameras, meshes, atomic output)."""
