"""The paper's Table 2 (ablations) on a generated scene with ground truth (``dualphys ablate``).

Each row trains the same scene (true cameras, so no SfM) with one configuration and scores the held-out views
(every 8th by name): PSNR and SSIM of the with-water prediction against the photos, and of the restored J
against the generator's clean images, plus training seconds.

Reading of the paper's rows (its Table 2 has a "Model" and a "Loss" section under "Total"):

- ``Total``: dualphys with every module (RGBAt = eq. 5's RGB-guided attenuation, MSBs = eqs. 7-8's multi-scale
  backscatter, WAT = the water-type adaptation) and every loss term.
- Model section: the named modules on, the others off, trained without the three loss terms the loss section
  varies (L_ab, L_wat, L_ms), so the rows isolate the modules.
- Loss section: the full model with only the named terms of L_ab, L_wat, L_ms; "L_ab+L_wat+L_ms w/o WAT" is all
  three without the water-type adaptation (the paper's last row, "even with all three loss terms ... lacking
  the aquatic-type adaptation").
- L_edge and our floater term, which the paper's loss rows do not vary, stay on in every medium row.
- Baselines beyond the paper's table: plain ``3DGS`` and the ``homogeneous`` medium (eq. 3).

``leave-one-out`` rows instead switch off one module or one loss term at a time from the full model.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.config import SynthConfig, scaled_train_config, to_dict
from pipeline.job.markers import atomic_write_json
from pipeline.ops.metrics import mean_ssim, pooled_psnr
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.scene.split import split_views
from pipeline.synth.procedural import generate_scene
from pipeline.synth.water import TRUE_WATER_FILE
from pipeline.train.resolve import medium_with_water
from pipeline.train.trainer import Trainer
from pipeline.water import classify

log = logging.getLogger(__name__)

VARIED_LOSSES = ("ab", "wat", "ms")  # the terms the paper's loss rows switch
FIXED_LOSSES = ("edge", "floater", "surface")  # on in every medium row
ALL_LOSSES = VARIED_LOSSES + FIXED_LOSSES


@dataclass(frozen=True)
class AblationRow:
    """One row: a training mode and the medium's switches."""

    name: str
    section: str  # "baseline" | "total" | "model" | "loss" | "leave-one-out"
    mode: str = "dualphys"
    rgb_attenuation: bool = True
    multiscale_scattering: bool = True
    water_adaptation: bool = True
    losses: tuple[str, ...] = ALL_LOSSES


def _model_row(name: str, rgbat: bool, msbs: bool, wat: bool) -> AblationRow:
    return AblationRow(name, "model", rgb_attenuation=rgbat, multiscale_scattering=msbs, water_adaptation=wat,
                       losses=FIXED_LOSSES)


def _loss_row(name: str, terms: tuple[str, ...], wat: bool = True) -> AblationRow:
    return AblationRow(name, "loss", water_adaptation=wat, losses=terms + FIXED_LOSSES)


BASELINES = [AblationRow("3DGS", "baseline", mode="3dgs"), AblationRow("homogeneous", "baseline", mode="homogeneous")]
TOTAL = AblationRow("Total", "total")
ROW_SETS: dict[str, list[AblationRow]] = {
    "paper": BASELINES + [
        TOTAL,
        _model_row("RGBAt only", True, False, False),
        _model_row("MSBs only", False, True, False),
        _model_row("WAT only", False, False, True),
        _model_row("RGBAt+MSBs", True, True, False),
        _model_row("RGBAt+MSBs+WAT", True, True, True),
        _loss_row("L_wat only", ("wat",)),
        _loss_row("L_ms only", ("ms",)),
        _loss_row("L_ab only", ("ab",)),
        _loss_row("L_ab+L_wat", ("ab", "wat")),
        _loss_row("L_ab+L_wat+L_ms", ("ab", "wat", "ms")),
        _loss_row("L_ab+L_wat+L_ms w/o WAT", ("ab", "wat", "ms"), wat=False),
    ],
    "leave-one-out": BASELINES + [
        TOTAL,
        dataclasses.replace(TOTAL, name="-RGBAt", section="leave-one-out", rgb_attenuation=False),
        dataclasses.replace(TOTAL, name="-MSBs", section="leave-one-out", multiscale_scattering=False),
        dataclasses.replace(TOTAL, name="-WAT", section="leave-one-out", water_adaptation=False),
        *[dataclasses.replace(TOTAL, name=f"-L_{t}", section="leave-one-out",
                              losses=tuple(x for x in ALL_LOSSES if x != t)) for t in ALL_LOSSES],
    ],
}


@dataclass
class AblationConfig:
    """The scene and the training length of every row."""

    views: int = 16
    width: int = 160
    height: int = 120
    water: str = "medium"  # generator preset (pipeline.synth.water)
    iterations: int = 1500
    seed: int = 0
    rows: str = "paper"  # a key of ROW_SETS
    only: tuple[str, ...] = ()  # row names to run (default: all of the set)
    backend: str = "auto"


@dataclass
class RowResult:
    name: str
    section: str
    psnr: float  # with water, held-out photos
    ssim: float
    restored_psnr: float  # restored J against the clean images of the held-out views
    restored_ssim: float
    seconds: float  # training
    n_gaussians: int
    config: dict[str, Any] = field(default_factory=dict)


