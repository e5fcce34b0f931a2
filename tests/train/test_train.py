"""Plain 3DGS training: loss pieces and schedules (fast), then end-to-end runs on the synthetic scene (slow):
a held-out PSNR floor, and cancel + checkpoint + resume matching an uninterrupted run."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pipeline.config import (
    TRAIN_PRESETS,
    DensifyConfig,
    TrainConfig,
    from_dict,
    to_dict,
    train_preset,
)
from pipeline.job.options import JobOptions
from pipeline.ops.image_losses import ssim
from pipeline.scene.records import Camera, Scene, View
from pipeline.train.checkpoint import load_checkpoint, save_checkpoint
from pipeline.train.resolve import resolve_train_config
from pipeline.train.setup import (
    active_sh_degree,
    initial_gaussians,
    make_optimizers,
    means_lr,
    prepare_images,
    scene_extent,
)
from pipeline.train.trainer import CHECKPOINT_NAME, Trainer, TrainingCancelled, config_changes, train

# ---- fast unit tests ------------------------------------------------------------------------------------


def graphdeco_ssim(img1: torch.Tensor, img2: torch.Tensor) -> torch.Tensor:
    """graphdeco ``utils/loss_utils.py::ssim`` ([C, H, W] inputs): a 2-D 11x11 window, zero padding."""
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-(x**2) / (2 * 1.5**2))
    g = (g / g.sum())[:, None]
    ch = img1.shape[0]
    window = (g @ g.T)[None, None].expand(ch, 1, 11, 11).to(img1.dtype).contiguous()

    def conv(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t[None], window, padding=5, groups=ch)[0]

    mu1, mu2 = conv(img1), conv(img2)
    s1, s2, s12 = conv(img1 * img1) - mu1**2, conv(img2 * img2) - mu2**2, conv(img1 * img2) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s1 + s2 + c2))).mean()


def test_ssim_matches_graphdeco_2d_window():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(37, 53, 3, generator=g, dtype=torch.float64)
    b = (a + 0.1 * torch.randn(37, 53, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    torch.testing.assert_close(ssim(a, b), graphdeco_ssim(a.permute(2, 0, 1), b.permute(2, 0, 1)))
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-12)
    # a batch of images is the mean over the batch
    batch = ssim(torch.stack([a, a]), torch.stack([b, a]))
    assert float(batch) == pytest.approx((float(ssim(a, b)) + 1.0) / 2, abs=1e-12)


def test_schedules():
    cfg = TrainConfig(iterations=30_000)
    assert means_lr(cfg, 2.0, 0) == pytest.approx(2 * 1.6e-4)
    assert means_lr(cfg, 2.0, 15_000) == pytest.approx(2 * 1.6e-5)  # geometric midpoint
    assert means_lr(cfg, 2.0, 30_000) == pytest.approx(2 * 1.6e-6)
    assert [active_sh_degree(cfg, i) for i in (1, 999, 1000, 2999, 3000, 29_000)] == [0, 0, 1, 2, 3, 3]


def test_presets_scale_the_schedule_and_round_trip_as_json():
    paper, fast = TRAIN_PRESETS["paper"], TRAIN_PRESETS["fast"]
    assert paper.iterations == 30_000 and paper.densify == DensifyConfig() and paper.sh_degree_interval == 1000
    assert fast.iterations == 3000 and fast.sh_degree_interval == 100
    assert (fast.densify.refine_start, fast.densify.refine_stop, fast.densify.refine_every) == (50, 1500, 100)
    assert fast.densify.reset_every == 1000 and fast.densify.grow_grad2d == 2e-4
    import json

    for name in TRAIN_PRESETS:
        cfg = train_preset(name)
        assert from_dict(TrainConfig, json.loads(json.dumps(to_dict(cfg)))) == cfg
    with pytest.raises(ValueError, match="unknown training preset"):
        train_preset("slowest")


def _view(name: str, center: tuple[float, float, float], cam: Camera) -> View:
    return View(name, cam, np.eye(3), -np.asarray(center, dtype=float))


def test_scene_extent_and_image_checks():
    cam = Camera(8, 6, 10.0, 10.0, 4.0, 3.0)
    views = [_view("a", (0, 0, 0), cam), _view("b", (2, 0, 0), cam)]
    assert scene_extent(views) == pytest.approx(1.1)
    assert scene_extent(views[:1]) == 1.0
    imgs = [np.full((6, 8, 3), 0.5, np.float32), np.zeros((6, 8, 3), np.float32)]
    small_views, targets = prepare_images(views, imgs, 2, torch.device("cpu"))
    assert targets[0].shape == (3, 4, 3) and small_views[0].camera.width == 4
    torch.testing.assert_close(targets[0], torch.full((3, 4, 3), 0.5))
    with pytest.raises(ValueError, match=r"image of 'b' is \(6, 7, 3\)"):
        prepare_images(views, [imgs[0], np.zeros((6, 7, 3))], 1, torch.device("cpu"))


def test_random_init_without_points():
    cam = Camera(8, 6, 10.0, 10.0, 4.0, 3.0)
    scene = Scene([_view("a", (0, 0, 0), cam), _view("b", (2, 0, 0), cam)])  # no points
    cfg = TrainConfig(random_init_points=500, random_init_extent=3.0, sh_degree=2)
    params = initial_gaussians(scene, cfg, 1.1, torch.device("cpu"))
    means = params["means"].detach()
    assert means.shape == (500, 3) and tuple(params["shN"].shape) == (500, 8, 3)
    assert float((means - torch.tensor([1.0, 0, 0])).abs().max()) <= 3.3  # cube of half-size 3 x extent
    again = initial_gaussians(scene, cfg, 1.1, torch.device("cpu"))
    assert torch.equal(again["means"], params["means"])  # seeded


def test_fused_adam_matches_its_for_loop_twin():
    """The Gaussians' Adam is fused (one pass per tensor); torch's for-loop Adam is the reference: the same
    trajectory over 20 steps to float rounding, and the state gsplat's densification edits has the same keys."""
    cam = Camera(8, 6, 10.0, 10.0, 4.0, 3.0)
    scene = Scene([_view("a", (0, 0, 0), cam), _view("b", (2, 0, 0), cam)])
    cfg = TrainConfig(random_init_points=300, sh_degree=3)
    fused_p = initial_gaussians(scene, cfg, 1.0, torch.device("cpu"))
    ref_p = torch.nn.ParameterDict({k: torch.nn.Parameter(v.detach().clone()) for k, v in fused_p.items()})
    fused, ref = make_optimizers(fused_p, cfg, 1.0), make_optimizers(ref_p, cfg, 1.0, fused=False)
    assert all(o.param_groups[0]["fused"] for o in fused.values())
    assert not any(o.param_groups[0]["fused"] for o in ref.values())  # the twin: torch's for-loop Adam
    for step in range(20):
        for params, opts in ((fused_p, fused), (ref_p, ref)):
            grads = torch.Generator().manual_seed(step)  # the same gradients for both
            for k in sorted(params.keys()):
                params[k].grad = torch.randn(params[k].shape, generator=grads) * 1e-2
            for o in opts.values():
                o.step()
    for k in fused_p.keys():
        np.testing.assert_allclose(fused_p[k].detach().numpy(), ref_p[k].detach().numpy(), rtol=1e-5, atol=1e-6)
        assert set(fused[k].state[fused_p[k]]) == set(ref[k].state[ref_p[k]]) == {"step", "exp_avg", "exp_avg_sq"}


