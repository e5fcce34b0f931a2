"""Water-type adaptation (paper §4 "Scene Adaptive Mechanism"): classifier, index w and adaptive controller.

- :mod:`.features`    pooled image statistics (pure tensor functions)
- :mod:`.classifier`  eq. 14 MLP and its JSON weights file (shipped in ``pipeline/data``)
- :mod:`.ood`         is the water outside what the classifier learned (lamp-lit, dark, blank frames)
- :mod:`.decision`    ``classify(images) -> WaterDecision`` (a class, or "unknown" with the closest one)
- :mod:`.controller`  the paper's rule: learning rates, α, β, medium start
- :mod:`.sampling`, :mod:`.dataset`, :mod:`.training`  the synthetic training data and ``train_classifier``

Importing this package loads no weights and touches no files; the shipped classifier is read on first use.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.water.classifier import WaterClassifier, load_classifier
from pipeline.water.controller import (
    WATER_TYPES,
    ControllerConfig,
    ControllerSettings,
    WaterType,
    controller_settings,
    medium_start_iteration,
    water_index,
)
from pipeline.water.decision import WaterDecision, classify
from pipeline.water.training import ClassifierTrainConfig
from pipeline.water.training import train_classifier as _train

__all__ = [
    "WATER_TYPES",
    "ControllerConfig",
    "ControllerSettings",
    "WaterClassifier",
    "WaterDecision",
    "WaterType",
    "classify",
    "controller_settings",
    "load_classifier",
    "medium_start_iteration",
    "train_classifier",
    "water_index",
]


def train_classifier(out_path: str | Path, seed: int = 0, cfg: ClassifierTrainConfig | None = None) -> dict:
    """Retrain and write the weights JSON to ``out_path``; returns the metrics (held-out accuracy, confusion, ...).

    The ``dualphys train-classifier`` entry point. See :func:`pipeline.water.training.train_classifier`.
    """
    return _train(out_path, seed=seed, cfg=cfg)
