"""The water-type classifier of paper eq. 14 and its weights file.

    T(I) = Softmax(W2 · ReLU(W1 · pool(I)))  →  (clear, medium, turbid)

``pool(I)`` is the pooled statistics vector of :func:`.features.image_features`, standardised with the mean and
std of the training set (stored with the weights). The weights file is JSON (a few KB, readable, diffable):
``{"format", "version", "classes", "feature_names", "feature_mean", "feature_std", "W1", "b1", "W2", "b2",
"metrics", "training"}``, one key per line, and optionally ``"feature_distribution"`` (the training features'
centre and whitening factor in the standardised space, for the out-of-distribution distance of :mod:`.ood`;
added to the shipped file without retraining, so the MLP's numbers are unchanged). Weights are written with
the shortest decimal that round-trips their float32 value, so a save/load cycle is exact.
"""

from __future__ import annotations

import json
import logging
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from pipeline.water.controller import WATER_TYPES
from pipeline.water.features import FEATURE_NAMES, NUM_FEATURES
from pipeline.water.ood import FeatureDistribution

log = logging.getLogger(__name__)

WEIGHTS_FORMAT = "dualphys-water-classifier"
WEIGHTS_VERSION = 1
SHIPPED_WEIGHTS = "water_classifier.json"  # inside the ``pipeline.data`` folder


class WaterClassifier(nn.Module):
    """Standardise → Linear → ReLU → Linear (logits). Features [N, F] → logits [N, 3]."""

    def __init__(self, hidden: int = 16, num_features: int = NUM_FEATURES, num_classes: int = len(WATER_TYPES)):
        super().__init__()
        self.register_buffer("feature_mean", torch.zeros(num_features))
        self.register_buffer("feature_std", torch.ones(num_features))
        self.fc1 = nn.Linear(num_features, hidden)  # W1
        self.fc2 = nn.Linear(hidden, num_classes)  # W2
        self.distribution: FeatureDistribution | None = None  # the training features' (None: not recorded)

    def set_standardisation(self, mean: Tensor, std: Tensor) -> None:
        """Store the training-set feature statistics ([F] each); std is floored so a constant feature is safe."""
        self.feature_mean.copy_(mean)
        self.feature_std.copy_(std.clamp(min=1e-6))

    def forward(self, features: Tensor) -> Tensor:
        """Logits. [N, F] → [N, 3]"""
        if features.ndim != 2 or features.shape[1] != self.feature_mean.shape[0]:
            raise ValueError(f"expected features [N, {self.feature_mean.shape[0]}], got {tuple(features.shape)}")
        z = (features - self.feature_mean) / self.feature_std
        return self.fc2(torch.relu(self.fc1(z)))

    def standardised(self, features: Tensor) -> Tensor:
        """The features as the MLP sees them. [N, F] → [N, F]"""
        return (features - self.feature_mean) / self.feature_std

    def distance(self, features: Tensor) -> Tensor | None:
        """Mahalanobis distance from the training features ([N, F] → [N]); None without a recorded distribution."""
        return self.distribution.distance(self.standardised(features)) if self.distribution is not None else None

    def probabilities(self, features: Tensor) -> Tensor:
        """Eq. 14: softmax over (clear, medium, turbid). [N, F] → [N, 3]"""
        return torch.softmax(self.forward(features), dim=1)


def classifier_to_dict(model: WaterClassifier, *, metrics: dict | None = None, training: dict | None = None) -> dict:
    """The JSON-able weights record (see the module docstring)."""

    def lst(t: Tensor) -> list:
        # float32 values through numpy's shortest float32 repr: ~9 digits instead of 17, still exact on reload.
        a = t.detach().cpu().float().numpy()
        return np.array([float(str(v)) for v in a.ravel()]).reshape(a.shape).tolist()

    d = {
        "format": WEIGHTS_FORMAT,
        "version": WEIGHTS_VERSION,
        "classes": list(WATER_TYPES),
        "feature_names": list(FEATURE_NAMES),
        "hidden": model.fc1.out_features,
        "feature_mean": lst(model.feature_mean),
        "feature_std": lst(model.feature_std),
        "W1": lst(model.fc1.weight),
        "b1": lst(model.fc1.bias),
        "W2": lst(model.fc2.weight),
        "b2": lst(model.fc2.bias),
        "metrics": metrics or {},
        "training": training or {},
    }
    if model.distribution is not None:
        d["feature_distribution"] = distribution_to_dict(model.distribution)
    return d


