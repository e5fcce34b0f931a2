"""ROV-like camera paths over the synthetic seabed (world: metres, z up, seabed near z = 0)."""

from __future__ import annotations

import math

import numpy as np


def look_rotation(forward: np.ndarray, up_hint: np.ndarray) -> np.ndarray:
    """cam_from_world rotation for a camera looking along ``forward`` with image-up towards ``up_hint``.

    Camera axes (COLMAP): x right, y down, z forward. Rows of the result are those axes in world coordinates.
    """
    z = forward / np.linalg.norm(forward)
    x = np.cross(z, up_hint)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def survey_path(
    n_views: int, kind: str, altitude: float, rng: np.random.Generator, step: float = 0.3
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera poses (R cam_from_world, centre) along a survey.

    - ``lawnmower``: downward-looking, two parallel rows flown in opposite directions (boustrophedon).
    - ``forward``: forward-looking (pitched 40° down) pass, crabbing sideways along the survey strip.
    - ``survey``: two thirds lawnmower, then one third forward pass: the usual ROV mix.
    Small seeded jitter in position (±2 cm) and attitude (±1.5°) makes it look flown, not drawn.
    """
    if n_views < 1:
        raise ValueError(f"need at least one view, got {n_views}")
    if kind == "survey":
        n_down = max(1, round(n_views * 2 / 3)) if n_views > 2 else n_views
        return _lawnmower(n_down, altitude, rng, step) + _forward(n_views - n_down, altitude, rng, step)
    if kind == "lawnmower":
        return _lawnmower(n_views, altitude, rng, step)
    if kind == "forward":
        return _forward(n_views, altitude, rng, step)
    raise ValueError(f"unknown path kind {kind!r}: use survey, lawnmower or forward")


def _jitter(r: np.ndarray, c: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    angles = np.deg2rad(rng.uniform(-1.5, 1.5, 3))
    rot = _euler(*angles)
    return rot @ r, c + rng.uniform(-0.02, 0.02, 3)


def _euler(a: float, b: float, c: float) -> np.ndarray:
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _lawnmower(n: int, altitude: float, rng: np.random.Generator, step: float):
    rows = 2 if n >= 6 else 1
    per_row = math.ceil(n / rows)
    row_gap = 0.42 * altitude
    poses = []
    for i in range(n):
        row, k = divmod(i, per_row)
        x = (k - (per_row - 1) / 2) * step
        if row % 2 == 1:
            x = -x  # fly back along the next row
        y = (row - (rows - 1) / 2) * row_gap
        heading = np.array([1.0, 0.0, 0.0]) if row % 2 == 0 else np.array([-1.0, 0.0, 0.0])
        r = look_rotation(np.array([0.0, 0.0, -1.0]), heading)
        poses.append(_jitter(r, np.array([x, y, altitude]), rng))
    return poses


def _forward(n: int, altitude: float, rng: np.random.Generator, step: float):
    poses = []
    pitch = math.radians(40.0)
    fwd = np.array([0.0, math.cos(pitch), -math.sin(pitch)])
    h = 0.75 * altitude
    y0 = -h / math.tan(pitch)  # the optical axis meets the seabed near y = 0, the lawnmower strip's middle
    for k in range(n):
        x = (k - (n - 1) / 2) * step
        r = look_rotation(fwd, np.array([0.0, 0.0, 1.0]))
        poses.append(_jitter(r, np.array([x, y0, h]), rng))
    return poses
