"""The "photo" family of generated underwater scenes (CLI: ``dualphys synth --family photo``).

A second generator, independent of :mod:`.procedural` on purpose: that family's bright procedural seabeds with the
water applied per pixel exactly as our medium model assumes could never show where the model fails. Here:

- albedo is cut from real colour photographs (:mod:`.photo_texture`), darkened and lower in contrast;
- geometry is a filtered-noise heightfield grid with boulders, ray marched (:mod:`.photo_world`);
- the camera flies lawnmower lines at varying altitude plus an oblique pass (:mod:`.photo_path`);
- water is applied per supersample, *before* box filtering, as in a real camera: a written pixel is the mean
  of ``J_s·exp(−β_D r_s) + B∞(1 − exp(−β_B r_s))`` over its supersamples, which differs from the closed form
  applied to the pixel's mean J and mean depth wherever depth or colour varies inside the pixel;
- sensor noise is signal dependent (Poisson–Gaussian approximation): ``std = sqrt(a·I + b²)``.

Output folder (the layout of :mod:`pipeline.synth.procedural`, so ground truth and evaluation work)::

    images/      underwater images, 8-bit PNG frame_0000.png ..., with the survey's records in their EXIF
    clean/       clean radiance J (box-filtered supersamples), 8-bit PNG
    depth/       camera-space z in metres (box-filtered), float32 .npy [H, W]; 1e3 where a ray hits nothing
    sparse_gt/   COLMAP text model of the true PINHOLE cameras and true surface points with observations
    water.json   preset, beta_D, beta_B, B_inf, units, model, generator config, "family": "photo"
    records.csv  per frame: capture time, altimeter (noisy) and true camera-to-bottom distance, lat/lon
                 (:mod:`.survey_records`; the same records in each photo's EXIF, :mod:`.exif_records`)

World: metres, z up, x east, y north (with ``gps_origin``, world x/y are UTM metres from the origin: :mod:`.geo`).
The true seabed height and clean colour at any world x, y: :func:`pipeline.synth.survey_truth.true_surface`.

Water presets (R, G, B camera bands, 1/m; B∞ linear [0, 1]). Chosen inside published ranges, not measured at a
site, and deliberately different from ``pipeline.synth.water.WATER_PRESETS``. Sources: Jerlov (1976, *Marine Optics*)
diffuse attenuation K_d by water type; Solonenko & Mobley (Appl. Opt. 54(17), 2015) IOPs of the Jerlov types;
Akkaynak et al. (CVPR 2017) effective wideband β_D for cameras (a camera's red band sits where pure-water
absorption climbs steeply, so its β_D exceeds K_d(600 nm)); Akkaynak & Treibitz (CVPR 2018/2019) β_B ≠ β_D.

- ``clear``  ~ Jerlov oceanic II: K_d ≈ 0.04–0.05 (475 nm), 0.07–0.08 (525), 0.25–0.3 (600); blue veil.
  β_D = (0.46, 0.090, 0.062), β_B = (0.34, 0.078, 0.052), B∞ = (0.020, 0.160, 0.320).
- ``medium`` ~ Jerlov coastal 1C–3C: K_d ≈ 0.15–0.3 (475), 0.10–0.17 (525), 0.3–0.4 (600); green travels
  furthest, blue-green veil. β_D = (0.52, 0.20, 0.27), β_B = (0.44, 0.22, 0.25), B∞ = (0.060, 0.280, 0.260).
- ``turbid`` ~ Jerlov coastal 5C–7C: K_d ≈ 0.6–1.0 (475), 0.35–0.55 (525), 0.55–0.75 (600); strong
  scattering, green-dominant grey-green veil. β_D = (0.80, 0.44, 0.72), β_B = (0.66, 0.46, 0.60),
  B∞ = (0.150, 0.320, 0.210).
- ``none``: no water (I = J).

Lens distortion (``distortion`` = (k1, k2), COLMAP ``RADIAL``, :mod:`.lens`) and pinhole companions in
``pinhole/`` work as in :mod:`.procedural`. Water space: "srgb" applies the water to the albedo-shaded J as it is;
"linear" decodes each supersample's J with the sRGB EOTF (:mod:`pipeline.scene.colour`), applies the water and
the box filter in linear light (a sensor integrates light linearly), adds the sensor noise to the linear image
(noise always goes on the box-filtered water image, before clipping), then sRGB-encodes both the image and the
clean J (clean/ = encode(box(decode(J_s)))).

Sensor noise defaults: a = 1.5e-4, b = 0.002 (in [0, 1] units): std ≈ 0.0050 at I = 0.15 and ≈ 0.0072 at
I = 0.33, i.e. 1.3–1.8 DN at 8 bits, a typical machine-vision camera at moderate gain.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from pipeline.scene.colour import linear_to_srgb, srgb_to_linear
from pipeline.scene.records import Camera, View
from pipeline.synth.geo import WorldGeo
from pipeline.synth.lens import distortion_pair, is_distorted, original_camera, pixel_directions, row_bands
from pipeline.synth.photo_path import photo_survey_path
from pipeline.synth.photo_texture import Mosaic, PhotoBox, PhotoSet, load_photos, make_mosaic, mosaic_albedo
from pipeline.synth.photo_world import Terrain, make_terrain, march, normals
from pipeline.synth.procedural import (
    BAND_RAYS,
    FAR,
    NO_DISTORTION,
    SynthView,
    effective_supersample,
    lens_and_space_meta,
    write_scene_files,
)
from pipeline.synth.survey_records import RECORDS_FILE, frame_records, parse_start, write_survey_records
from pipeline.synth.water import TRUE_WATER_FILE, WaterParams

log = logging.getLogger(__name__)
F64 = torch.float64

PHOTO_WATER_PRESETS: dict[str, WaterParams] = {
    "none": WaterParams(beta_D=(0.0, 0.0, 0.0), beta_B=(0.0, 0.0, 0.0), B_inf=(0.0, 0.0, 0.0)),
    "clear": WaterParams(beta_D=(0.46, 0.090, 0.062), beta_B=(0.34, 0.078, 0.052), B_inf=(0.020, 0.160, 0.320)),
    "medium": WaterParams(beta_D=(0.52, 0.20, 0.27), beta_B=(0.44, 0.22, 0.25), B_inf=(0.060, 0.280, 0.260)),
    "turbid": WaterParams(beta_D=(0.80, 0.44, 0.72), beta_B=(0.66, 0.46, 0.60), B_inf=(0.150, 0.320, 0.210)),
}

# The best seabed photos of euvp-gtr-a (see shared/data/textures/README.md) as (stem, top, bottom, left, right)
# fractions of the 256x256 photo: the seabed box, leaving out open water, the black background of 23, the
# caption of 11 and the ray's eye-spot in 1 (a salient mark that reads as repetition when tiles reuse it;
# picked by eye).
DEFAULT_PHOTOS: tuple[PhotoBox, ...] = (
    ("1", 0.0, 1.0, 0.58, 1.0), ("2", 0.15, 1.0, 0.0, 1.0), ("9", 0.0, 1.0, 0.0, 1.0),
    ("10", 0.45, 1.0, 0.0, 1.0), ("11", 0.45, 0.95, 0.3, 1.0), ("15", 0.0, 1.0, 0.0, 1.0),
    ("21", 0.0, 1.0, 0.0, 1.0), ("22", 0.0, 1.0, 0.0, 1.0), ("23", 0.5, 1.0, 0.0, 0.84),
)
LIGHT_DIR = (-0.30, 0.45, 1.0)  # towards the light; not world.py's (0.35, 0.25, 1.0)


def default_textures_dir() -> Path:
    """``<repo>/../shared/data/textures/euvp-gtr-a`` (the shared folder sits beside the repository)."""
    return Path(__file__).resolve().parents[2].parent / "shared" / "data" / "textures" / "euvp-gtr-a"


@dataclass
class PhotoSynthConfig:
    """The "photo" scene generator (this module). Every random choice follows from ``seed``."""

    views: int = 24  # number of camera views (lawnmower lines + oblique pass)
    width: int = 320  # image width in pixels
    height: int = 240  # image height in pixels
    preset: Literal["none", "clear", "medium", "turbid"] = "medium"  # water type, see PHOTO_WATER_PRESETS
    seed: int = 0  # terrain, mosaic, path jitter and noise all follow from it
    fov_deg: float = 60.0  # horizontal field of view
    supersample: int = 2  # rays per pixel per axis; water is applied per ray, then box filtered
    altitude_range: tuple[float, float] = (1.9, 3.2)  # m above z = 0; each line's altitude varies inside it
    line_step: float = 0.4  # m between views along a lawnmower line (about 80 % forward overlap at 2.5 m)
    line_spacing: float = 1.0  # m between lawnmower lines (55–75 % side overlap over the altitude range)
    oblique_fraction: float = 0.25  # share of views in the forward-looking oblique pass
    oblique_pitch_deg: tuple[float, float] = (30.0, 45.0)  # downward pitch of the oblique views' axis
    textures_dir: str | None = None  # seabed photo folder; None = <repo>/../shared/data/textures/euvp-gtr-a
    photos: tuple[PhotoBox, ...] = DEFAULT_PHOTOS  # (file stem, top, bottom, left, right) seabed box per photo
    albedo_scale: float = 0.6  # real seabeds reflect less than these enhanced photos: scale colours by this
    contrast: float = 0.7  # and pull them towards each photo's mean colour (1 = as photographed)
    tile_pitch: float = 0.8  # m between mosaic tile centres (before jitter)
    tile_size: tuple[float, float] = (0.6, 1.2)  # m of seabed covered by one crop of crop_px pixels
    crop_px: int = 128  # side of a tile's nominal crop, photo pixels (≈ 7 mm texels at 0.9 m)
    tile_blend: float = 0.18  # soft-Voronoi blend σ as a fraction of tile_pitch (seams ≈ ±2σ²/pitch)
    patch_tiles: int = 3  # substrate patches: blocks of patch_tiles x patch_tiles tiles share a dominant photo
    patch_share: float = 0.4  # probability that a tile uses its patch's dominant photo
    tile_gain: float = 0.1  # ± relative brightness variation between tiles
    ambient: float = 0.5  # share of light that does not depend on the surface orientation
    relief_std: float = 0.08  # m, standard deviation of the noise relief (before boulders)
    relief_corr: float = 2.5  # m, largest undulation wavelength of the relief spectrum
    relief_fine: float = 0.06  # m, finest relief wavelength (Gaussian roll-off)
    boulders_per_m2: float = 0.18  # boulder density
    boulder_radius: tuple[float, float] = (0.15, 0.45)  # m, boulder footprint radius range
    grid_spacing: float = 0.02  # m between heightfield nodes
    grid_size: int = 1024  # nodes per side (period grid_size · grid_spacing = 20.5 m)
    noise_gain: float = 1.5e-4  # a: shot-noise variance per unit intensity ([0, 1] units)
    noise_floor: float = 0.002  # b: read-noise std ([0, 1] units); a = b = 0 disables noise
    n_points: int = 3000  # true surface points written to sparse_gt/points3D.txt
    # Radial lens distortion (k1, k2) of COLMAP's RADIAL model (pipeline.synth.lens); (0, 0) = PINHOLE. When set,
    # images/, clean/, depth/ and sparse_gt/ are in the distorted geometry and pinhole/ holds pinhole companions.
    distortion: tuple[float, float] = (0.0, 0.0)
    water_space: Literal["srgb", "linear"] = "srgb"  # "linear": water applied to sRGB-decoded J, then re-encoded
    max_rays_per_view: int = 4_000_000  # supersample is lowered until width·height·s² fits (large sizes)
    # The survey's records per frame (pipeline.synth.survey_records; records.csv and each photo's EXIF):
    altimeter_noise: float | None = 0.02  # relative std of the altimeter's Gaussian error; 0 = exact; None/< 0 = none
    gps_origin: tuple[float, float] | None = None  # (lat, lon) degrees of world (0, 0); None = no GPS tags
    capture_start: str = "2024-06-01T00:00:00"  # ISO 8601 capture time of the first frame (UTC without a zone)
    capture_interval: float = 0.3  # seconds between consecutive frames


@dataclass
class PhotoWorld:
    """Everything the renderer needs, built once per scene."""

    terrain: Terrain
    photos: PhotoSet
    mosaic: Mosaic
    textures_dir: Path


def make_camera(cfg: PhotoSynthConfig) -> Camera:
    f = 0.5 * cfg.width / math.tan(math.radians(cfg.fov_deg) / 2)
    return Camera(cfg.width, cfg.height, f, f, cfg.width / 2, cfg.height / 2)


def build_world(cfg: PhotoSynthConfig) -> PhotoWorld:
    """Terrain and photo mosaic for ``cfg`` (reads the photos; raises TextureFolderError if missing)."""
    folder = Path(cfg.textures_dir) if cfg.textures_dir else default_textures_dir()
    boxes = tuple((str(b[0]), *(float(x) for x in b[1:5])) for b in cfg.photos)
    photos = load_photos(folder, boxes, cfg.albedo_scale, cfg.contrast)  # type: ignore[arg-type]
    rng = np.random.default_rng([cfg.seed, 101])
    terrain = make_terrain(rng, n=cfg.grid_size, spacing=cfg.grid_spacing, relief_std=cfg.relief_std,
                           corr_length=cfg.relief_corr, roughness_cut=cfg.relief_fine,
                           boulders_per_m2=cfg.boulders_per_m2, boulder_radius=cfg.boulder_radius)
    mosaic = make_mosaic(photos, np.random.default_rng([cfg.seed, 202]), pitch=cfg.tile_pitch,
                         size_range=cfg.tile_size, crop_px=cfg.crop_px, blend=cfg.tile_blend,
                         gain_spread=cfg.tile_gain, patch_tiles=cfg.patch_tiles, patch_share=cfg.patch_share)
    return PhotoWorld(terrain, photos, mosaic, folder)


def _water_arrays(water: WaterParams) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return tuple(torch.tensor(v, dtype=F64) for v in (water.beta_D, water.beta_B, water.B_inf))  # type: ignore


def surface_colour(world: PhotoWorld, xy: torch.Tensor, ambient: float) -> torch.Tensor:
    """Clean radiance J of the seabed at world points xy [M, 2] (metres): albedo · (ambient + (1 − ambient) ·
    lambert), clipped to [0, 1]; view independent, in the albedo's encoding (the photos' sRGB values).  # [M, 3]
    float64"""
    n = normals(world.terrain, xy)
    light = torch.tensor(LIGHT_DIR, dtype=F64)
    lambert = (n @ (light / torch.linalg.norm(light))).clamp(min=0)
    albedo = mosaic_albedo(world.photos, world.mosaic, xy).to(F64)
    return (albedo * (ambient + (1 - ambient) * lambert)[:, None]).clamp(0, 1)


def render_view(world: PhotoWorld, view: View, supersample: int, water: WaterParams, ambient: float,
                distortion: tuple[float, float] = NO_DISTORTION, water_space: str = "srgb"
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clean radiance J [H, W, 3], camera-space depth z [H, W] (FAR where any supersample misses) and the
    noiseless underwater image [H, W, 3] of one view through the lens ``distortion``; water applied per
    supersample, then box filtered. With ``water_space`` "linear" J and the image are returned in linear light
    (the caller encodes them after adding noise). Rendered in bands of at most BAND_RAYS rays."""
    if water_space not in ("srgb", "linear"):
        raise ValueError(f"water_space must be 'srgb' or 'linear', got {water_space!r}")
    cam, s = view.camera, supersample
    bands = [_render_rows(world, view, s, water, ambient, distortion, water_space == "linear", rows)
             for rows in row_bands(cam.height, cam.width * s * s, BAND_RAYS)]
    if len(bands) == 1:
        return bands[0]
    return tuple(np.concatenate([b[k] for b in bands]) for k in range(3))  # type: ignore[return-value]


