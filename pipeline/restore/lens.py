"""Where each original photo pixel looks: its undistorted normalised ray (xn, yn) and its position (u, v) in the
render camera.

The exact map undistorts every pixel with pycolmap (iterative for radial models): :func:`exact_rays`, the slow
twin. The fast path (:class:`LensGrid`) undistorts exactly only on a coarse grid (every ``step``-th pixel centre
plus the last row and column) and interpolates bilinearly; distortion is smooth. The step is chosen per camera:
starting at ``MAX_STEP`` it halves until the interpolation error at every cell's centre (where bilinear
interpolation errs most), measured against the exact undistortion in photo pixels (|Δxn|·f), is below
``tol`` (0.005 px). Measured errors: docs/DECISIONS.md, "Restoring the originals".
"""

from __future__ import annotations

import numpy as np

from pipeline.restore._kernels import interp_grid_rows
from pipeline.scene.records import Camera, LensCamera

MAX_STEP = 16
DEFAULT_TOL = 0.005  # photo pixels


def exact_rays(lens: LensCamera, y0: int, y1: int, x0: int = 0, x1: int | None = None) -> tuple[np.ndarray, ...]:
    """Slow twin: (xn, yn) float64 [y1−y0, x1−x0] each, every pixel centre of rows [y0, y1) and columns [x0, x1)
    undistorted exactly by pycolmap."""
    x1 = lens.width if x1 is None else x1
    xs, ys = np.meshgrid(np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5)
    n = lens.colmap().cam_from_img(np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64))
    return n[:, 0].reshape(xs.shape), n[:, 1].reshape(xs.shape)


def _nodes(n: int, step: int) -> np.ndarray:
    """Grid node indices along one axis: 0, step, 2·step, ... and always n − 1. [K] int"""
    return np.unique(np.r_[np.arange(0, n, step), n - 1]).astype(np.int64)


def _undistort(cam, xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact (xn, yn) float64 [len(ys), len(xs)] each at the grid of pixel-centre coordinates xs × ys."""
    gx, gy = np.meshgrid(xs, ys)
    n = cam.cam_from_img(np.stack([gx.ravel(), gy.ravel()], 1).astype(np.float64))
    if not np.isfinite(n).all():
        raise ValueError(f"{cam.model} {cam.params}: undistortion failed at some grid nodes")
    return np.ascontiguousarray(n[:, 0].reshape(gx.shape)), np.ascontiguousarray(n[:, 1].reshape(gx.shape))


def _centre_error(cam, cols: np.ndarray, rows: np.ndarray, xn: np.ndarray, yn: np.ndarray) -> float:
    """Max |interpolated − exact| of xn, yn at the centre of every grid cell (normalised units)."""
    ex, ey = _undistort(cam, (cols[:-1] + cols[1:]) / 2 + 0.5, (rows[:-1] + rows[1:]) / 2 + 0.5)
    ix = (xn[:-1, :-1] + xn[:-1, 1:] + xn[1:, :-1] + xn[1:, 1:]) / 4
    iy = (yn[:-1, :-1] + yn[:-1, 1:] + yn[1:, :-1] + yn[1:, 1:]) / 4
    return float(max(np.abs(ix - ex).max(initial=0.0), np.abs(iy - ey).max(initial=0.0)))


def _cells(n: int, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each index 0..n−1: (its cell i [n] int64, fraction t [n] float64) with nodes[i] ≤ idx ≤ nodes[i+1]."""
    idx = np.arange(n)
    i = np.clip(np.searchsorted(nodes, idx, side="right") - 1, 0, max(len(nodes) - 2, 0))
    span = np.maximum(nodes[np.minimum(i + 1, len(nodes) - 1)] - nodes[i], 1)
    return i.astype(np.int64), ((idx - nodes[i]) / span).astype(np.float64)


class LensGrid:
    """The exact undistortion on a coarse grid of one photo, interpolated per row band on request.

    Args:
        lens: the photo's camera (width and height ≥ 2).
        step: grid spacing in photo pixels (the last row and column are always nodes); None: chosen as above.
        tol: the error bound that chooses the step, photo pixels.

    Attributes: ``step``, ``error`` (the measured cell-centre error in photo pixels; 0 when step is 1).
    """

    def __init__(self, lens: LensCamera, step: int | None = None, tol: float = DEFAULT_TOL):
        self.lens = lens
        cam = lens.colmap()
        f = float(cam.mean_focal_length())
        for s in ([step] if step else [MAX_STEP // 2**i for i in range(MAX_STEP.bit_length())]):
            self.step = s
            self.rows, self.cols = _nodes(lens.height, s), _nodes(lens.width, s)
            self.xn, self.yn = _undistort(cam, self.cols + 0.5, self.rows + 0.5)  # [Kr, Kc] float64 each
            self.error = _centre_error(cam, self.cols, self.rows, self.xn, self.yn) * f if s > 1 else 0.0
            if self.error < tol:
                break
        self._col_cell, self._col_t = _cells(lens.width, self.cols)
        self._row_cell, self._row_t = _cells(lens.height, self.rows)

    def rays(self, y0: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
        """(xn, yn) float32 [y1−y0, W] each: the undistorted normalised rays of rows [y0, y1)."""
        return interp_grid_rows(self.xn, self.yn, self._row_cell[y0:y1], self._row_t[y0:y1], self._col_cell,
                                self._col_t)


def render_position(xn: np.ndarray, yn: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) [same shape as xn]: where rays (xn, yn) land in the PINHOLE ``camera`` (pixel-centre convention)."""
    return camera.fx * xn + camera.cx, camera.fy * yn + camera.cy
