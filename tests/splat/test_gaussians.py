"""Gaussian parameters: init from points (kNN scale vs brute force), random init, shape checks."""

from __future__ import annotations

import math

import pytest
import torch

from pipeline.splat.gaussians import (
    GAUSSIAN_KEYS,
    activate,
    check_gaussians,
    init_from_points,
    init_random,
    knn_rms_distance,
    sh0_to_rgb,
    sh_degree_of,
)


def brute_knn_rms(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Obvious O(P^2) float64 reference: full distance matrix, self excluded by index."""
    p = points.double()
    d2 = (p[:, None, :] - p[None, :, :]).square().sum(-1)  # [P, P]
    d2.fill_diagonal_(math.inf)
    nearest = d2.sort(dim=1).values[:, :k]  # [P, k]
    return nearest.mean(1).clamp_min(1e-7).sqrt()


def test_knn_rms_matches_brute_force_across_blocks():
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(700, 3, generator=g) * torch.tensor([3.0, 1.0, 0.2])
    pts[650:] = pts[:50]  # exact duplicates: their nearest distance is 0, must not be excluded as "self"
    ref = brute_knn_rms(pts)
    for block in (700 * 700, 700 * 64, 700 * 7, 1):  # one block, several, 7 rows, one row at a time
        got = knn_rms_distance(pts, max_block_elems=block)
        torch.testing.assert_close(got.double(), ref, rtol=1e-5, atol=1e-6)


def test_knn_rejects_too_few_points():
    with pytest.raises(ValueError, match="more than k=3"):
        knn_rms_distance(torch.zeros(3, 3))


def test_init_from_points():
    g = torch.Generator().manual_seed(1)
    pts, cols = torch.rand(200, 3, generator=g), torch.rand(200, 3, generator=g)
    params = init_from_points(pts, cols, sh_degree=3, init_opacity=0.1)
    assert check_gaussians(params) == 200 and set(params) == set(GAUSSIAN_KEYS)
    assert tuple(params["shN"].shape) == (200, 15, 3) and sh_degree_of(params) == 3
    assert all(p.requires_grad and p.dtype == torch.float32 for p in params.values())
    act = activate(params)
    torch.testing.assert_close(act.means, pts)
    torch.testing.assert_close(sh0_to_rgb(params["sh0"][:, 0]), cols)
    torch.testing.assert_close(act.opacities, torch.full((200,), 0.1))
    expected_scales = brute_knn_rms(pts).float()[:, None].expand(200, 3)
    torch.testing.assert_close(act.scales, expected_scales, rtol=1e-5, atol=0)
    torch.testing.assert_close(params["quats"].detach(), torch.tensor([1.0, 0, 0, 0]).expand(200, 4))
    assert act.sh.shape == (200, 16, 3) and float(params["shN"].detach().abs().max()) == 0.0


def test_init_random_inside_box_and_seeded():
    lo, hi = torch.tensor([-1.0, 0.0, 2.0]), torch.tensor([1.0, 0.5, 3.0])
    a = init_random(500, lo, hi, generator=torch.Generator().manual_seed(3), sh_degree=1)
    b = init_random(500, lo, hi, generator=torch.Generator().manual_seed(3), sh_degree=1)
    assert ((a["means"] >= lo) & (a["means"] <= hi)).all()
    assert tuple(a["shN"].shape) == (500, 3, 3)
    for k in GAUSSIAN_KEYS:
        assert torch.equal(a[k], b[k])
    rgb = sh0_to_rgb(a["sh0"][:, 0].detach())
    assert float(rgb.min()) >= 0.0 and float(rgb.max()) <= 1.0


def test_check_gaussians_names_bad_shape():
    params = dict(init_from_points(torch.rand(10, 3), torch.rand(10, 3)))
    params["quats"] = torch.zeros(10, 3)
    with pytest.raises(ValueError, match=r"quats must have shape \(10, 4\), got \(10, 3\)"):
        check_gaussians(params)
    params = dict(init_from_points(torch.rand(10, 3), torch.rand(10, 3)))
    params["shN"] = torch.zeros(10, 14, 3)
    with pytest.raises(ValueError, match="shN"):
        check_gaussians(params)
