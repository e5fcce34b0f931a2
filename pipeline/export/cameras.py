"""``output/cameras.json``: the registered training cameras, for the dashboard's 3D viewer.

Same world frame as ``reconstruction.ply`` (the SfM model's). Per camera: ``name``, ``position`` [3] (the centre),
``rotation`` [3][3] (world_from_cam, rows; camera axes as OpenCV/COLMAP: x right, y down in the image, z forward),
``forward`` and ``up`` [3] (world directions of the optical axis and of the image's up), ``fov_x_deg`` /
``fov_y_deg``, ``width`` / ``height`` / ``fx`` / ``fy`` / ``cx`` / ``cy`` at the training resolution, and
``median_depth``: the median camera-z of the Gaussians in front of it (where the viewer aims; null if none is).
Top level: ``extent`` (the cameras' bounding-box diagonal), ``count`` and ``display``: how the viewer shows the
PLY's colours, ``colour_space`` ("linear": the viewer encodes them to sRGB) and ``water`` (the homogeneous medium
``beta_D``, ``beta_B`` in 1/scene-unit and ``B_inf``, for its "with water" switch; null in mode 3dgs).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from pipeline.job.markers import atomic_write_text
from pipeline.scene.records import View

FORMAT = "dualphys-cameras/1"
_DEPTH_SAMPLE = 100_000  # Gaussians used for each camera's median depth (strided; the median needs no more)


def camera_record(view: View, means: np.ndarray | None = None) -> dict:
    """One camera as ``cameras.json`` lists it. ``means`` [N, 3] world points for the median depth."""
    cam = view.camera
    R = np.asarray(view.R, dtype=np.float64)  # [3, 3] cam_from_world
    rot = R.T  # world_from_cam: its columns are the camera axes in the world
    depth = None
    if means is not None and len(means):
        z = means @ R[2] + float(view.t[2])  # [N] camera-z
        z = z[z > 1e-6]
        depth = float(np.median(z)) if len(z) else None
    return {
        "name": view.name,
        "position": [float(v) for v in view.center],
        "rotation": [[float(v) for v in row] for row in rot],
        "forward": [float(v) for v in rot[:, 2]],
        "up": [float(-v) for v in rot[:, 1]],
        "fov_x_deg": math.degrees(2 * math.atan(cam.width / (2 * cam.fx))),
        "fov_y_deg": math.degrees(2 * math.atan(cam.height / (2 * cam.fy))),
        "width": int(cam.width),
        "height": int(cam.height),
        "fx": float(cam.fx),
        "fy": float(cam.fy),
        "cx": float(cam.cx),
        "cy": float(cam.cy),
        "median_depth": depth,
    }


def viewer_display(state: dict[str, Any], coefficients: dict | None) -> dict:
    """``display`` for a training checkpoint ``state`` and the medium's ``coefficients`` as training reported them
    (``MediumTerm.effective_coefficients``, the train result's ``medium``; None without a medium): the colour space
    and the water as one homogeneous medium (β_D the effective coefficient, the running mean over training views of
    eq. 5's w·β·(1 − γE)·T; the network medium's per-pixel terms are left out)."""
    water = None
    if coefficients:
        water = {k: [float(x) for x in np.ravel(coefficients[k])] for k in ("beta_D", "beta_B", "B_inf")}
    return {"colour_space": state["config"].get("colour_space", "srgb"), "water": water}


def cameras_document(views: Sequence[View], means: np.ndarray | None = None, display: dict | None = None) -> dict:
    """The whole ``cameras.json`` document for ``views`` (sorted by name), the Gaussians' ``means`` [N, 3] and
    ``display`` (:func:`viewer_display`; the PLY's colours as they are when None)."""
    if means is not None:
        means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
        if len(means) > _DEPTH_SAMPLE:
            means = means[:: math.ceil(len(means) / _DEPTH_SAMPLE)]
    ordered = sorted(views, key=lambda v: v.name)
    centres = np.array([v.center for v in ordered]).reshape(-1, 3)
    extent = float(np.linalg.norm(centres.max(0) - centres.min(0))) if len(centres) else 0.0
    return {
        "format": FORMAT,
        "frame": "the PLY's world; camera axes x right, y down, z forward (OpenCV/COLMAP)",
        "count": len(ordered),
        "extent": extent,
        "display": display or {"colour_space": "srgb", "water": None},
        "cameras": [camera_record(v, means) for v in ordered],
    }


def export_cameras(views: Sequence[View], means: np.ndarray | None, path: str | os.PathLike[str],
                   display: dict | None = None) -> int:
    """Write ``cameras.json`` to ``path``; returns the number of cameras."""
    doc = cameras_document(views, means, display)
    atomic_write_text(path, json.dumps(doc, indent=1))  # a reader (the API) never sees half a file
    return doc["count"]
