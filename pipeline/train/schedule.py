"""Schedules that follow the survey: iterations and the Gaussian cap from the view count (docs/DECISIONS.md,
"Schedules that scale with the survey").

A preset's iteration count and Gaussian cap are those of the reference survey, ``REFERENCE_VIEWS`` views (the
24-view scene every preset was tuned on). A survey of ``V`` views trains for

    iterations = preset_iterations x clamp((V / REFERENCE_VIEWS) ^ ITERATIONS_EXPONENT, 1, MAX_FACTOR)

Why a power between "fixed count" (p = 0) and "fixed passes" (p = 1): a survey that grows by more views at the
same overlap covers more seabed, so the Gaussians to fit grow with V, and each needs some number of updates;
but a single step's view updates every Gaussian it sees, and at a fixed overlap each Gaussian is seen by the
same number of views whatever V is, so passes over the views can fall as V grows. The exponent is measured
(``bench/schedule.py``: held-out PSNR of 24 and 72 views against iterations). Fewer views than the reference
keep the preset's count (the factor's floor is 1: every existing 24-view result, and smaller test scenes, train
exactly as before).

Iterations follow the view count, not the pixels: the number of steps 3DGS needs does not grow with the
resolution (graphdeco's 30k serves 0.3 and 1.6 Mpx alike); the pixels set the Gaussian budget
(``pipeline.train.budget``). The Gaussian cap of a preset scales with the views (the seabed's area), capped at
``budget.MAX_GAUSSIANS``; a preset without a cap (paper) stays without.

Densification: refine start/stop scale with the run (``DensifyConfig.scaled``); ``refine_every`` stays the
preset's 100 (the gradient it averages is a mean over the steps that saw each Gaussian, unbiased whatever the
window; a window of W steps gives a Gaussian seen by k of V views about W k / V samples: ~6 at 300 frames with
the generator's k ≈ 16, docs/DECISIONS.md); ``reset_every`` scales with the run and stays >= 10 refinements.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from pipeline.train.budget import MAX_GAUSSIANS

REFERENCE_VIEWS = 24  # the survey every preset's iteration count and Gaussian cap were tuned on
ITERATIONS_EXPONENT = 0.5  # p: iterations grow as views^p (bench/schedule.py)
MAX_FACTOR = 6.0  # at most this many times the preset's iterations (fast: 18,000; reached at 864 views)
RULE = "iterations = preset x clamp((views / 24) ^ 0.5, 1, 6)"


def iterations_factor(views: int) -> float:
    """How many times the preset's iterations a survey of ``views`` views trains for."""
    if views < 1:
        raise ValueError(f"a survey needs at least one view, got {views}")
    return min(MAX_FACTOR, max(1.0, (views / REFERENCE_VIEWS) ** ITERATIONS_EXPONENT))


def survey_iterations(preset_iterations: int, views: int) -> int:
    """The preset's iteration count scaled to a survey of ``views`` views (module docstring)."""
    return round(preset_iterations * iterations_factor(views))


def survey_cap(preset_cap: int, views: int) -> int:
    """The preset's Gaussian cap (0 = none) scaled with the survey's area (views at a fixed overlap)."""
    if preset_cap <= 0:
        return 0
    return min(MAX_GAUSSIANS, round(preset_cap * max(1.0, views / REFERENCE_VIEWS)))


def coarse_iterations(iterations: int, fraction: float, medium_start: int | None) -> int:
    """How many of the first iterations train at the coarse size (``TrainConfig.coarse_fraction``): the fraction
    of the run, and in medium modes never past the medium's start (the water is fitted at the training size
    only, so the coarse phase is J's warm-up alone)."""
    n = round(iterations * fraction)
    return n if medium_start is None else min(n, medium_start)


@dataclass(frozen=True)
class Schedule:
    """What the report states about a job's schedule (report.json ``schedule``)."""

    views: int  # views of the survey (the rule's input: training and held-out)
    train_views: int  # views trained on
    width: int  # training size
    height: int
    pixels: int  # training pixels: train_views x width x height
    rule: str  # RULE
    factor: float  # iterations_factor(views)
    iterations: int  # the run's length
    explicit_iterations: bool  # --iterations given: it wins over the rule
    passes: float  # iterations / train_views: how often each training view is seen
    refine_every: int  # densification window (iterations)
    refine_start: int
    refine_stop: int  # in medium modes: x DensifyConfig.medium_refine_factor, as the trainer runs it
    reset_every: int
    max_gaussians: int  # the Gaussian budget trained with (0 = no cap)
    medium_start: int | None  # the iteration after which the medium is on (a fixed fraction of the run); None: 3dgs
    coarse_until: int = 0  # iterations 1..coarse_until train at the coarse size (TrainConfig.coarse_fraction)
    coarse_width: int = 0  # the coarse size (0: no coarse phase)
    coarse_height: int = 0

    def to_json(self) -> dict:
        return asdict(self)


__all__ = ["ITERATIONS_EXPONENT", "MAX_FACTOR", "REFERENCE_VIEWS", "RULE", "Schedule", "coarse_iterations",
           "iterations_factor", "survey_cap", "survey_iterations"]
