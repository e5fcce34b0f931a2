"""A training resumed in another process repeats the uninterrupted run bit for bit, whether each process compiled
the numba kernels afresh or loaded them from the disk cache (issue 44, item 6).

Each run is its own interpreter with ``NUMBA_CACHE_DIR`` set: an empty folder compiles every kernel (a fresh
host), a folder an earlier run filled loads them (a warm worker, a resumed ``dualphys run``). Until raster_bwd
stopped being cached, a loaded raster_bwd gave other last bits than a fresh one and the resumed model drifted
(the cause: ``pipeline/splat/_cpu_raster_kernels.py``'s docstring). The children report how many kernels they
loaded and compiled, so each case provably took the path it names.

Scene: the suite's 12-view 160x120 `medium` scene; 80 iterations of plain 3DGS (checkpoint at 40; refinements
at 20, 40, 60; SH degree steps at 30 and 60), so the resumed half has densification and SH steps to carry over.
The medium is torch, not numba (its resume: tests/train/test_train_medium.py). Measured: a child compiling every
kernel takes 40-50 s on the shared 2-core machine, one loading them ~8 s.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.config import SynthConfig
from pipeline.synth.procedural import generate_scene

REPO = Path(__file__).resolve().parents[2]
ITERATIONS, CHECKPOINT_EVERY = 80, 40

# Runs one case and prints one JSON line: sha256 of every output, and per kernel (cache hits, cache misses).
CHILD = """
import hashlib, json, sys
from pathlib import Path

import numba
import torch

from pipeline.config import DensifyConfig, TrainConfig
from pipeline.ops.image_losses import ssim
from pipeline.scene.images import read_image
from pipeline.scene.loader import load_scene
from pipeline.splat import _cpu_project_kernels, _cpu_raster_kernels
from pipeline.splat.random_scene import random_scene
from pipeline.splat.rasterize import rasterize
from pipeline.train.trainer import CHECKPOINT_NAME, TrainingCancelled, train
from pipeline.ops import _ssim_kernels

cases, arg = sys.argv[1].split("+"), json.loads(sys.argv[2])


def sha(t):
    return hashlib.sha256(t.detach().contiguous().numpy().tobytes()).hexdigest()


out = {}
if "kernels" in cases:  # every rasterizer kernel (both render modes, SH 0 and 3) and the SSIM kernels, fwd + bwd
    for sh_degree, mode in ((None, "RGB"), (3, "RGB+ED")):
        s = random_scene(3000, 64, 48, seed=1, sh=sh_degree is not None)
        params = [p.detach().clone().requires_grad_() for p in s.params()]
        img, alpha, _ = rasterize(*params, s.viewmats, s.Ks, 64, 48, sh_degree=sh_degree, backend="cpu",
                                  render_mode=mode)
        target = torch.linspace(0, 1, img.numel()).reshape(img.shape)
        ((img - target).abs().sum() + alpha.sum()).backward()
        out.update({f"{mode} image": sha(img), f"{mode} alpha": sha(alpha)})
        out.update({f"{mode} grad {i}": sha(p.grad) for i, p in enumerate(params)})
    a = torch.rand(1, 48, 64, 3, generator=torch.Generator().manual_seed(0), requires_grad=True)
    b = torch.rand(1, 48, 64, 3, generator=torch.Generator().manual_seed(1))
    value = ssim(a, b)
    value.backward()
    out.update({"ssim": sha(value), "ssim grad": sha(a.grad)})
case = cases[-1]
if case != "kernels":  # training: "straight" to the end, "stop" after the first checkpoint, "resume" from it
    root, ckdir = Path(arg["scene"]), Path(arg["checkpoints"])
    scene = load_scene(root)
    images = [read_image(root / "images" / v.name) for v in scene.views]
    densify = DensifyConfig(refine_start=20, refine_stop=70, refine_every=20, reset_every=10_000)
    cfg = TrainConfig(iterations=arg["iterations"], checkpoint_every=arg["checkpoint_every"], sh_degree_interval=30,
                      densify=densify, backend="cpu", log_every=0)
    ckpt = ckdir / CHECKPOINT_NAME
    stop = (lambda: ckpt.exists()) if case == "stop" else None
    try:
        res = train(scene, images, cfg, checkpoint_dir=None if case == "straight" else ckdir, should_cancel=stop)
        out["iteration"] = res.iteration
        out.update({k: sha(v) for k, v in sorted(res.gaussians.items())})
    except TrainingCancelled as exc:
        out["iteration"] = exc.iteration