def distribution_to_dict(dist: FeatureDistribution) -> dict:
    """JSON-able record of a :class:`~.ood.FeatureDistribution`: the whitening factor as the rows of its lower
    triangle (row i holds i + 1 values), float32 shortest decimals."""
    w = dist.whitening.detach().cpu().float().numpy()
    return {"shrinkage": dist.shrinkage,
            "centre": [float(str(v)) for v in dist.centre.detach().cpu().float().numpy()],
            "whitening_lower": [[float(str(v)) for v in w[i, : i + 1]] for i in range(w.shape[0])]}


def distribution_from_dict(d: dict) -> FeatureDistribution:
    n = len(d["centre"])
    w = torch.zeros(n, n)
    for i, row in enumerate(d["whitening_lower"]):
        w[i, : i + 1] = torch.tensor(row)
    return FeatureDistribution(torch.tensor(d["centre"]), w, float(d["shrinkage"]))


def classifier_from_dict(d: dict) -> WaterClassifier:
    """Rebuild a classifier from :func:`classifier_to_dict` output, refusing a file for other features/classes."""
    if d.get("format") != WEIGHTS_FORMAT or d.get("version") != WEIGHTS_VERSION:
        raise ValueError(f"not a version-{WEIGHTS_VERSION} {WEIGHTS_FORMAT} record: "
                         f"format={d.get('format')!r} version={d.get('version')!r}")
    if tuple(d["classes"]) != WATER_TYPES:
        raise ValueError(f"weights are for classes {d['classes']}, expected {list(WATER_TYPES)}")
    if tuple(d["feature_names"]) != FEATURE_NAMES:
        raise ValueError("weights were trained on other features than pipeline.water.features computes; retrain "
                         "them (dualphys train-classifier)")
    model = WaterClassifier(hidden=int(d["hidden"]))
    with torch.no_grad():
        model.set_standardisation(torch.tensor(d["feature_mean"]), torch.tensor(d["feature_std"]))
        model.fc1.weight.copy_(torch.tensor(d["W1"]))
        model.fc1.bias.copy_(torch.tensor(d["b1"]))
        model.fc2.weight.copy_(torch.tensor(d["W2"]))
        model.fc2.bias.copy_(torch.tensor(d["b2"]))
    if "feature_distribution" in d:
        model.distribution = distribution_from_dict(d["feature_distribution"])
    model.eval()
    return model


def save_classifier(model: WaterClassifier, path: str | Path, **record) -> Path:
    """Write the weights record as JSON (atomically: temp file then rename). ``record``: metrics=, training=."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    d = classifier_to_dict(model, **record)
    # One key per line (readable diffs), each value compact (a few KB in all).
    tmp.write_text("{\n" + ",\n".join(f"{json.dumps(k)}: {json.dumps(v)}" for k, v in d.items()) + "\n}\n")
    tmp.replace(path)
    return path


def read_weights_record(path: str | Path | None = None) -> dict:
    """The raw JSON record of a weights file (the shipped one when ``path`` is None)."""
    if path is None:
        text = resources.files("pipeline").joinpath("data", SHIPPED_WEIGHTS).read_text()
    else:
        text = Path(path).read_text()
    return json.loads(text)


def load_classifier(path: str | Path | None = None) -> WaterClassifier:
    """Load a classifier (the shipped weights when ``path`` is None; read once, then cached). Eval mode, CPU."""
    if path is None:
        return _load_shipped()
    return classifier_from_dict(read_weights_record(path))


@lru_cache(maxsize=1)
def _load_shipped() -> WaterClassifier:
    model = classifier_from_dict(read_weights_record(None))
    log.debug("loaded the shipped water-type classifier")
    return model
