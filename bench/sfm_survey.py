"""SfM at survey size: matchers compared on a generated survey against its ground-truth cameras.

    python bench/sfm_survey.py SCENE [SCENE ...] [--variants exhaustive,sequential,sequential-noloop]

SCENE is a generated scene folder (``pipeline.synth.procedural.generate_scene``: images/ and sparse_gt/). For
each variant it prints views, verified pairs, loop pairs, registered images, models, reprojection error, the
pose error of the kept model after a similarity fit to the truth (rotation in degrees, centre error relative to
the survey's extent), and the wall time per phase (extract, vocab, match, map, undistort).
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

VARIANTS = {
    "exhaustive": {"matcher": "exhaustive"},
    "sequential": {"matcher": "sequential", "loop_detection": True},
    "sequential-noloop": {"matcher": "sequential", "loop_detection": False},
    "auto": {"matcher": "auto"},
}


def pose_errors(model_dir: Path, gt_dir: Path) -> dict[str, float]:
    """Rotation error (deg) and centre error (/ extent of the true centres) after a similarity fit of the
    estimated camera centres to the true ones (common images only)."""
    import pycolmap

    from pipeline.scene.align import rotation_angle_deg, umeyama

    est, gt = pycolmap.Reconstruction(str(model_dir)), pycolmap.Reconstruction(str(gt_dir))
    gt_by_name = {im.name: im for im in gt.images.values()}
    pairs = [(im, gt_by_name[im.name]) for im in est.images.values() if im.has_pose and im.name in gt_by_name]
    c_est = np.array([im.projection_center() for im, _ in pairs])  # [N, 3]
    c_gt = np.array([g.projection_center() for _, g in pairs])  # [N, 3]
    s, r, t = umeyama(c_est, c_gt)
    extent = float(np.linalg.norm(c_gt.max(0) - c_gt.min(0)))
    c_err = np.linalg.norm(s * c_est @ r.T + t - c_gt, axis=1) / extent
    # world_from_est = (s, r, t): R_est_cam_from_world @ r.T is the estimate in the true frame
    rots = np.array([im.cam_from_world().rotation.matrix() @ r.T @ g.cam_from_world().rotation.matrix().T
                     for im, g in pairs])  # fmt: skip
    ang = rotation_angle_deg(rots)
    return {"n": len(pairs), "rot_deg_mean": float(ang.mean()), "rot_deg_max": float(ang.max()),
            "centre_rel_mean": float(c_err.mean()), "centre_rel_max": float(c_err.max())}  # fmt: skip


def main() -> None:
    from pipeline.sfm.config import SfmConfig
    from pipeline.sfm.recipe import run_sfm

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--variants", default="auto,exhaustive,sequential,sequential-noloop")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    rows = []
    for scene in args.scenes:
        for v in args.variants.split(","):
            cfg = replace(SfmConfig(num_threads=args.threads), **VARIANTS[v])
            with tempfile.TemporaryDirectory() as tmp:
                s = run_sfm(scene / "images", Path(tmp) / "out", cfg)
                err = pose_errors(Path(tmp) / "out" / "distorted" / "sparse" / "0", scene / "sparse_gt")
            rows.append((scene.name, v, s, err))
            print(f"{scene.name:>8} {v:>18}: views {s.total}, matcher {s.matcher}, pairs {s.pairs_matched} "
                  f"(loop {s.loop_pairs}), registered {s.registered}, models {1 + len(s.other_models)}, "
                  f"reproj {s.mean_reproj_error_px:.3f} px, rot {err['rot_deg_mean']:.3f}/{err['rot_deg_max']:.3f}"
                  f" deg, centre {err['centre_rel_mean']:.4f}/{err['centre_rel_max']:.4f} of extent, "
                  f"{s.seconds:.1f} s ({', '.join(f'{k} {x:.1f}' for k, x in s.phase_seconds.items())})",
                  flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