def _render_rows(world: PhotoWorld, view: View, s: int, water: WaterParams, ambient: float,
                 distortion: tuple[float, float], linear: bool, rows: tuple[int, int]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    cam, height = view.camera, rows[1] - rows[0]
    dirs_cam = pixel_directions(cam, distortion, s, rows)
    z_per_t = (1.0 / torch.linalg.norm(dirs_cam, dim=-1)).reshape(-1)  # camera z per metre along the ray
    R = torch.as_tensor(view.R, dtype=F64)
    d = (dirs_cam.reshape(-1, 3) * z_per_t[:, None]) @ R  # [M, 3] unit world directions (R^T d_cam)
    o = torch.as_tensor(view.center, dtype=F64).expand_as(d)
    t = march(world.terrain, o, d)  # [M] metres along the ray
    hit = torch.isfinite(t)
    J = torch.zeros_like(d)
    if hit.any():
        p = o[hit] + t[hit, None] * d[hit]
        J[hit] = surface_colour(world, p[:, :2], ambient)
    if linear:
        J = srgb_to_linear(J)
    bd, bb, binf = _water_arrays(water)
    r = torch.where(hit, t, torch.full_like(t, math.inf))[:, None]
    td = torch.nan_to_num(torch.exp(-bd * r), nan=1.0)  # exp(−0·inf) = NaN for the "none" preset at a miss
    tb = torch.nan_to_num(torch.exp(-bb * r), nan=1.0)
    image = J * td + binf * (1 - tb)  # [M, 3] per supersample
    z = torch.where(hit, t * z_per_t, torch.full_like(t, FAR))

    def box(x: torch.Tensor) -> torch.Tensor:
        return x.reshape(height, s, cam.width, s, *x.shape[1:]).mean(dim=(1, 3))

    missed = box((~hit).to(F64)) > 0
    z_px = torch.where(missed, torch.full((height, cam.width), FAR, dtype=F64), box(z))
    return box(J).numpy(), z_px.numpy(), box(image).numpy()


def add_sensor_noise(image: np.ndarray, gain: float, floor: float, rng: np.random.Generator) -> np.ndarray:
    """Poisson–Gaussian (Gaussian approximation) noise: std = sqrt(gain·I + floor²). image [H, W, 3] in [0, 1]
    → clipped to [0, 1]."""
    if gain <= 0 and floor <= 0:
        return np.clip(image, 0.0, 1.0)
    std = np.sqrt(gain * np.clip(image, 0.0, None) + floor**2)
    return np.clip(image + rng.standard_normal(image.shape) * std, 0.0, 1.0)


def photo_views(cfg: PhotoSynthConfig, world: PhotoWorld | None = None) -> tuple[PhotoWorld, list[SynthView]]:
    """Render every view in memory (no files), through the lens ``cfg.distortion``. Raises ValueError for an
    unknown preset."""
    world, views, _ = photo_scene(cfg, world, companions=False)
    return world, views


def photo_scene(cfg: PhotoSynthConfig, world: PhotoWorld | None = None, companions: bool = True
                ) -> tuple[PhotoWorld, list[SynthView], list[SynthView] | None]:
    """Every view and, with distortion (and ``companions``), its pinhole companion (same pose, ideal PINHOLE
    lens, own noise stream). Returns (world, views, pinhole views or None)."""
    world, rendered = iter_photo_scene(cfg, world, companions)
    pairs = list(rendered)
    pinhole = [p[1] for p in pairs if p[1] is not None]
    return world, [p[0] for p in pairs], (pinhole if pinhole else None)


def iter_photo_scene(cfg: PhotoSynthConfig, world: PhotoWorld | None = None, companions: bool = True):
    """(world, iterator of (view, pinhole companion or None)), rendered one view at a time (bounded memory)."""
    if cfg.preset not in PHOTO_WATER_PRESETS:
        raise ValueError(f"unknown water preset {cfg.preset!r}; choose from {sorted(PHOTO_WATER_PRESETS)}")
    if cfg.supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {cfg.supersample}")
    distortion = distortion_pair(cfg.distortion)
    cam = make_camera(cfg)
    original_camera(cam, distortion)  # fails early on a lens that folds over
    world = world or build_world(cfg)
    s = effective_supersample(cfg.width, cfg.height, cfg.supersample, cfg.max_rays_per_view)
    water = PHOTO_WATER_PRESETS[cfg.preset]
    path = photo_survey_path(cfg.views, np.random.default_rng([cfg.seed, 303]), altitude_range=cfg.altitude_range,
                             line_step=cfg.line_step, line_spacing=cfg.line_spacing,
                             oblique_fraction=cfg.oblique_fraction, pitch_range_deg=cfg.oblique_pitch_deg)
    lenses = [(distortion, np.random.default_rng([cfg.seed, 404]))]
    if companions and is_distorted(distortion):
        lenses.append((NO_DISTORTION, np.random.default_rng([cfg.seed, 405])))

    def views():
        for i, (R, c) in enumerate(path):
            view = View(name=f"frame_{i:04d}.png", camera=cam, R=R, t=-R @ c)
            out = []
            for lens, noise_rng in lenses:
                J, z, img = render_view(world, view, s, water, cfg.ambient, lens, cfg.water_space)
                n_far = int((z >= FAR).sum())
                if n_far:
                    log.warning("%s: %d pixels whose rays hit no seabed (depth %g)", view.name, n_far, FAR)
                img = add_sensor_noise(img, cfg.noise_gain, cfg.noise_floor, noise_rng)
                if cfg.water_space == "linear":
                    J, img = linear_to_srgb(J), linear_to_srgb(img)
                out.append(SynthView(view, J, z, img))
            log.debug("rendered %s", view.name)
            yield out[0], (out[1] if len(out) > 1 else None)

    return world, views()


def generate_photo_scene(cfg: PhotoSynthConfig, out_dir: str | Path) -> Path:
    """Render a photo-family scene and write it to ``out_dir`` (layout in the module docstring)."""
    t0 = time.perf_counter()
    geo = WorldGeo(cfg.gps_origin) if cfg.gps_origin is not None else None  # bad records fail before rendering
    start = parse_start(cfg.capture_start)
    world, rendered = iter_photo_scene(cfg)
    out = Path(out_dir)
    distortion = distortion_pair(cfg.distortion)
    views = write_scene_files(out, rendered, cfg.views, distortion, cfg.n_points,
                              np.random.default_rng([cfg.seed, 505]))
    write_survey_records(out, frame_records(
        [sv.view for sv in views], world.terrain, altimeter_noise=cfg.altimeter_noise,
        rng=np.random.default_rng([cfg.seed, 606]), start=start, interval=cfg.capture_interval, geo=geo))
    water = PHOTO_WATER_PRESETS[cfg.preset]
    centres = [sv.view.center for sv in views]
    meta = {
        "preset": cfg.preset,
        **water.to_json(),
        "family": "photo",
        "model": "I = J*exp(-beta_D*r) + B_inf*(1-exp(-beta_B*r)), r = distance along the ray; applied per "
                 "supersample before box filtering, so pixels obey it only approximately",
        "noise": {"model": "std = sqrt(a*I + b^2), Gaussian", "a": cfg.noise_gain, "b": cfg.noise_floor},
        **lens_and_space_meta(distortion, cfg.water_space, effective_supersample(
            cfg.width, cfg.height, cfg.supersample, cfg.max_rays_per_view)),
        "depth": "camera-space z in metres (depth/*.npy, box-filtered); r = depth * ray_length_factor at the "
                 f"pixel centre; {FAR:g} where a ray hits nothing",
        "world": "metres, z up, x east, y north, seabed near z = 0; poses in sparse_gt are cam_from_world",
        "textures": {"dir": str(world.textures_dir), "photos": list(world.photos.names),
                     "source": "EUVP GTr_A (FUnIE-GAN test set), enhanced photos used as albedo"},
        "survey_records": {
            "file": RECORDS_FILE, "exif": "pipeline.synth.exif_records",
            "altimeter": "EXIF SubjectDistance = true distance along the optical axis * (1 + N(0, noise^2))",
            "altimeter_noise": cfg.altimeter_noise if cfg.altimeter_noise is not None and cfg.altimeter_noise >= 0
            else None,
            "gps": geo.to_json() if geo is not None else None,
        },
        "generator": dataclasses.asdict(cfg),
        "path_length_m": float(sum(np.linalg.norm(a - b) for a, b in zip(centres, centres[1:]))),
    }
    (out / TRUE_WATER_FILE).write_text(json.dumps(meta, indent=2))  # the truth, not a classifier's guess
    log.info("wrote photo-family %s scene with %d views to %s in %.1f s", cfg.preset, len(views), out,
             time.perf_counter() - t0)
    return out


__all__ = ["PHOTO_WATER_PRESETS", "PhotoSynthConfig", "generate_photo_scene", "make_camera", "photo_scene",
           "photo_views"]