kernels = {}
for mod in (_cpu_project_kernels, _cpu_raster_kernels, _ssim_kernels):
    for name in dir(mod):
        d = getattr(mod, name)
        if isinstance(d, numba.core.registry.CPUDispatcher) and d.overloads:
            st = d.stats
            kernels[name] = [sum(st.cache_hits.values()), sum(st.cache_misses.values()), st.cache_path is not None]
out["kernels"] = kernels
print(json.dumps(out))
"""


def _run(case: str, cache: Path, **arg) -> dict:
    """One case in a new interpreter whose numba cache is ``cache``; its JSON report."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_CACHE_DIR")}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])
    env["NUMBA_CACHE_DIR"] = str(cache)
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    out = subprocess.run([sys.executable, "-c", CHILD, case, json.dumps(arg)], env=env, cwd=REPO,
                         capture_output=True, text=True, timeout=600)  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    logging.getLogger(__name__).info("%s in %s: %s", case, cache.name, out.stdout.strip().splitlines()[-1][-300:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def _assert_path(report: dict, loaded: bool) -> None:
    """Every kernel the child ran that numba caches was loaded (``loaded``) or else compiled, none the other way;
    raster_bwd is never cached, so it compiled in either case."""
    kernels = report["kernels"]
    assert {"raster_bwd", "bin_and_pack", "raster_fwd", "project_bwd"} <= set(kernels), sorted(kernels)
    assert kernels.pop("raster_bwd")[::2] == [0, False]  # no cache: never a hit
    assert len(kernels) >= 4 and all(cached for _, _, cached in kernels.values()), kernels
    if loaded:
        assert all(hits > 0 and misses == 0 for hits, misses, _ in kernels.values()), kernels
    else:
        assert all(hits == 0 and misses > 0 for hits, misses, _ in kernels.values()), kernels


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
    """The scene, a numba cache filled by one fresh run, and that run's reports: the kernels' outputs and the
    uninterrupted training (both compiled, not loaded)."""
    tmp = tmp_path_factory.mktemp("kernel-cache")
    scene = generate_scene(SynthConfig(views=12, width=160, height=120, preset="medium", seed=0), tmp / "scene")
    cache = tmp / "numba-a"
    cache.mkdir()
    straight = _run("kernels+straight", cache, scene=str(scene), checkpoints=str(tmp / "unused"),
                    iterations=ITERATIONS, checkpoint_every=CHECKPOINT_EVERY)  # fmt: skip
    _assert_path(straight, loaded=False)
    assert straight["iteration"] == ITERATIONS
    return tmp, scene, cache, straight


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_kernels_give_the_same_bits_loaded_as_compiled(fresh):
    """Every kernel's outputs (image, alpha, gradients of all five inputs; SSIM and its gradient) in a process
    that loads the cache equal those of the process that compiled it."""
    _, _, cache, compiled = fresh
    loaded = _run("kernels", cache)
    _assert_path(loaded, loaded=True)
    assert {"ssim_fwd", "ssim_bwd"} <= set(loaded["kernels"])
    names = sorted(k for k in compiled if k.startswith(("RGB", "ssim")))
    assert len(names) == 16
    assert {k: loaded[k] for k in names} == {k: compiled[k] for k in names}


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_resumed_training_repeats_the_straight_run_in_any_process(fresh, tmp_path):
    """Stopped after its first checkpoint by a process compiling every kernel (an empty cache: another host),
    resumed by one loading them (the cache the straight run filled), and again by the stopping process's own
    now-warm cache: each resumed model equals the uninterrupted, freshly compiled run bit for bit."""
    tmp, scene, warm, straight = fresh
    other = tmp_path / "numba-b"
    other.mkdir()
    ck = tmp_path / "train"
    common = dict(scene=str(scene), iterations=ITERATIONS, checkpoint_every=CHECKPOINT_EVERY)
    stopped = _run("stop", other, checkpoints=str(ck), **common)
    _assert_path(stopped, loaded=False)
    assert stopped["iteration"] == CHECKPOINT_EVERY
    shutil.copytree(ck, tmp_path / "train-2")
    model = sorted(k for k in straight if k not in {"kernels", "iteration"} and not k.startswith(("RGB", "ssim")))
    assert len(model) >= 6, model
    for cache, ckdir in ((warm, ck), (other, tmp_path / "train-2")):
        resumed = _run("resume", cache, checkpoints=str(ckdir), **common)
        _assert_path(resumed, loaded=True)
        assert resumed["iteration"] == ITERATIONS
        assert {k: resumed[k] for k in model} == {k: straight[k] for k in model}, cache.name
