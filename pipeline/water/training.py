"""Train the water-type classifier offline (CLI: ``dualphys train-classifier``).

Reproducibility: every random draw comes from generators seeded by ``seed`` (numpy for the water and camera
draws, a torch ``Generator`` for the initial weights), the optimiser is full-batch Adam (no shuffling), and
everything runs on the CPU in float32. Two runs with the same seed and the same torch build and thread count
give bit-identical weights (tested). Across machines or thread counts, float summation order in BLAS may
differ in the last bits, so weights can differ slightly while the accuracy agrees to within a sample or two.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from pipeline.water.classifier import WaterClassifier, classifier_from_dict, read_weights_record, save_classifier
from pipeline.water.controller import WATER_TYPES
from pipeline.water.dataset import RenderSpec, make_samples, render_clean
from pipeline.water.ood import SHRINKAGE, fit_distribution
from pipeline.water.sampling import NuisanceSpec

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ClassifierTrainConfig:
    """Data and optimiser settings of :func:`train_classifier` (defaults make the shipped weights)."""

    train_seeds: tuple[int, ...] = tuple(range(30))  # synthetic scene seeds used for training
    heldout_seeds: tuple[int, ...] = tuple(range(1000, 1008))  # disjoint scene seeds for the held-out check
    render: RenderSpec = field(default_factory=RenderSpec)
    train_draws_per_class: int = 12  # waters drawn per clean view and class (training)
    heldout_draws_per_class: int = 4
    nuisance: NuisanceSpec = field(default_factory=NuisanceSpec)
    hidden: int = 16  # width of W1
    steps: int = 1000  # full-batch Adam steps
    lr: float = 1e-2
    weight_decay: float = 1e-4


def make_split(cfg: ClassifierTrainConfig, seed: int, split: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Features [N, F] and labels [N] of the "train" or "heldout" split (deterministic in ``cfg`` and ``seed``)."""
    if split == "train":
        seeds, draws, stream = cfg.train_seeds, cfg.train_draws_per_class, 0
    elif split == "heldout":
        seeds, draws, stream = cfg.heldout_seeds, cfg.heldout_draws_per_class, 1
    else:
        raise ValueError(f"split must be 'train' or 'heldout', got {split!r}")
    if set(cfg.train_seeds) & set(cfg.heldout_seeds):
        raise ValueError("train and held-out scene seeds overlap: the held-out accuracy would not be held out")
    views = render_clean(seeds, cfg.render)
    return make_samples(views, draws, np.random.default_rng([seed, stream]), cfg.render.optical_depth_range,
                        cfg.nuisance)


def fit(features: torch.Tensor, labels: torch.Tensor, cfg: ClassifierTrainConfig, seed: int) -> WaterClassifier:
    """Full-batch Adam on cross-entropy. features [N, F], labels [N] → trained classifier (eval mode)."""
    gen = torch.Generator().manual_seed(seed)
    model = WaterClassifier(hidden=cfg.hidden, num_features=features.shape[1])
    with torch.no_grad():
        for lin in (model.fc1, model.fc2):  # seeded init, independent of the global RNG
            bound = 1.0 / lin.in_features**0.5
            lin.weight.copy_(torch.rand(lin.weight.shape, generator=gen) * 2 * bound - bound)
            lin.bias.copy_(torch.rand(lin.bias.shape, generator=gen) * 2 * bound - bound)
        model.set_standardisation(features.mean(dim=0), features.std(dim=0))
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    model.train()
    for step in range(cfg.steps):
        opt.zero_grad()
        loss = F.cross_entropy(model(features), labels)
        loss.backward()
        opt.step()
        if step % 500 == 0 or step == cfg.steps - 1:
            log.debug("step %d loss %.4f", step, loss.item())
    model.eval()
    return model


def confusion_matrix(model: WaterClassifier, features: torch.Tensor, labels: torch.Tensor) -> np.ndarray:
    """[3, 3] counts; rows = true class, columns = predicted (order of WATER_TYPES)."""
    with torch.no_grad():
        pred = model(features).argmax(dim=1)
    cm = np.zeros((len(WATER_TYPES), len(WATER_TYPES)), dtype=np.int64)
    np.add.at(cm, (labels.numpy(), pred.numpy()), 1)
    return cm


def accuracy(cm: np.ndarray) -> float:
    return float(np.trace(cm) / max(1, cm.sum()))


def train_classifier(out_path: str | Path, seed: int = 0, cfg: ClassifierTrainConfig | None = None) -> dict:
    """Generate the synthetic data, train, write the weights JSON to ``out_path``; return the metrics.

    Metrics: ``train_accuracy``, ``heldout_accuracy``, ``heldout_confusion`` (rows true, columns predicted,
    order clear/medium/turbid), ``n_train``, ``n_heldout``, ``seconds``. They are also stored in the file
    (with the config and seed, so the held-out set can be regenerated and the accuracy re-checked).
    """
    cfg = cfg or ClassifierTrainConfig()
    t0 = time.perf_counter()
    train, heldout = make_split(cfg, seed, "train"), make_split(cfg, seed, "heldout")
    t_data = time.perf_counter() - t0
    model = fit(*train, cfg, seed)
    with torch.no_grad():
        model.distribution = fit_distribution(model.standardised(train[0]), SHRINKAGE)
    cm_train = confusion_matrix(model, *train)
    cm_held = confusion_matrix(model, *heldout)
    metrics = {
        "train_accuracy": accuracy(cm_train),
        "heldout_accuracy": accuracy(cm_held),
        "heldout_confusion": cm_held.tolist(),
        "classes": list(WATER_TYPES),
        "n_train": int(cm_train.sum()),
        "n_heldout": int(cm_held.sum()),
        "seconds_data": round(t_data, 2),
        "seconds": round(time.perf_counter() - t0, 2),
    }
    save_classifier(model, out_path, metrics=metrics, training={"seed": seed, "config": asdict(cfg)})
    log.info("water classifier: held-out accuracy %.3f on %d images (train %.3f), %.1f s; wrote %s",
             metrics["heldout_accuracy"], metrics["n_heldout"], metrics["train_accuracy"], metrics["seconds"],
             out_path)
    return metrics


def record_distribution(path: str | Path, features: torch.Tensor | None = None) -> Path:
    """Add the training features' distribution (:mod:`.ood`) to an existing weights file, leaving its MLP,
    metrics and training record as they are. ``features``: the file's training split when already at hand
    (else regenerated from the file's config and seed, minutes); checked against the file's stored mean."""
    rec = read_weights_record(path)
    model = classifier_from_dict(rec)
    if features is None:
        cfg, seed = config_from_record(rec["training"])
        features, _ = make_split(cfg, seed, "train")
    if not torch.equal(features.mean(dim=0), model.feature_mean):
        raise ValueError("these features are not the weights' training split (their mean differs from the file's)")
    with torch.no_grad():
        model.distribution = fit_distribution(model.standardised(features), SHRINKAGE)
    return save_classifier(model, path, metrics=rec["metrics"], training=rec["training"])


def config_from_record(training: dict) -> tuple[ClassifierTrainConfig, int]:
    """The config and seed stored in a weights file's ``training`` record."""
    def tuples(d: dict) -> dict:
        return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}

    c = tuples(training["config"])
    c["render"] = RenderSpec(**tuples(c["render"]))
    c["nuisance"] = NuisanceSpec(**tuples(c["nuisance"]))
    return ClassifierTrainConfig(**c), int(training["seed"])