def test_config_changes_are_named():
    cfg = TrainConfig(iterations=100)
    assert config_changes(to_dict(cfg), cfg) == []
    saved = to_dict(TrainConfig(iterations=50, log_every=7))
    assert config_changes(saved, cfg) == ["iterations", "log_every"]
    assert config_changes({**saved, "old_field": 1}, cfg) == ["old_field"]


def test_checkpoint_refuses_other_versions(tmp_path):
    path = save_checkpoint(tmp_path / "c.pt", {"iteration": 3})
    assert load_checkpoint(path)["iteration"] == 3
    torch.save({"kind": "dualphys.trainer", "version": 999}, tmp_path / "old.pt")
    with pytest.raises(ValueError, match="version 999"):
        load_checkpoint(tmp_path / "old.pt")


# ---- end-to-end on the synthetic scene (cpu backend) ------------------------------------------------------


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory):
    """24 views at 160x120 of the generator's clean seabed (no water), split every 8th view for testing.
    Returns (train scene with the true surface points, train images, test views, test images)."""
    from pipeline.config import SynthConfig
    from pipeline.scene.images import read_image
    from pipeline.scene.loader import load_scene
    from pipeline.scene.split import split_views
    from pipeline.synth.procedural import generate_scene

    root = generate_scene(SynthConfig(views=24, width=160, height=120, preset="none"), tmp_path_factory.mktemp("s"))
    scene = load_scene(root)
    train_views, test_views = split_views(scene.views)

    def clean(views: list[View]) -> list[np.ndarray]:
        return [read_image(root / "clean" / v.name) for v in views]

    train_scene = Scene(train_views, scene.points, scene.colors, root)
    return train_scene, clean(train_views), test_views, clean(test_views)


