"""The configs several pipeline packages read, with named presets: training (``TrainConfig`` and its parts
``DensifyConfig``, ``MediumConfig``) and the generated scenes (``SynthConfig``). A config that one package reads
sits beside the code it configures (``pipeline.sfm.config.SfmConfig``, ``pipeline.ingest.intake.IngestConfig``,
``pipeline.train.probe.ProbeConfig``, ...).

Science configs are plain dataclasses (no pydantic at this layer); each field's comment is its documentation.
The training configs are frozen: a job's is resolved once (``pipeline.train.resolve``) and every variant of it
(the mode probe's, the collapse guard's retry) is made with ``dataclasses.replace``.
Service settings live in ``service/`` (pydantic-settings). ``to_dict``/``from_dict`` give the JSON form saved
next to outputs so a run can be reproduced.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

WaterPreset = Literal["none", "clear", "medium", "turbid"]


@dataclass
class SynthConfig:
    """The synthetic underwater scene generator (``pipeline.synth.procedural``)."""

    views: int = 24  # number of camera views
    width: int = 320  # image width in pixels
    height: int = 240  # image height in pixels
    preset: WaterPreset = "medium"  # water type; "none" renders the clean scene as the underwater image too
    seed: int = 0  # everything (terrain, objects, textures, path jitter) follows from it
    path: Literal["survey", "lawnmower", "forward"] = "survey"  # survey = lawnmower pass then forward pass
    altitude: float = 2.0  # m, camera height above the mean seabed on the downward pass
    fov_deg: float = 60.0  # horizontal field of view
    supersample: int = 2  # rays per pixel per axis (anti-aliasing)
    relief: float = 1.0  # scale of the seabed relief (0 = flat seabed at z = 0)
    n_rocks: int = 14
    n_corals: int = 10
    n_points: int = 3000  # true surface points written to sparse_gt/points3D.txt
    noise_std: float = 0.004  # sensor noise (std in [0, 1] units) added to the underwater image; 0 disables
    # Radial lens distortion (k1, k2) of COLMAP's RADIAL model (pipeline.synth.lens); (0, 0) = PINHOLE. When set,
    # images/, clean/, depth/ and sparse_gt/ are in the distorted geometry and pinhole/ holds pinhole companions.
    distortion: tuple[float, float] = (0.0, 0.0)
    # "srgb": the water acts on J as written (8-bit-style values); "linear": on sRGB-decoded J, re-encoded after
    water_space: Literal["srgb", "linear"] = "srgb"
    max_rays_per_view: int = 4_000_000  # supersample is lowered until width·height·s² fits (large sizes)


C = TypeVar("C")


def to_dict(cfg: Any) -> dict[str, Any]:
    """A config as a JSON-able dict."""
    return dataclasses.asdict(cfg)


def from_dict(cls: type[C], data: dict[str, Any]) -> C:
    """Build a config from a dict, refusing unknown keys (a typo must not silently fall back to a default)."""
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"unknown {cls.__name__} fields: {sorted(unknown)}")
    return cls(**data)



@dataclass(frozen=True)
class DensifyConfig:
    """Adaptive density control (``pipeline.splat.densify``): gsplat's ``DefaultStrategy``, 3DGS schedule.

    Iteration counts are those of a 30k-iteration run; ``scaled`` shrinks them for shorter presets. Iterations
    are 1-based (the first optimiser step is iteration 1), as in graphdeco's loop.
    """

    refine_start: int = 500  # grow/prune only at iterations strictly after this one
    refine_stop: int = 15_000  # no growing, pruning or opacity reset from this iteration on
    # Medium modes refine until this many times refine_stop (fast: 2,250 of 3,000 instead of 1,500): growth goes
    # on while the medium settles (it starts at a third of the run), so a seabed the water dims can still be
    # split fine enough to carry its texture (docs/DECISIONS.md, fix 6).
    medium_refine_factor: float = 1.5
    refine_every: int = 100  # grow/prune every this many iterations
    reset_every: int = 3000  # clamp opacities to 2 * prune_opacity every this many iterations
    pause_after_reset: int = 0  # skip growing/pruning for this many iterations after a reset
    grow_grad2d: float = 2e-4  # mean screen-space gradient (NDC units) above which a Gaussian grows
    grow_scale3d: float = 0.01  # max scale (x scene extent) under which a grower is cloned, else split
    prune_opacity: float = 0.005  # prune Gaussians whose opacity is below this
    prune_scale3d: float = 0.1  # after the first reset, prune Gaussians larger than this x scene extent
    max_gaussians: int = 0  # stop growing at this count (0 = no cap); a memory/time guard for CPU runs

    def scaled(self, factor: float) -> DensifyConfig:
        """The schedule of a run ``factor`` times as long: refine start/stop scale with the run.

        ``refine_every`` does not scale: it is the window of views whose gradients are averaged before a
        Gaussian grows, and every refinement grows all Gaussians above the threshold, so scaling it multiplies
        growth. ``reset_every`` scales but stays >= 10 refinements, so opacities recover between resets (both
        measured: docs/DECISIONS.md, "Numbers behind code comments").
        """
        return dataclasses.replace(
            self,
            refine_start=max(1, round(self.refine_start * factor)),
            refine_stop=max(1, round(self.refine_stop * factor)),
            reset_every=max(round(self.reset_every * factor), 10 * self.refine_every),
            pause_after_reset=round(self.pause_after_reset * factor),
        )


@dataclass(frozen=True)
class MediumConfig:
    """The water model in training (``pipeline.medium``); modes ``homogeneous`` and ``dualphys``."""

    rgb_attenuation: bool = True  # eq. 5's edge-perception modulation (dualphys); off = homogeneous attenuation
    multiscale_scattering: bool = True  # eq. 7/8's multi-scale depth-aware backscatter; off = eq. 6
    water_adaptation: bool = True  # let the water-type classifier set rates, α(w), β(w) and T
    gamma: float = 0.3  # eq. 5 edge modulation strength γ
    lam: float = 0.3  # eq. 8 depth-edge modulation λ
    delta: float = 0.5  # eq. 8 multi-scale modulation δ
    start_fraction: float = 1 / 3  # the medium switches on after this fraction of iterations (10k of 30k)
    lr_attenuation: float = 5e-4  # paper §5 base rate of the attenuation model
    lr_scattering: float = 1e-4  # paper §5 base rate of the scattering model
    lr_reference_iterations: int = 20_000  # medium iterations the paper's rates are meant for; shorter runs
    #                                        scale both rates up by reference / actual
    alpha_w: float = 1.0  # α(w) in L_wat (controller: clear 1.2, turbid 0.8)
    beta_w: float = 1.0  # β(w) in L_wat (controller: clear 0.8, turbid 1.2)
    water_factor: float = 1.0  # T in eq. 5
    init_optical_depth: tuple[float, float, float] = (0.6, 0.3, 0.25)  # β·(median scene depth) at the start
    losses: tuple[str, ...] = ("ab", "wat", "edge", "ms", "floater", "surface")  # enabled terms beyond L_basic
    loss_weights: dict[str, float] = field(default_factory=dict)  # overrides of pipeline.medium.losses.LossWeights
    max_sh_degree: int = 1  # low-order SH keeps J view-consistent, so range-dependent colour goes to the water
    densify_transmission: bool = True  # densify on the scene's scale: screen gradients / the view's transmission
    colour_prior: Literal["tracks", "grey_world"] = "tracks"  # L_attenuation: anchor β_D to the multi-view
    #   estimate from the sparse points (pipeline.medium.estimate), or the grey-world prior on J
    #   ("tracks" falls back to grey-world when the points cannot measure the water)

    def __post_init__(self) -> None:
        # JSON round trips turn tuples into lists.
        object.__setattr__(self, "init_optical_depth", tuple(float(x) for x in self.init_optical_depth))
        object.__setattr__(self, "losses", tuple(self.losses))


TrainMode = Literal["3dgs", "homogeneous", "dualphys"]
Backend = Literal["auto", "torch", "cpu", "cuda"]


@dataclass(frozen=True)
class TrainConfig:
    """Training (``pipeline.train.trainer``). Defaults are graphdeco 3DGS's 30k-iteration recipe."""

    mode: TrainMode = "3dgs"  # "3dgs": no medium; "homogeneous": eq. 3's global water; "dualphys": eqs. 5-8
    iterations: int = 30_000
    seed: int = 0  # view order, random init and densification splits follow from it
    backend: Backend = "auto"  # rasterizer backend (pipeline.splat.rasterize)
    downscale: int = 1  # train on images shrunk by this integer factor (area averaging)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # RGB composited behind the Gaussians
    # 3dgs only: a random background colour every step (gsplat's random_bkgd), so no Gaussian can paint a dark
    # surface by letting the black background through; the mode probe's runs use it (pipeline.train.probe)
    random_background: bool = False
    # "srgb": the physics runs on the photos' encoded values; "linear": on linear light (the photos decoded with
    # the sRGB EOTF; renders encoded back for display): JobOptions.colour_space, docs/DECISIONS.md
    colour_space: str = "srgb"
    # Each training view's exposure and white balance as gains per channel on linear light (pipeline.train.exposure):
    # "fit": the water fit's gains (pipeline.medium.exposure_fit), held; "learn": learned with the model (from the
    # fit's gains where there are some); "off"; "auto": fit in the medium modes, learn in 3dgs (docs/DECISIONS.md,
    # "Exposure per view"). exposure_lr: lr of their log when learned, decaying to a tenth; exposure_weight: the
    # penalty on them
    exposure: str = "auto"
    exposure_lr: float = 5e-3
    exposure_weight: float = 1e-3
    sh_degree: int = 3  # maximum spherical-harmonics degree
    sh_degree_interval: int = 1000  # the active SH degree rises by one every this many iterations
    lr_means: float = 1.6e-4  # initial position learning rate, multiplied by the scene extent
    lr_means_final: float = 1.6e-6  # final position lr (x extent); exponential decay over `iterations`
    lr_sh0: float = 2.5e-3  # SH DC (base colour)
    lr_shN: float = 2.5e-3 / 20  # higher SH bands
    lr_opacities: float = 0.05  # logit opacities
    lr_scales: float = 0.005  # log scales
    lr_quats: float = 0.001  # rotations
    adam_eps: float = 1e-15
    ssim_weight: float = 0.2  # loss = (1 - w) * L1 + w * (1 - SSIM)
    init_opacity: float = 0.1
    init_scale: float = 1.0  # multiplier on the initial kNN scale
    random_init_points: int = 20_000  # Gaussians drawn when the scene has no points (gsplat: 100k)
    random_init_extent: float = 3.0  # half-size of the random-init cube around the cameras, x scene extent
    checkpoint_every: int = 2000  # write latest checkpoint every this many its (0 = end/cancel only)
    eval_every: int = 0  # held-out PSNR every this many iterations (0 = at the end only)
    log_every: int = 100  # log a progress line every this many iterations
    # torch.compile the step's loss graphs: "auto" for runs of >= 2,000 iterations when a C++ compiler is found,
    # "on", "off" (pipeline.ops.jit; the same losses, fused: numbers agree to float rounding)
    compile_losses: str = "auto"
    # Coarse start (issue 16): iterations 1..coarse_fraction x iterations train on the images and cameras shrunk
    # coarse_downscale times (area averaging), never past the medium's start in medium modes
    # (pipeline.train.schedule.coarse_iterations). The early model is coarse anyway; its steps cost a quarter of
    # the pixels. 0 = full resolution throughout (graphdeco's recipe; the presets fast and balanced use 1/3:
    # docs/DECISIONS.md, "Whole-job speed").
    coarse_fraction: float = 0.0
    coarse_downscale: int = 2
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    medium: MediumConfig = field(default_factory=MediumConfig)  # used by the homogeneous and dualphys modes

    def __post_init__(self) -> None:
        # JSON round trips turn the nested config into a dict and the tuple into a list.
        if isinstance(self.densify, dict):
            object.__setattr__(self, "densify", from_dict(DensifyConfig, self.densify))
        if isinstance(self.medium, dict):
            object.__setattr__(self, "medium", from_dict(MediumConfig, self.medium))
        if self.exposure not in ("auto", "fit", "learn", "off"):
            raise ValueError(f"exposure must be auto, fit, learn or off, got {self.exposure!r}")
        if self.mode not in ("3dgs", "homogeneous", "dualphys"):
            raise ValueError(f"mode must be 3dgs, homogeneous or dualphys, got {self.mode!r}")
        object.__setattr__(self, "background", tuple(float(c) for c in self.background))
        if not 0.0 <= self.coarse_fraction <= 1.0 or self.coarse_downscale < 1:
            raise ValueError(f"coarse_fraction must be in [0, 1] and coarse_downscale >= 1, got "
                             f"{self.coarse_fraction}, {self.coarse_downscale}")
        if len(self.background) != 3:
            raise ValueError(f"background must have 3 components, got {self.background}")


