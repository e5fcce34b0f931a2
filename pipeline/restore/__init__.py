"""Restoring the user's original photos (issue 14): every original pixel, at the photo's own resolution and in
its own lens geometry, gets J = (I − B(r)) / A(r), with r the multi-view-consistent range of that pixel from
the reconstruction.

Modules (one job each): ``records`` (inputs), ``lens`` (photo pixel → render camera), ``sample`` (bilinear
sampling of render maps), ``guided`` (depth to full resolution along the photo's edges), ``medium``
(per-pixel coefficients from rendered A, B), ``dewater`` (the physics, gain cap, confidence), ``files`` (banded
read/write with metadata), ``frame`` (one whole frame in row bands). Rules: docs/DECISIONS.md, "Restoring the
originals".
"""
