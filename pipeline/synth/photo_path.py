"""Survey camera path of the "photo" scene family: lawnmower lines at varying altitude plus an oblique pass.

Unlike :mod:`.path` (fixed 2 m altitude, two rows, one 40° forward pass crabbing sideways), this is
shaped like a real ROV photogrammetry survey:

- Downward-looking lawnmower lines (boustrophedon along ±x, 1–3 lines depending on the view count). Each line
  has its own altitude, which also drifts along the line (the pilot follows the seabed roughly), all kept in
  ``altitude_range``.
- A forward-looking oblique pass flown along +x after the lines, low in the altitude range: the pitch sweeps
  from the steep to the shallow end of ``pitch_range_deg`` (±2° jitter) while the optical axis's ground point
  moves across the surveyed strip, so the lower halves of the frames overlap the downward views and
  consecutive oblique frames overlap each other (SfM needs both to register the pass).
- Seeded jitter: ±3 cm position, ±2° roll/pitch, ±3° yaw on the lines; ±5 cm, ±1.5°, ±4° on the pass.

World: metres, z up, seabed near z = 0. Poses are (R cam_from_world, camera centre).
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.synth.path import look_rotation


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation matrix about a unit axis."""
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def _attitude(forward: np.ndarray, up_hint: np.ndarray, rng: np.random.Generator, yaw_deg: float,
              tilt_deg: float) -> np.ndarray:
    """cam_from_world rotation looking along ``forward`` (image up towards ``up_hint``), with seeded yaw
    (about world z) and small roll/pitch (about the camera's own axes) jitter."""
    yaw = _rot(np.array([0.0, 0.0, 1.0]), math.radians(rng.uniform(-yaw_deg, yaw_deg)))
    r = look_rotation(yaw @ forward, yaw @ up_hint)
    roll = _rot(np.array([0.0, 0.0, 1.0]), math.radians(rng.uniform(-tilt_deg, tilt_deg)))  # camera z
    pitch = _rot(np.array([1.0, 0.0, 0.0]), math.radians(rng.uniform(-tilt_deg, tilt_deg)))  # camera x
    return roll @ pitch @ r


def photo_survey_path(n_views: int, rng: np.random.Generator, *, altitude_range: tuple[float, float],
                      line_step: float, line_spacing: float, oblique_fraction: float,
                      pitch_range_deg: tuple[float, float]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera poses (R cam_from_world [3, 3], centre [3]): lawnmower lines, then the oblique pass.

    Args:
        n_views: total number of views (≥ 1).
        altitude_range: (min, max) camera height above z = 0, metres.
        line_step: metres between consecutive views along a line.
        line_spacing: metres between lawnmower lines.
        oblique_fraction: share of views in the oblique pass (none below 4 views).
        pitch_range_deg: (min, max) downward pitch of the oblique views' optical axis, degrees.
    """
    if n_views < 1:
        raise ValueError(f"need at least one view, got {n_views}")
    lo, hi = altitude_range
    if not 0 < lo <= hi:
        raise ValueError(f"altitude range must be 0 < min <= max, got {altitude_range}")
    n_obl = int(round(n_views * oblique_fraction)) if n_views >= 4 else 0
    n_down = n_views - n_obl
    rows = 3 if n_down >= 12 else 2 if n_down >= 6 else 1
    per_row = math.ceil(n_down / rows)
    half_len = 0.5 * (per_row - 1) * line_step
    poses = []
    for row in range(rows):
        base = rng.uniform(lo + 0.25 * (hi - lo), hi - 0.25 * (hi - lo))  # this line's altitude
        drift = rng.uniform(0.1, 0.3) * (hi - lo)  # how far it wanders along the line
        phase = rng.uniform(0, 2 * math.pi)
        n_here = min(per_row, n_down - row * per_row)
        heading = np.array([1.0, 0.0, 0.0]) if row % 2 == 0 else np.array([-1.0, 0.0, 0.0])
        y = (row - (rows - 1) / 2) * line_spacing
        for k in range(n_here):
            x = (k - (per_row - 1) / 2) * line_step * heading[0]
            alt = float(np.clip(base + drift * math.sin(2 * math.pi * x / 3.0 + phase), lo, hi))
            r = _attitude(np.array([0.0, 0.0, -1.0]), heading, rng, yaw_deg=3.0, tilt_deg=2.0)
            poses.append((r, np.array([x, y, alt]) + rng.uniform(-0.03, 0.03, 3)))
    # The oblique pass: one smooth forward run along +x (pitch sweeping from steep to shallow, altitude in
    # the lower part of the range, one lateral offset), so consecutive oblique views overlap each other as
    # well as the downward views under the lower halves of their frames.
    y_pass = rng.uniform(-0.25, 0.25) * (rows - 1) * line_spacing
    alt_pass = rng.uniform(lo, lo + 0.4 * (hi - lo))
    p_lo, p_hi = pitch_range_deg
    for k in range(n_obl):
        f = k / max(1, n_obl - 1)
        pitch = math.radians(float(np.clip(p_hi + (p_lo - p_hi) * f + rng.uniform(-2.0, 2.0), p_lo, p_hi)))
        alt = float(np.clip(alt_pass + rng.uniform(-0.1, 0.1) * (hi - lo), lo, hi))
        x_aim = -half_len + 0.3 + (2 * half_len + 0.6) * f  # where the optical axis meets z = 0
        fwd = np.array([math.cos(pitch), 0.0, -math.sin(pitch)])
        r = _attitude(fwd, np.array([0.0, 0.0, 1.0]), rng, yaw_deg=4.0, tilt_deg=1.5)
        centre = np.array([x_aim - alt / math.tan(pitch), y_pass, alt]) + rng.uniform(-0.05, 0.05, 3)
        poses.append((r, centre))
    return poses