def medium_densify(densify: DensifyConfig) -> DensifyConfig:
    """``densify`` as a medium mode runs it: refinement stops ``medium_refine_factor`` times later, and the factor
    is spent (1.0), so applying this twice changes nothing."""
    return dataclasses.replace(densify, refine_stop=round(densify.refine_stop * densify.medium_refine_factor),
                               medium_refine_factor=1.0)


def rescheduled(cfg: TrainConfig, iterations: int, *, checkpoint_every: int, max_gaussians: int) -> TrainConfig:
    """``cfg`` as a run of ``iterations``: the 30k schedule (densification, SH warm-up) compressed to fit
    (``DensifyConfig.scaled``), this checkpoint cadence and Gaussian cap (0 = no cap); every other field kept.
    The densification section is the 30k recipe's, rescaled, not ``cfg``'s (a scaled schedule cannot be
    scaled again without knowing what it was scaled from)."""
    factor = iterations / 30_000
    return dataclasses.replace(
        cfg,
        iterations=iterations,
        sh_degree_interval=max(1, round(1000 * factor)),
        densify=dataclasses.replace(DensifyConfig().scaled(factor), max_gaussians=max_gaussians),
        checkpoint_every=checkpoint_every,
    )


def scaled_train_config(iterations: int, checkpoint_every: int, max_gaussians: int = 0) -> TrainConfig:
    """A run of ``iterations`` with the 30k schedule (densification, SH warm-up) compressed to fit
    (``DensifyConfig.scaled``); ``max_gaussians`` 0 = no cap."""
    return rescheduled(TrainConfig(), iterations, checkpoint_every=checkpoint_every, max_gaussians=max_gaussians)


