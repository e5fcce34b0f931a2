"""LPIPS-VGG: loads both standard weight layouts, is zero on identical images, and is never faked."""

from __future__ import annotations

import pytest
import torch

from pipeline.evaluate.perceptual import (
    BACKBONE_ENV,
    LAYER_CHANNELS,
    LPIPSVGG,
    WEIGHTS_ENV,
    LPIPSUnavailable,
    load_lpips,
    lpips_distance,
    lpips_from_env,
)

_SLICES = ((0, 4), (4, 9), (9, 16), (16, 23), (23, 30))


def _random_model(seed: int = 0) -> LPIPSVGG:
    torch.manual_seed(seed)
    m = LPIPSVGG()
    for lin in m.lins:
        lin.weight.data.uniform_(0.0, 1.0)  # LPIPS's learned weights are non-negative
    return m.eval()


def _lpips_layout(m: LPIPSVGG) -> dict[str, torch.Tensor]:
    """The ``lpips`` package's whole-model state dict: net.sliceK.<torchvision index>.*, linK.model.1.weight."""
    sd: dict[str, torch.Tensor] = {}
    for k, (lo, hi) in enumerate(_SLICES, start=1):
        for i in range(lo, hi):
            layer = m.features[i]
            if isinstance(layer, torch.nn.Conv2d):
                sd[f"net.slice{k}.{i}.weight"], sd[f"net.slice{k}.{i}.bias"] = layer.weight, layer.bias
    for i, lin in enumerate(m.lins):
        sd[f"lin{i}.model.1.weight"] = lin.weight
    sd["scaling_layer.shift"] = m.shift  # present in the package's dict, unused by the loader
    return {k: v.detach().clone() for k, v in sd.items()}


@pytest.fixture(scope="module")
def images() -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    a = torch.rand(48, 64, 3, generator=g)
    b = (a + 0.15 * torch.randn(48, 64, 3, generator=g)).clamp(0, 1)
    return a, b


def test_both_weight_layouts_load_to_the_same_network(tmp_path, images):
    ref = _random_model()
    full = tmp_path / "lpips_full.pth"
    torch.save(_lpips_layout(ref), full)
    lins = tmp_path / "vgg.pth"  # the lpips package's file: linear layers only
    torch.save({k: v for k, v in _lpips_layout(ref).items() if k.startswith("lin")}, lins)
    backbone = tmp_path / "vgg16.pth"  # torchvision's layout
    torch.save({f"features.{k}": v for k, v in ref.features.state_dict().items()}
               | {"classifier.0.weight": torch.zeros(2, 2)}, backbone)
    a, b = images
    d_ref = lpips_distance(ref, a, b)
    d_full = lpips_distance(load_lpips(full), a, b)
    d_split = lpips_distance(load_lpips(lins, backbone), a, b)
    assert d_ref > 0.01
    assert d_full == pytest.approx(d_ref, rel=1e-6) and d_split == pytest.approx(d_ref, rel=1e-6)
    assert lpips_distance(ref, a, a) == 0.0
    assert lpips_distance(ref, b, a) == pytest.approx(d_ref, rel=1e-6)


def test_distance_is_bounded_by_the_unit_normalised_features(images):
    # With all linear weights 1, each layer adds the mean over pixels of |f_a - f_b|^2 of unit vectors: <= 4.
    m = _random_model()
    for lin in m.lins:
        lin.weight.data.fill_(1.0)
    a, b = images
    assert 0 < lpips_distance(m, a, b) <= 4.0 * len(LAYER_CHANNELS)
    assert lpips_distance(m, a, 1 - a) > lpips_distance(m, a, b)  # an inverted image is further than a noisy one


def test_missing_or_partial_weights_give_a_reason_not_a_number(tmp_path, monkeypatch):
    monkeypatch.delenv(WEIGHTS_ENV, raising=False)
    s = lpips_from_env()
    assert s.model is None and WEIGHTS_ENV in s.reason
    lins = tmp_path / "vgg.pth"
    torch.save({f"lin{i}.model.1.weight": torch.ones(1, c, 1, 1) for i, c in enumerate(LAYER_CHANNELS)}, lins)
    monkeypatch.setenv(WEIGHTS_ENV, str(lins))
    monkeypatch.delenv(BACKBONE_ENV, raising=False)
    s = lpips_from_env()
    assert s.model is None and BACKBONE_ENV in s.reason
    torch.save({"lin0.model.1.weight": torch.ones(1, 64, 1, 1)}, lins)
    with pytest.raises(LPIPSUnavailable, match="lin1"):
        load_lpips(lins)
    monkeypatch.setenv(WEIGHTS_ENV, str(tmp_path / "nowhere.pth"))
    assert "does not exist" in lpips_from_env().reason
