"""The export stage: the reconstruction PLY and the per-view images."""
