"""The ``cuda`` backend (gsplat) against the ``torch`` reference. Skipped on CPU-only machines (all of ours):
it is the one backend we cannot run here."""

from __future__ import annotations

import pytest
import torch

from pipeline.splat.random_scene import random_scene
from pipeline.splat.rasterize import rasterize

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")

W, H = 64, 48


def test_cuda_matches_reference():
    s = random_scene(2000, W, H, seed=1, opacity=(0.05, 0.6))  # away from gsplat's 0.999 cap (ours: 0.99)
    outs = {}
    for backend, device in (("cuda", "cuda"), ("torch", "cpu")):
        params = [p.to(device).requires_grad_() for p in s.params()]
        img, alpha, info = rasterize(
            *params, s.viewmats.to(device), s.Ks.to(device), W, H, render_mode="RGB+ED", backend=backend
        )
        (img.sum() + alpha.sum()).backward()
        outs[backend] = (img.detach().cpu(), alpha.detach().cpu(), params[0].grad.cpu(), info)
    assert outs["cuda"][3]["means2d"].shape == (1, 2000, 2)
    assert float((outs["cuda"][0] - outs["torch"][0]).abs().max()) < 1e-3
    assert float((outs["cuda"][1] - outs["torch"][1]).abs().max()) < 1e-3
    g_c, g_t = outs["cuda"][2], outs["torch"][2]
    assert float((g_c - g_t).abs().max()) <= 1e-2 * float(g_t.abs().max())
