"""Similarity alignment of estimated camera poses to a reference (pure numpy).

Used to score SfM against ground truth (synthetic scenes) or a reference model: SfM recovers poses only up
to a similarity (scale, rotation, translation), so the camera centres are aligned first (Umeyama 1991) and
the errors measured after alignment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.scene.records import Scene, View


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity with ``dst ≈ s * R @ src + t``.  src, dst: [N, 3], N >= 3.

    Returns (s, R [3, 3] proper rotation, t [3]). Umeyama, "Least-squares estimation of transformation
    parameters between two point patterns", PAMI 1991, eqs. 34-42.
    """
    src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama expects two [N, 3] arrays with N >= 3; got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = (xs**2).sum() / len(src)
    if var_s <= 1e-18:
        raise ValueError("umeyama: source points are all identical; the scale is undefined")
    cov = xd.T @ xs / len(src)  # [3, 3]
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s)
    t = mu_d - s * R @ mu_s
    return s, R, t


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Angle of rotation matrices [..., 3, 3] in degrees.  # [...]

    atan2(sin, cos) rather than arccos of the trace, which loses precision near 0° (about 1e-6 deg).
    """
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    axis = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = np.linalg.norm(axis, axis=-1) / 2.0
    return np.degrees(np.arctan2(sin, cos))


@dataclass(frozen=True)
class Similarity:
    """``x_ref = scale * R @ x_est + t``: maps an estimated scene's world into a reference world."""

    scale: float  # reference units per estimated unit (metres per scene unit against a metric reference)
    R: np.ndarray  # [3, 3]
    t: np.ndarray  # [3]


def _common_views(est: Scene, ref: Scene) -> list[tuple[View, View]]:
    ref_by_name = {v.name: v for v in ref.views}
    pairs = sorted(((v, ref_by_name[v.name]) for v in est.views if v.name in ref_by_name), key=lambda p: p[0].name)
    if len(pairs) < 3:
        raise ValueError(f"align_to_reference: need >= 3 views common to both scenes, found {len(pairs)}")
    return pairs


def fit_similarity(est: Scene, ref: Scene) -> Similarity:
    """The similarity taking ``est``'s camera centres onto ``ref``'s (views matched by name, >= 3 common)."""
    pairs = _common_views(est, ref)
    s, R, t = umeyama(np.stack([e.center for e, _ in pairs]), np.stack([r.center for _, r in pairs]))
    return Similarity(s, R, t)


def view_in_estimated_frame(ref_view: View, sim: Similarity) -> View:
    """A reference camera expressed in the estimated scene's world (same intrinsics and name), so a model
    trained in that world can be rendered from the true pose. Camera-space depth comes out in estimated units
    (reference depth / ``sim.scale``).

    With x_ref = s A x_est + b: x_cam = R_ref x_ref + t_ref = s (R_ref A x_est + (R_ref b + t_ref) / s), and the
    overall factor s changes no pixel, only the depth's unit.
    """
    R = ref_view.R @ sim.R
    t = (ref_view.R @ sim.t + ref_view.t) / sim.scale
    return View(ref_view.name, ref_view.camera, R, t, ref_view.image_path)


def align_to_reference(est: Scene, ref: Scene) -> dict[str, float]:
    """Align ``est`` camera centres to ``ref`` (views matched by name) and measure the pose errors.

    Returns a dict of floats: ``n_common``, ``scale`` (ref units per est unit), ``rot_err_deg_mean/max``
    (angle between aligned est and ref camera orientations), ``center_err_mean/max`` (ref units),
    ``path_length`` (sum of distances between consecutive ref centres, views sorted by name) and
    ``center_err_rel_mean/max`` (centre errors divided by the path length). Needs >= 3 common views with
    distinct centres.
    """
    pairs = _common_views(est, ref)
    c_est = np.stack([e.center for e, _ in pairs])  # [N, 3]
    c_ref = np.stack([r.center for _, r in pairs])  # [N, 3]
    s, A, b = umeyama(c_est, c_ref)
    # x_ref = s A x_est + b  =>  aligned rotation of a camera is R_est A^T.
    R_err = np.stack([(e.R @ A.T) @ r.R.T for e, r in pairs])  # [N, 3, 3]
    rot = rotation_angle_deg(R_err)
    cerr = np.linalg.norm((s * (A @ c_est.T)).T + b - c_ref, axis=1)
    ref_sorted = np.stack([v.center for v in sorted(ref.views, key=lambda v: v.name)])
    path = float(np.linalg.norm(np.diff(ref_sorted, axis=0), axis=1).sum())
    rel = cerr / path if path > 0 else np.full_like(cerr, np.nan)
    return {
        "n_common": float(len(pairs)),
        "scale": s,
        "rot_err_deg_mean": float(rot.mean()),
        "rot_err_deg_max": float(rot.max()),
        "center_err_mean": float(cerr.mean()),
        "center_err_max": float(cerr.max()),
        "path_length": path,
        "center_err_rel_mean": float(rel.mean()),
        "center_err_rel_max": float(rel.max()),
    }


__all__ = ["Similarity", "align_to_reference", "fit_similarity", "rotation_angle_deg", "umeyama",
           "view_in_estimated_frame"]
