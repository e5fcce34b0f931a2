"""Gaussian splatting: parameters, rasterization backends, densification glue, PLY.

Import the pieces from their modules (``from pipeline.splat.rasterize import rasterize``). This package file
stays empty on purpose: importing it must not pull in numba (compiled lazily on first use of the ``cpu``
backend) or gsplat (whose CUDA extension builds on first use).
"""