def short_config(iterations: int, **kw) -> TrainConfig:
    """The 3DGS recipe on a short clock: SH +1 every 100 its, grow/prune every 50 its from 100 to 400."""
    densify = DensifyConfig(refine_start=100, refine_stop=400, refine_every=50, reset_every=10_000)
    base = dict(iterations=iterations, sh_degree_interval=100, densify=densify, backend="cpu", log_every=0)
    return TrainConfig(**{**base, **kw})


@pytest.mark.slow
def test_training_reaches_psnr_floor(synth_scene):
    """600 iterations on 21 views, 3 held out (every 8th). Measured: held-out PSNR 19.5 / 23.4 / 24.0 dB at
    200 / 400 / 600 iterations, 3000 -> 44k Gaussians, 25-90 s depending on machine load. The run is
    deterministic on one machine; the floor sits 2 dB under the measurement for rasterizer tuning and BLAS or
    thread-count differences elsewhere."""
    scene, images, test_views, test_images = synth_scene
    progress: list[int] = []
    res = train(scene, images, short_config(600, eval_every=200), test_views=test_views, test_images=test_images,
                on_progress=lambda i, n, m: progress.append(i))  # fmt: skip
    assert progress == list(range(1, 601))
    psnrs = [h["psnr"] for h in res.history]
    assert [h["iteration"] for h in res.history] == [200, 400, 600]
    assert psnrs[-1] >= 22.0, psnrs
    assert psnrs[0] < psnrs[-1]
    assert res.metrics["n_gaussians"] > 3000  # densification grew the cloud


@pytest.mark.slow
def test_training_with_a_coarse_start_reaches_the_psnr_floor(synth_scene):
    """The floor test's 600-iteration run with its first third at half size. Measured: held-out PSNR 23.90 dB
    (full size throughout: 24.06), 45.0k Gaussians, training 18.8 s (20.4 s); the floor is the same 22 dB."""
    scene, images, test_views, test_images = synth_scene
    res = train(scene, images, short_config(600, eval_every=600, coarse_fraction=1 / 3), test_views=test_views,
                test_images=test_images)  # fmt: skip
    assert res.history[-1]["psnr"] >= 22.0, res.history
    assert res.metrics["n_gaussians"] > 3000


@pytest.mark.slow
def test_cancel_checkpoint_resume_matches_straight_run(synth_scene, tmp_path):
    """K = 160 iterations straight vs cancelled at 80 (checkpoint written) + resumed to 160 by a second
    ``train`` call. The second half crosses densification (100, 150), an opacity reset (120) and SH degree
    steps, so params, Adam moments, strategy statistics and all RNG states must round-trip."""
    scene, images, _, _ = synth_scene
    cfg = short_config(160, densify=DensifyConfig(refine_start=40, refine_stop=400, refine_every=50,
                                                  reset_every=120), sh_degree_interval=50)  # fmt: skip
    straight = train(scene, images, cfg)

    with pytest.raises(TrainingCancelled) as exc:
        calls = iter(range(10_000))
        train(scene, images, cfg, checkpoint_dir=tmp_path, should_cancel=lambda: next(calls) >= 80)
    assert exc.value.iteration == 80 and exc.value.checkpoint == tmp_path / CHECKPOINT_NAME
    assert load_checkpoint(exc.value.checkpoint)["iteration"] == 80
    resumed = train(scene, images, cfg, checkpoint_dir=tmp_path)

    assert resumed.iteration == 160
    a, b = straight.gaussians, resumed.gaussians
    assert a["means"].shape == b["means"].shape
    # Same machine, same thread count: expected bit-identical. The tolerance only absorbs a change in
    # float summation order should the thread partition of a reduction differ between processes.
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=1e-5, atol=1e-6, msg=k)
    assert resumed.metrics["loss"] == pytest.approx(straight.metrics["loss"], rel=1e-5)


@pytest.mark.parametrize("mode", ["3dgs", "homogeneous", "dualphys"])
def test_the_saved_config_is_the_schedule_the_trainer_runs(synth_scene, mode):
    """Resolve once (issue 41): train/config.json of a job is what its trainer uses, in a medium mode too (the
    longer refinement of DensifyConfig.medium_refine_factor is in it, not added again by the trainer)."""
    scene, images, _, _ = synth_scene
    cfg = resolve_train_config(JobOptions(mode=mode), 160, None, None, views=24)
    saved = from_dict(TrainConfig, json.loads(json.dumps(to_dict(cfg))))  # what train/config.json holds
    trainer = Trainer(scene, images, saved)
    assert trainer.densifier.cfg == saved.densify
    stop = 1500 if mode == "3dgs" else 2250  # fast; a medium mode refines 1.5x longer
    assert trainer.densifier.strategy.refine_stop_iter == saved.densify.refine_stop == stop