def select_rows(cfg: AblationConfig) -> list[AblationRow]:
    if cfg.rows not in ROW_SETS:
        raise ValueError(f"unknown row set {cfg.rows!r}; choose from {', '.join(ROW_SETS)}")
    rows = ROW_SETS[cfg.rows]
    if cfg.only:
        names = {r.name.lower(): r for r in rows}
        missing = [n for n in cfg.only if n.lower() not in names]
        if missing:
            raise ValueError(f"unknown rows {missing}; the {cfg.rows!r} set has {[r.name for r in rows]}")
        rows = [names[n.lower()] for n in cfg.only]
    return rows


def row_config(row: AblationRow, cfg: AblationConfig, water: dict):
    """The TrainConfig of one row: the scaled schedule, the row's mode and switches, the controller's settings
    when WAT is on."""
    tc = scaled_train_config(cfg.iterations, checkpoint_every=0, max_gaussians=100_000)
    m = dataclasses.replace(tc.medium, rgb_attenuation=row.rgb_attenuation,
                            multiscale_scattering=row.multiscale_scattering, water_adaptation=row.water_adaptation,
                            losses=row.losses)
    if row.mode != "3dgs":
        m = medium_with_water(m, water)  # unchanged when water_adaptation is off
    return dataclasses.replace(tc, mode=row.mode, seed=cfg.seed, backend=cfg.backend, log_every=0, medium=m)


def _score_row(trainer, views, photos, clean) -> dict[str, float]:
    outs = [trainer.outputs(v) for v in views]
    with_water = list(zip([o.I for o in outs], photos, strict=True))
    restored = list(zip([o.J for o in outs], clean, strict=True))
    return {"psnr": pooled_psnr(with_water), "ssim": mean_ssim(with_water),
            "restored_psnr": pooled_psnr(restored), "restored_ssim": mean_ssim(restored)}


def run_ablation(out: str | Path, cfg: AblationConfig,
                 on_row: Callable[[RowResult], None] | None = None) -> dict[str, Any]:
    """Generate the scene under ``out/scene`` (reused when present), train every row, write
    ``out/ablation.json`` and return its content."""
    out = Path(out)
    rows = select_rows(cfg)
    synth = SynthConfig(views=cfg.views, width=cfg.width, height=cfg.height, preset=cfg.water,  # type: ignore[arg-type]
                        seed=cfg.seed)
    root = out / "scene"
    truth = root / TRUE_WATER_FILE  # the generated scene's true water, with the generator's config
    same = truth.is_file() and json.loads(truth.read_text()).get("generator") == to_dict(synth)
    if not same:
        generate_scene(synth, root)
    scene = load_scene(root)
    train_views, test_views = split_views(scene.views)
    images = [read_image(root / "images" / v.name) for v in train_views]
    photos = [read_image(root / "images" / v.name) for v in test_views]
    clean = [read_image(root / "clean" / v.name) for v in test_views]
    water = classify(images[:: max(1, len(images) // 8)]).to_dict()
    train_scene = scene.subset(train_views)
    results: list[RowResult] = []
    for row in rows:
        tc = row_config(row, cfg, water)
        t0 = time.perf_counter()
        tr = Trainer(train_scene, images, tc)
        tr.run([])
        scores = _score_row(tr, test_views, photos, clean)
        res = RowResult(row.name, row.section, seconds=round(time.perf_counter() - t0, 2),
                        n_gaussians=int(tr.gaussians["means"].shape[0]), config=dataclasses.asdict(row), **scores)
        log.info("ablation %s: PSNR %.2f dB, restored %.2f dB, %.1f s", row.name, res.psnr, res.restored_psnr,
                 res.seconds)
        results.append(res)
        if on_row is not None:
            on_row(res)
    report = {"scene": {**to_dict(synth), "train_views": len(train_views), "test_views": len(test_views)},
              "iterations": cfg.iterations, "rows_set": cfg.rows, "water_decision": water,
              "rows": [dataclasses.asdict(r) for r in results],
              "columns": {"psnr": "dB, with water, held-out photos", "ssim": "with water, held-out photos",
                          "restored_psnr": "dB, restored J against the clean images of the held-out views",
                          "restored_ssim": "restored J against the clean images", "seconds": "training time"}}
    atomic_write_json(out / "ablation.json", report)
    return report


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """The rows as a plain-text table in the paper's layout (sections separated by rules)."""
    head = f"{'row':<26} {'PSNR':>7} {'SSIM':>6} {'J PSNR':>7} {'J SSIM':>7} {'time s':>7}"
    lines, section = [head, "-" * len(head)], None
    for r in rows:
        if section is not None and r["section"] != section:
            lines.append("-" * len(head))
        section = r["section"]
        lines.append(f"{r['name']:<26} {r['psnr']:7.2f} {r['ssim']:6.3f} {r['restored_psnr']:7.2f} "
                     f"{r['restored_ssim']:7.3f} {r['seconds']:7.1f}")
    return "\n".join(lines)


__all__ = ["AblationConfig", "AblationRow", "ROW_SETS", "RowResult", "format_table", "row_config", "run_ablation",
           "select_rows"]
