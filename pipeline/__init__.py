"""dualphys pipeline: the science (scenes, SfM, splatting, medium model, training).

`import pipeline` needs only numpy and torch; pycolmap, OpenImageIO, numba and gsplat load lazily inside the
functions that use them (no import-time side effects).
"""

__version__ = "0.1.0"
