"""A job's training config, resolved in one place.

Everything that decides how a job trains meets in :func:`resolve_train_config`: the preset and ``--iterations``
(the schedule), the mode (the job's, or what ``--mode auto``'s probe chose, with the Gaussian budget and SH
degree it sized to the scene), the seed, the downscale for ``max_width``, the speed-vs-error curve's cadence
and the classifier's water decision. The result is frozen; the train stage saves it as the job's
``train/config.json``, and the mode probe (``pipeline.train.probe.probe_config``) and the collapse guard's retry
(``pipeline.train.guard.safer_config``) derive theirs from it with ``dataclasses.replace``. (Before, five
places assembled the config or patched it in place, and the probe applied the water decision a second time.)
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

from pipeline.config import MediumConfig, TrainConfig, medium_densify, rescheduled, train_preset
from pipeline.job.options import JobOptions
from pipeline.train.hooks import curve_every
from pipeline.train.schedule import survey_cap, survey_iterations

# Mode "auto" before its probe has chosen resolves to this: the probe's base, the mode whose medium section
# carries the whole water decision (the probe sets each candidate's mode itself).
PROBE_BASE_MODE = "dualphys"


def medium_with_water(medium: MediumConfig, decision: Mapping[str, Any]) -> MediumConfig:
    """``medium`` with the adaptive controller's settings (paper §5) from a water decision
    (:meth:`pipeline.water.decision.WaterDecision.to_dict`, the classify stage's output). The one place the
    decision's keys become :class:`~pipeline.config.MediumConfig` fields. Unchanged when ``water_adaptation`` is
    off (the ablation's rows without WAT); a decision without ``init_optical_depth`` (written by older versions)
    keeps the medium's starting optical depth."""
    if not medium.water_adaptation:
        return medium
    return replace(medium, lr_attenuation=decision["lr_attenuation"], lr_scattering=decision["lr_scattering"],
                   alpha_w=decision["alpha"], beta_w=decision["beta"],
                   start_fraction=decision["medium_start_fraction"],
                   init_optical_depth=tuple(decision.get("init_optical_depth", medium.init_optical_depth)))


def training_downscale(opts: JobOptions, width: int) -> int:
    """The integer downscale that brings images ``width`` wide to at most ``opts.max_width``."""
    return max(1, math.ceil(width / opts.max_width))


def resolve_train_config(opts: JobOptions, width: int, water: Mapping[str, Any] | None,
                         selection: Mapping[str, Any] | None, views: int | None = None) -> TrainConfig:
    """The frozen TrainConfig a job trains with.

    - schedule: the preset ``opts.preset`` scaled to a survey of ``views`` views (``pipeline.train.schedule``:
      the iterations and the Gaussian cap grow with the views; None or up to 24 views: the preset as it is).
      ``opts.iterations`` wins over the rule. A run of another length than the preset's is: the
      30k schedule (densification, SH warm-up) compressed to that many iterations, the preset's Gaussian cap
      (fast 100k, balanced 300k, paper none; x views / 24 above 24 views) and its checkpoint cadence scaled
      with the run (as many checkpoints per run: fast every 1/6, balanced 1/10, paper 1/15).
      ``--preset fast --iterations 3000`` is ``--preset fast``. (It used to be a 300k cap and a checkpoint
      every fifth whatever the preset.)
    - mode: ``selection["chosen"]`` when the probe has chosen, else ``opts.mode``; mode "auto" without a
      selection is the probe's base (:data:`PROBE_BASE_MODE`);
    - with a ``selection`` (``pipeline.train.probe.select_for_job``): its budget's SH degree and Gaussian cap;
    - ``opts.seed``; the integer downscale that brings ``width`` (the scene's image width) to at most
      ``opts.max_width``; held-out evaluation on the speed-vs-error curve's schedule;
    - medium modes: refinement stopping ``medium_refine_factor`` later (:func:`medium_densify`), and with a
      ``water`` decision the controller's settings (:func:`medium_with_water`).
    """
    cfg = train_preset(opts.preset)  # also refuses an unknown preset name
    iterations = opts.iterations
    if iterations is None and views is not None:
        iterations = survey_iterations(cfg.iterations, views)
    cap = survey_cap(cfg.densify.max_gaussians, views) if views is not None else cfg.densify.max_gaussians
    if iterations is not None and (iterations != cfg.iterations or cap != cfg.densify.max_gaussians):
        every = max(1, round(cfg.checkpoint_every * iterations / cfg.iterations))
        every = every if cfg.checkpoint_every > 0 else 0  # a preset without periodic checkpoints keeps none
        cfg = rescheduled(cfg, iterations, checkpoint_every=every, max_gaussians=cap)
    mode = selection["chosen"] if selection is not None else opts.mode
    if mode == "auto":
        mode = PROBE_BASE_MODE
    sh_degree, densify = cfg.sh_degree, cfg.densify
    if selection is not None:  # the Gaussian budget and SH degree scaled to the scene (pipeline.train.budget)
        sh_degree = selection["budget"]["sh_degree"]
        densify = replace(densify, max_gaussians=selection["budget"]["max_gaussians"])
    medium = cfg.medium
    if mode != "3dgs":  # refinement goes on while the medium settles (DensifyConfig.medium_refine_factor), applied
        densify = medium_densify(densify)  # here, once: train/config.json is the schedule that runs
    if mode != "3dgs" and water is not None:
        medium = medium_with_water(medium, water)
    return replace(cfg, mode=mode, seed=opts.seed, downscale=training_downscale(opts, width),
                   colour_space=opts.colour_space,
                   eval_every=curve_every(cfg.iterations), sh_degree=sh_degree, densify=densify, medium=medium)


__all__ = ["PROBE_BASE_MODE", "medium_with_water", "resolve_train_config", "training_downscale"]