# fast: a preview (refine 50-1500 every 100, reset at 1000, SH +1 every 100, at most 100k Gaussians, the first
# third at half resolution);
# balanced: a third of the paper schedule (refine 167-5000, reset every 1000, at most 300k, the first third at half
# resolution);
# paper: graphdeco's 30k recipe unchanged, no cap.
# The configs are frozen; derive variants with ``dataclasses.replace`` (the resolved job config:
# pipeline.train.resolve).
TRAIN_PRESETS: dict[str, TrainConfig] = {
    "fast": dataclasses.replace(scaled_train_config(3_000, checkpoint_every=500, max_gaussians=100_000),
                                coarse_fraction=1 / 3),
    "balanced": dataclasses.replace(scaled_train_config(10_000, checkpoint_every=1000, max_gaussians=300_000),
                                    coarse_fraction=1 / 3),
    "paper": scaled_train_config(30_000, checkpoint_every=2000, max_gaussians=0),
}


def train_preset(name: str) -> TrainConfig:
    """A private copy of a named training preset."""
    if name not in TRAIN_PRESETS:
        raise ValueError(f"unknown training preset {name!r}; choose from {sorted(TRAIN_PRESETS)}")
    return from_dict(TrainConfig, to_dict(TRAIN_PRESETS[name]))

__all__ = ["DensifyConfig", "MediumConfig", "SynthConfig", "TRAIN_PRESETS", "TrainConfig", "from_dict",
           "medium_densify", "rescheduled", "scaled_train_config", "to_dict", "train_preset"]
