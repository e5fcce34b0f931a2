"""Synthetic underwater scenes with ground truth (CLI: ``dualphys synth``).

A seabed (heightfield, rocks, corals; :mod:`.world`) is ray cast analytically from an ROV-like camera
path (:mod:`.path`), then the revised underwater image-formation model (:mod:`.water`) is applied
with the preset's known coefficients. Output folder::

    images/      underwater images, 8-bit PNG        (what a survey camera would record)
    clean/       clean radiance J, 8-bit PNG          (the restoration ground truth)
    depth/       camera-space z in metres, float32 .npy [H, W] (+inf where a ray hits nothing)
    sparse_gt/   COLMAP text model (cameras.txt, images.txt, points3D.txt) of the true cameras and
                 true surface points with their visible observations
    water.json   the true water parameters, units, conventions and the generator config
    pinhole/     only with lens distortion: images/, clean/, depth/, sparse/ of the same views rendered through
                 the ideal PINHOLE camera (same f, cx, cy, size, poses and points)

Per pixel the model uses the pixel's mean J and mean depth over its supersamples, and the distance along the
ray r = z · sqrt(1 + x² + y²) with (x, y) the undistorted normalised coordinates of the pixel centre
(``ray_length_factor`` without distortion), so every written pixel obeys the closed-form model exactly
(before noise and 8-bit quantisation). Everything is deterministic given the config (``seed``).

Lens distortion (``SynthConfig.distortion`` = (k1, k2), COLMAP ``RADIAL``; :mod:`.lens`): every output pixel
and supersample casts the ray of its undistorted position, so images/, clean/, depth/ are what the distorted
camera records, and sparse_gt/ holds the RADIAL camera with observations projected through the distortion.

Water space (``SynthConfig.water_space``): "srgb" applies the water to J as it is written; "linear" decodes J
with the sRGB EOTF (:mod:`pipeline.scene.colour`), applies I_lin = J_lin·exp(−β_D r) + B∞(1 − exp(−β_B r)),
adds the sensor noise to I_lin (noise always goes on the water model's output, before clipping), clips and
sRGB-encodes I; clean/ keeps J (= encode(J_lin)).
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
from pipeline.scene.colour import linear_to_srgb, srgb_to_linear
from pipeline.scene.images import write_image
from pipeline.scene.records import Camera, LensCamera, View
from pipeline.synth.lens import (
    distortion_pair,
    is_distorted,
    original_camera,
    pixel_directions,
    pixel_ray_factor,
    project_pixels,
    row_bands,
    undistort_normalized,
)
from pipeline.synth.path import survey_path
from pipeline.synth.water import TRUE_WATER_FILE, WATER_PRESETS, underwater_image
from pipeline.synth.world import World, cast, make_world

log = logging.getLogger(__name__)
FAR = 1e3  # metres: depth recorded for the rare supersample whose ray hits nothing
BAND_RAYS = 1 << 20  # rays cast at once; larger images are rendered in bands of pixel rows (bounded memory)
NO_DISTORTION = (0.0, 0.0)
PINHOLE_DIR = "pinhole"  # the pinhole companions of a distorted scene


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


def effective_supersample(width: int, height: int, supersample: int, max_rays: int) -> int:
    """``supersample`` lowered (not below 1) until width·height·s² ≤ ``max_rays``."""
    s = max(1, supersample)
    while s > 1 and width * height * s * s > max_rays:
        s -= 1
    if s != supersample:
        log.info("%dx%d: supersample %d -> %d (max %d rays per view)", width, height, supersample, s, max_rays)
    return s


def render(world: World, view: View, supersample: int, distortion: tuple[float, float] = NO_DISTORTION
           ) -> tuple[np.ndarray, np.ndarray]:
    """Clean radiance J [H, W, 3] and camera-space depth [H, W] of one view (box-filtered supersamples), in
    the geometry of the lens ``distortion`` (:mod:`.lens`); rendered in bands of at most BAND_RAYS rays."""
    cam, s = view.camera, supersample
    bands = [_render_rows(world, view, s, distortion, rows)
             for rows in row_bands(cam.height, cam.width * s * s, BAND_RAYS)]
    if len(bands) == 1:
        return bands[0]
    return np.concatenate([b[0] for b in bands]), np.concatenate([b[1] for b in bands])


def _render_rows(world: World, view: View, s: int, distortion: tuple[float, float], rows: tuple[int, int]
                 ) -> tuple[np.ndarray, np.ndarray]:
    cam, h = view.camera, rows[1] - rows[0]
    dirs_cam = pixel_directions(cam, distortion, s, rows)
    z_per_t = 1.0 / torch.linalg.norm(dirs_cam, dim=-1)  # camera z per unit distance along the ray
    R = torch.as_tensor(view.R, dtype=torch.float64)
    d = (dirs_cam * z_per_t[..., None]).reshape(-1, 3) @ R  # world directions (R^T d_cam), unit length
    o = torch.as_tensor(view.center, dtype=torch.float64).expand_as(d)
    J, t = cast(world, o, d, t_max=FAR)
    z = torch.where(torch.isfinite(t), t * z_per_t.reshape(-1), torch.full_like(t, FAR))
    J = J.reshape(h, s, cam.width, s, 3).mean(dim=(1, 3))
    z = z.reshape(h, s, cam.width, s).mean(dim=(1, 3))
    return J.numpy(), z.numpy()


def water_image(J: np.ndarray, r: np.ndarray, water, water_space: str, noise_std: float,
                rng: np.random.Generator) -> np.ndarray:
    """The underwater image [H, W, 3] in [0, 1] as written (before 8-bit rounding): the water model on J
    (sRGB-decoded first for ``water_space`` "linear"), noise on its output, clipped, re-encoded if linear."""
    if water_space not in ("srgb", "linear"):
        raise ValueError(f"water_space must be 'srgb' or 'linear', got {water_space!r}")
    linear = water_space == "linear"
    img = underwater_image(srgb_to_linear(J) if linear else J, r, water)
    if noise_std > 0:
        img = img + rng.normal(0.0, noise_std, img.shape)
    img = np.clip(img, 0.0, 1.0)
    return linear_to_srgb(img) if linear else img


def synth_views(cfg: SynthConfig) -> tuple[World, list[SynthView]]:
    """Render every view in memory (no files), in the lens geometry of ``cfg.distortion``."""
    world, views, _ = synth_scene(cfg, companions=False)
    return world, views


def synth_scene(cfg: SynthConfig, companions: bool = True
                ) -> tuple[World, list[SynthView], list[SynthView] | None]:
    """Render every view; with distortion (and ``companions``) also its pinhole companion (same pose, ideal
    PINHOLE lens, own noise stream). Returns (world, views, pinhole views or None)."""
    world, rendered = iter_scene(cfg, companions)
    pairs = list(rendered)
    views = [p[0] for p in pairs]
    pinhole = [p[1] for p in pairs if p[1] is not None]
    return world, views, (pinhole if pinhole else None)


def iter_scene(cfg: SynthConfig, companions: bool = True):
    """(world, iterator of (view, pinhole companion or None)), rendered one view at a time (bounded memory)."""
    if cfg.preset not in WATER_PRESETS:
        raise ValueError(f"unknown water preset {cfg.preset!r}; choose from {sorted(WATER_PRESETS)}")
    distortion = distortion_pair(cfg.distortion)
    rng = np.random.default_rng(cfg.seed)
    world = build_world(cfg)
    cam = make_camera(cfg)
    original_camera(cam, distortion)  # fails early on a lens that folds over
    s = effective_supersample(cfg.width, cfg.height, cfg.supersample, cfg.max_rays_per_view)
    water = WATER_PRESETS[cfg.preset]
    lenses = [(distortion, pixel_ray_factor(cam, distortion), np.random.default_rng(cfg.seed + 7919))]
    if companions and is_distorted(distortion):
        lenses.append((NO_DISTORTION, pixel_ray_factor(cam, NO_DISTORTION), np.random.default_rng([cfg.seed, 7920])))
    poses = survey_path(cfg.views, cfg.path, cfg.altitude, rng)

    def views():
        for i, (R, c) in enumerate(poses):
            view = View(name=f"frame_{i:04d}.png", camera=cam, R=R, t=-R @ c)
            out = []
            for lens, ray, noise_rng in lenses:
                J, z = render(world, view, s, lens)
                out.append(SynthView(view, J, z, water_image(J, z * ray, water, cfg.water_space, cfg.noise_std,
                                                             noise_rng)))
            log.debug("rendered %s", view.name)
            yield out[0], (out[1] if len(out) > 1 else None)

    return world, views()


def generate_scene(cfg: SynthConfig, out_dir: str | Path) -> Path:
    """Render a scene and write it to ``out_dir`` (layout in the module docstring). Returns the folder."""
    out = Path(out_dir)
    world, rendered = iter_scene(cfg)
    distortion = distortion_pair(cfg.distortion)
    views = write_scene_files(out, rendered, cfg.views, distortion, cfg.n_points, np.random.default_rng(cfg.seed + 1))
    water = WATER_PRESETS[cfg.preset]
    meta = {
        "preset": cfg.preset,
        **water.to_json(),
        "model": "I = J*exp(-beta_D*r) + B_inf*(1-exp(-beta_B*r)), r = depth * ray_length_factor",
        **lens_and_space_meta(distortion, cfg.water_space, effective_supersample(
            cfg.width, cfg.height, cfg.supersample, cfg.max_rays_per_view)),
        "depth": "camera-space z in metres (depth/*.npy); r is the distance along the pixel's ray",
        "world": "metres, z up, seabed near z = 0; poses in sparse_gt are cam_from_world",
        "generator": to_dict(cfg),
        "path_length_m": float(sum(np.linalg.norm(a.view.center - b.view.center) for a, b in zip(views, views[1:]))),
    }
    (out / TRUE_WATER_FILE).write_text(json.dumps(meta, indent=2))  # the truth, not a classifier's guess
    log.info("wrote synthetic %s scene with %d views to %s", cfg.preset, len(views), out)
    return out


def lens_and_space_meta(distortion: tuple[float, float], water_space: str, supersample: int) -> dict:
    """water.json entries on the lens, the water space and the supersampling actually used."""
    return {
        "camera_model": "RADIAL" if is_distorted(distortion) else "PINHOLE",
        "distortion": {"k1": distortion[0], "k2": distortion[1],
                       "note": "COLMAP RADIAL (f, cx, cy, k1, k2); images/clean/depth are in the distorted "
                               "geometry, the ray factor is sqrt(1 + x^2 + y^2) of each pixel's undistorted "
                               "normalised coordinates; pinhole companions in pinhole/"}
        if is_distorted(distortion) else None,
        "water_space": water_space,
        "supersample_used": supersample,
    }


def write_scene_files(out: Path, rendered, n_views: int, distortion: tuple[float, float], n_points: int,
                      rng: np.random.Generator) -> list[SynthView]:
    """Write each (view, pinhole companion or None) of ``rendered`` as it comes (images/, clean/, depth/; the
    companions under pinhole/), sampling its surface points on the way, then sparse_gt/ (lens ``distortion``)
    and pinhole/sparse/ (PINHOLE, the same points observed through the ideal lens). Only the depth maps are
    kept; returns the views with J and image dropped (empty arrays)."""
    per_view = math.ceil(n_points / n_views) if n_points > 0 and n_views > 0 else 0
    kept, kept_pin, pts, cols = [], [], [], []
    for sv, pin in rendered:
        write_views(out, [sv])
        if pin is not None:
            write_views(out / PINHOLE_DIR, [pin])
            kept_pin.append(_depth_only(pin))
        if per_view:
            p, c = _sample_view_points(sv, per_view, rng, distortion)
            pts.append(p)
            cols.append(c)
        kept.append(_depth_only(sv))
    if pts:
        points, colors = np.concatenate(pts)[:n_points], np.concatenate(cols)[:n_points]
    else:
        points, colors = np.zeros((0, 3)), np.zeros((0, 3))
    cam = kept[0].view.camera if kept else None
    write_colmap_text(out / "sparse_gt", [sv.view for sv in kept], points, colors,
                      observe_points(points, kept, distortion), original_camera(cam, distortion) if cam else None)
    if kept_pin:
        write_colmap_text(out / PINHOLE_DIR / "sparse", [sv.view for sv in kept_pin], points, colors,
                          observe_points(points, kept_pin, NO_DISTORTION))
    return kept


def _depth_only(sv: SynthView) -> SynthView:
    empty = np.zeros((0, 0, 3))
    return SynthView(sv.view, empty, sv.depth, empty)


def write_views(out: Path, views: list[SynthView]) -> None:
    """Each view's images/ and clean/ (8-bit PNG named as the view) and depth/ (float32 .npy by its stem)."""
    for sub in ("images", "clean", "depth"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    for sv in views:
        stem = Path(sv.view.name).stem
        write_image(out / "images" / sv.view.name, to_u8(sv.image))
        write_image(out / "clean" / sv.view.name, to_u8(sv.J))
        np.save(out / "depth" / f"{stem}.npy", sv.depth.astype(np.float32))


def to_u8(img: np.ndarray) -> np.ndarray:
    """[0, 1] floats as 8-bit values, rounded (what images/ and clean/ hold)."""
    return np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def sample_surface_points(views: list[SynthView], n: int, rng: np.random.Generator,
                          distortion: tuple[float, float] = NO_DISTORTION):
    """True surface points seen in the views (rendered through the lens ``distortion``), with every view that
    sees them (depth-test visibility).

    Returns points [P, 3], colours [P, 3] in [0, 1], and per point a list of (view index, x, y) observations.
    """
    if n <= 0 or not views:
        return np.zeros((0, 3)), np.zeros((0, 3)), []
    per_view = math.ceil(n / len(views))
    sampled = [_sample_view_points(sv, per_view, rng, distortion) for sv in views]
    points = np.concatenate([p for p, _ in sampled])[:n]
    colors = np.concatenate([c for _, c in sampled])[:n]
    return points, colors, observe_points(points, views, distortion)


def _sample_view_points(sv: SynthView, per_view: int, rng: np.random.Generator, distortion: tuple[float, float]
                        ) -> tuple[np.ndarray, np.ndarray]:
    """``per_view`` random pixels of one view back-projected to world points (rays that hit nothing dropped)
    with their J colours. ([K, 3], [K, 3])"""
    cam = sv.view.camera
    ys = rng.integers(0, cam.height, per_view)
    xs = rng.integers(0, cam.width, per_view)
    z = sv.depth[ys, xs]
    ok = z < FAR * 0.5
    xn, yn = (xs[ok] + 0.5 - cam.cx) / cam.fx, (ys[ok] + 0.5 - cam.cy) / cam.fy
    if is_distorted(distortion):
        xn, yn = (a.numpy() for a in undistort_normalized(torch.as_tensor(xn), torch.as_tensor(yn), distortion))
    xc = np.stack([xn * z[ok], yn * z[ok], z[ok]], 1)
    return (xc - sv.view.t) @ sv.view.R, sv.J[ys[ok], xs[ok]]  # R^T (x_cam − t)


def observe_points(points: np.ndarray, views: list[SynthView], distortion: tuple[float, float]
                   ) -> list[list[tuple[int, float, float]]]:
    """Per point, the (view index, x, y) pixel observations (projected through the lens) of the views whose
    depth map agrees with the point's camera z (visible, not hidden behind a nearer surface)."""
    tracks: list[list[tuple[int, float, float]]] = [[] for _ in range(len(points))]
    for vi, sv in enumerate(views):
        cam = sv.view.camera
        xc = points @ sv.view.R.T + sv.view.t
        zc = xc[:, 2]
        px, py = project_pixels(cam, distortion, xc)
        with np.errstate(invalid="ignore"):
            inside = (zc > 1e-3) & (px >= 0) & (px < cam.width) & (py >= 0) & (py < cam.height)
        for pi in np.nonzero(inside)[0]:
            zd = sv.depth[int(py[pi]), int(px[pi])]
            if abs(zd - zc[pi]) < 0.01 + 0.01 * zc[pi]:  # visible: not hidden behind a nearer surface
                tracks[pi].append((vi, float(px[pi]), float(py[pi])))
    return tracks


def write_colmap_text(out: Path, views: list[View], points: np.ndarray, colors: np.ndarray, tracks,
                      camera: LensCamera | None = None) -> None:
    """Classic 3-file COLMAP text model (one shared camera: ``camera``, default the views' PINHOLE camera;
    points with observations)."""
    out.mkdir(parents=True, exist_ok=True)
    cam = views[0].camera
    line = (camera.cameras_txt_line() if camera is not None and camera.model != "PINHOLE"
            else f"1 PINHOLE {cam.width} {cam.height} {cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}")
    (out / "cameras.txt").write_text("# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + line + "\n")
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
