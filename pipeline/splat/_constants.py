"""The compositing rules of 3DGS (Kerbl et al. 2023), shared by every backend.

A Gaussian is composited at a pixel only if its alpha reaches ``ALPHA_MIN``; alpha is capped at ``ALPHA_MAX``;
a pixel stops at the first Gaussian whose inclusion would drop its transmittance below ``T_MIN`` (that Gaussian
is not composited).

The numba kernels bake these values in when compiled; their on-disk cache does not notice edits here, so delete
``pipeline/splat/__pycache__/*.nb*`` after changing one.
"""

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
# The projected footprint is cut where alpha < ALPHA_MIN, but never beyond this many standard deviations
# (gsplat's constant; equal to sqrt(2 ln 255), i.e. the opacity-1 cut).
MAX_EXTENT_SIGMAS = 3.33
# Tile edge of the cpu backend, in pixels (8x8 measured faster than 16x16; docs/DECISIONS.md, "Numbers behind code
# comments").
CPU_TILE = 8
