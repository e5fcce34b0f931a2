"""Synthetic underwater scenes with ground truth (CLI: ``dualphys synth``).

A seabed (heightfield, rocks, corals; :mod:`.world`) is ray cast analytically from an ROV-like camera
path (:mod:`.path`), then the revised underwater image-formation model (:mod:`.water`) is applied
with the preset's known coefficients. Output folder::

    images/      underwater images, 8-bit PNG        (what a survey camera would record)
    clean/       clean radiance J, 8-bit PNG          (the restoration ground truth)
    depth/       camera-space z in metres, float32 .npy [H, W] (+inf where a ray hits nothing)
    sparse_gt/   COLMAP text model (cameras.txt, images.txt, points3D.txt) of the true PINHOLE cameras and
                 true surface points with their visible observations
    water.json   the true water parameters, units, conventions and the generator config

Per pixel the model uses the pixel's mean J and mean depth over its supersamples, and the distance along the
ray r = z · ray_length_factor (pixel centre), so every written pixel obeys the closed-form model exactly
(before noise and 8-bit quantisation). Everything is deterministic given the config (``seed``).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.config import SynthConfig, to_dict
from pipeline.scene.colmap import rotmat_to_qvec
from pipeline.scene.records import Camera, View, ray_length_factor
from pipeline.synth.path import survey_path
from pipeline.synth.water import TRUE_WATER_FILE, WATER_PRESETS, underwater_image
from pipeline.synth.world import World, cast, make_world

log = logging.getLogger(__name__)
FAR = 1e3  # metres: depth recorded for the rare supersample whose ray hits nothing


@dataclass
class SynthView:
    """One rendered view: pose, clean radiance, depth and the underwater image (all float, unquantised)."""

    view: View
    J: np.ndarray  # [H, W, 3] clean radiance in [0, 1]
    depth: np.ndarray  # [H, W] camera-space z, metres
    image: np.ndarray  # [H, W, 3] underwater image in [0, 1] (noise added, clipped, not quantised)


def make_camera(cfg: SynthConfig) -> Camera:
    f = 0.5 * cfg.width / math.tan(math.radians(cfg.fov_deg) / 2)
    return Camera(cfg.width, cfg.height, f, f, cfg.width / 2, cfg.height / 2)


def build_world(cfg: SynthConfig) -> World:
    n_path = max(1, math.ceil(cfg.views * 2 / 3 / 2))
    half_x = 0.5 * n_path * 0.3 + cfg.altitude * 0.9
    return make_world(cfg.seed, relief=cfg.relief, n_rocks=cfg.n_rocks, n_corals=cfg.n_corals,
                      extent=(half_x, 1.2 * cfg.altitude))


def render(world: World, view: View, supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """Clean radiance J [H, W, 3] and camera-space depth [H, W] of one view (box-filtered supersamples)."""
    cam, s = view.camera, supersample
    u = (torch.arange(cam.width * s, dtype=torch.float64) + 0.5) / s
    v = (torch.arange(cam.height * s, dtype=torch.float64) + 0.5) / s
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    dirs_cam = torch.stack([(uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy, torch.ones_like(uu)], -1)
    z_per_t = 1.0 / torch.linalg.norm(dirs_cam, dim=-1)  # camera z per unit distance along the ray
    R = torch.as_tensor(view.R, dtype=torch.float64)
    d = (dirs_cam * z_per_t[..., None]).reshape(-1, 3) @ R  # world directions (R^T d_cam), unit length
    o = torch.as_tensor(view.center, dtype=torch.float64).expand_as(d)
    J, t = cast(world, o, d, t_max=FAR)
    z = torch.where(torch.isfinite(t), t * z_per_t.reshape(-1), torch.full_like(t, FAR))
    J = J.reshape(cam.height, s, cam.width, s, 3).mean(dim=(1, 3))
    z = z.reshape(cam.height, s, cam.width, s).mean(dim=(1, 3))
    return J.numpy(), z.numpy()


def synth_views(cfg: SynthConfig) -> tuple[World, list[SynthView]]:
    """Render every view in memory (no files)."""
    if cfg.preset not in WATER_PRESETS:
        raise ValueError(f"unknown water preset {cfg.preset!r}; choose from {sorted(WATER_PRESETS)}")
    rng = np.random.default_rng(cfg.seed)
    world = build_world(cfg)
    cam = make_camera(cfg)
    water = WATER_PRESETS[cfg.preset]
    ray = ray_length_factor(cam)
    noise_rng = np.random.default_rng(cfg.seed + 7919)
    out = []
    for i, (R, c) in enumerate(survey_path(cfg.views, cfg.path, cfg.altitude, rng)):
        view = View(name=f"frame_{i:04d}.png", camera=cam, R=R, t=-R @ c)
        J, z = render(world, view, cfg.supersample)
        img = underwater_image(J, z * ray, water)
        if cfg.noise_std > 0:
            img = img + noise_rng.normal(0.0, cfg.noise_std, img.shape)
        out.append(SynthView(view, J, z, np.clip(img, 0.0, 1.0)))
        log.debug("rendered %s", view.name)
    return world, out


def generate_scene(cfg: SynthConfig, out_dir: str | Path) -> Path:
    """Render a scene and write it to ``out_dir`` (layout in the module docstring). Returns the folder."""
    from pipeline.scene.images import write_image  # OpenImageIO loads only when files are written

    out = Path(out_dir)
    for sub in ("images", "clean", "depth", "sparse_gt"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    world, views = synth_views(cfg)
    for sv in views:
        stem = Path(sv.view.name).stem
        write_image(out / "images" / sv.view.name, _to_u8(sv.image))
        write_image(out / "clean" / sv.view.name, _to_u8(sv.J))
        np.save(out / "depth" / f"{stem}.npy", sv.depth.astype(np.float32))
    points, colors, tracks = sample_surface_points(views, cfg.n_points, np.random.default_rng(cfg.seed + 1))
    write_colmap_text(out / "sparse_gt", [sv.view for sv in views], points, colors, tracks)
    water = WATER_PRESETS[cfg.preset]
    meta = {
        "preset": cfg.preset,
        **water.to_json(),
        "model": "I = J*exp(-beta_D*r) + B_inf*(1-exp(-beta_B*r)), r = depth * ray_length_factor",
        "depth": "camera-space z in metres (depth/*.npy); r is the distance along the pixel's ray",
        "world": "metres, z up, seabed near z = 0; poses in sparse_gt are cam_from_world",
        "generator": to_dict(cfg),
        "path_length_m": float(sum(np.linalg.norm(a.view.center - b.view.center) for a, b in zip(views, views[1:]))),
    }
    (out / TRUE_WATER_FILE).write_text(json.dumps(meta, indent=2))  # the truth, not a classifier's guess
    log.info("wrote synthetic %s scene with %d views to %s", cfg.preset, len(views), out)
    return out


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def sample_surface_points(views: list[SynthView], n: int, rng: np.random.Generator):
    """True surface points seen in the views, with every view that sees them (depth-test visibility).

    Returns points [P, 3], colours [P, 3] in [0, 1], and per point a list of (view index, x, y) observations.
    """
    if n <= 0 or not views:
        return np.zeros((0, 3)), np.zeros((0, 3)), []
    per_view = math.ceil(n / len(views))
    pts, cols = [], []
    for sv in views:
        cam = sv.view.camera
        ys = rng.integers(0, cam.height, per_view)
        xs = rng.integers(0, cam.width, per_view)
        z = sv.depth[ys, xs]
        ok = z < FAR * 0.5
        xc = np.stack([(xs[ok] + 0.5 - cam.cx) / cam.fx * z[ok], (ys[ok] + 0.5 - cam.cy) / cam.fy * z[ok], z[ok]], 1)
        pts.append((xc - sv.view.t) @ sv.view.R)  # R^T (x_cam − t)
        cols.append(sv.J[ys[ok], xs[ok]])
    points, colors = np.concatenate(pts)[:n], np.concatenate(cols)[:n]
    tracks: list[list[tuple[int, float, float]]] = [[] for _ in range(len(points))]
    for vi, sv in enumerate(views):
        cam = sv.view.camera
        xc = points @ sv.view.R.T + sv.view.t
        zc = xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            px = cam.fx * xc[:, 0] / zc + cam.cx
            py = cam.fy * xc[:, 1] / zc + cam.cy
        inside = (zc > 1e-3) & (px >= 0) & (px < cam.width) & (py >= 0) & (py < cam.height)
        for pi in np.nonzero(inside)[0]:
            zd = sv.depth[int(py[pi]), int(px[pi])]
            if abs(zd - zc[pi]) < 0.01 + 0.01 * zc[pi]:  # visible: not hidden behind a nearer surface
                tracks[pi].append((vi, float(px[pi]), float(py[pi])))
    return points, colors, tracks


def write_colmap_text(out: Path, views: list[View], points: np.ndarray, colors: np.ndarray, tracks) -> None:
    """Classic 3-file COLMAP text model (one shared PINHOLE camera, points with observations)."""
    cam = views[0].camera
    (out / "cameras.txt").write_text(
        "# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"1 PINHOLE {cam.width} {cam.height} {cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}\n"
    )
    obs: list[list[tuple[float, float, int]]] = [[] for _ in views]
    point_tracks: list[list[tuple[int, int]]] = []
    for pid, tr in enumerate(tracks):
        entries = []
        for vi, x, y in tr:
            entries.append((vi + 1, len(obs[vi])))
            obs[vi].append((x, y, pid + 1))
        point_tracks.append(entries)
    lines = ["# Image list: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME / POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, v in enumerate(views):
        q, t = rotmat_to_qvec(v.R), v.t
        lines.append(f"{i + 1} {' '.join(repr(float(x)) for x in (*q, *t))} 1 {v.name}")
        lines.append(" ".join(f"{x:.4f} {y:.4f} {p}" for x, y, p in obs[i]))
    (out / "images.txt").write_text("\n".join(lines) + "\n")
    plines = ["# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
    for pid, (p, c) in enumerate(zip(points, colors)):
        if not point_tracks[pid]:
            continue
        rgb = " ".join(str(int(round(float(x) * 255))) for x in c)
        track = " ".join(f"{im} {idx}" for im, idx in point_tracks[pid])
        plines.append(f"{pid + 1} {p[0]:.9g} {p[1]:.9g} {p[2]:.9g} {rgb} 0 {track}")
    (out / "points3D.txt").write_text("\n".join(plines) + "\n")
