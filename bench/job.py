"""Whole-job speed (issue 16, part 5): a fast job stage by stage, the training step op by op, numba compile cost.

1. **The job**: a generated 24-view ``medium`` scene (320x240 by default) run as ``dualphys run <images> --preset
   fast`` does (mode auto, ingest → sfm → classify → train (probe + training) → evaluate → restore → export), in
   a fresh process per run. Prints wall time per stage, the probe's share, held-out PSNR and the steps' sections.
   The compiled loss graphs' cache (``TORCHINDUCTOR_CACHE_DIR``) starts empty under ``--out``: round 0 pays the
   compile as a fresh install's first job at that image size does, later rounds load the graphs (``--rounds 2``
   gives both; the table's ratio is of the medians, read the rounds for cold against warm; ``--keep-graphs``
   keeps an earlier run's graphs, so every round is warm).
   ``--compare <checkout>`` runs the same job with another checkout's ``pipeline`` (e.g. a worktree of the
   baseline commit), alternating the order every round, so both see the same load: the ratio is the number.
2. **The step profile** at each ``--profile-sizes`` (default 320x240 and 640x480): the finished job's model
   (its checkpoint) and scene, cameras and targets resized to the size, ``--profile-steps`` steps from the middle
   of the run (densification still on, the medium on if the job chose a medium mode), timed by
   :mod:`pipeline.profiling` sections: projection and compositing forward/backward, SSIM, medium nets,
   losses, backward, optimizer, densification, and the rest (Python overhead). SSIM and the medium's backward run
   inside autograd's backward; they are timed alone (forward + backward on the same tensors) beside it.
3. **numba compile**: the first projection + compositing forward/backward in a new process with an empty
   cache directory (``NUMBA_CACHE_DIR``), then again in a new process with that cache filled.

Absolute times on the 2 shared cores drift (±30 %); compare within one run. ``--json`` makes the last stdout line
a JSON object.

    python bench/job.py --out /tmp/dualphys-job --compare /tmp/baseline-worktree --rounds 1
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

HERE = Path(__file__).resolve().parent
OURS = HERE.parent


# -- child processes -------------------------------------------------------------------------------------------

def _child_job(job: Path, images: Path, mode: str = "auto") -> None:
    """Run one fast job (``mode``: the job's --mode) in this process; print a JSON line with the stage table (this
    checkout's pipeline)."""
    import resource

    from pipeline.job.layout import JobLayout
    from pipeline.job.options import JobOptions
    from pipeline.job.runner import run_job

    try:
        from pipeline.profiling import collecting
    except ImportError:  # a checkout from before the profiling hook
        import contextlib

        def collecting():
            return contextlib.nullcontext({})

    t0 = time.perf_counter()
    with collecting() as sections:
        run_job(job, JobOptions(source=str(images), preset="fast", mode=mode))
    wall = time.perf_counter() - t0
    layout = JobLayout(job)
    rep = json.loads(layout.report_json.read_text())
    sel = rep.get("selection") or {}
    setup = sel.get("probe_setup") or {}
    train = json.loads(layout.train_result.read_text())
    print(json.dumps({
        "wall_s": wall, "stages_s": rep["timings"]["stages_s"], "probe_s": setup.get("seconds"),
        "train_steps_s": train.get("elapsed_s"), "iterations": train.get("iterations"), "mode": rep["mode"],
        "test_psnr": rep["metrics"]["test"]["psnr"], "n_gaussians": train.get("n_gaussians"),
        "probe": {m: s.get("psnr") for m, s in (sel.get("probe") or {}).items()},
        "sections": dict(sections), "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }))


def _child_numba(size: str) -> None:
    """Time the first and second projection + compositing forward/backward in this process (the cache directory
    is the parent's choice: empty = a fresh install)."""
    import torch

    from pipeline.splat.random_scene import random_scene
    from pipeline.splat.rasterize import rasterize

    w, h = (int(x) for x in size.split("x"))
    times = []
    for _ in range(2):
        s = random_scene(5_000, w, h, seed=0, sh=True)
        params = [p.requires_grad_(True) for p in s.params()]
        t0 = time.perf_counter()
        img, alpha, _ = rasterize(*params, s.viewmats, s.Ks, w, h, sh_degree=3, backend="cpu",
                                  render_mode="RGB+ED")
        (img.sum() + alpha.sum()).backward()
        times.append(time.perf_counter() - t0)
    print(json.dumps({"first_s": times[0], "second_s": times[1], "threads": torch.get_num_threads()}))


def _run_child(checkout: Path, args: list[str], env: dict[str, str] | None = None) -> dict:
    """This script in a new process with ``checkout``'s pipeline first on the path; its last stdout line."""
    e = {**os.environ, "PYTHONPATH": str(checkout), **(env or {})}
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, str(Path(__file__).resolve()), *args], cwd=checkout, env=e,
                       capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"child {args} in {checkout} failed:\n{p.stderr[-4000:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["process_s"] = time.perf_counter() - t0
    return out


# -- the step profile -----------------------------------------------------------------------------------------

def step_profile(job: Path, size: str, steps: int) -> dict:
    """``steps`` training steps of the finished ``job``'s model at ``size``, by section (ms per step)."""
    import dataclasses

    import torch
    import torch.nn.functional as F

    from pipeline.config import TrainConfig, from_dict
    from pipeline.job.layout import JobLayout
    from pipeline.ops.image_losses import ssim
    from pipeline.profiling import collecting
    from pipeline.scene.loader import load_scene
    from pipeline.scene.split import split_views
    from pipeline.train.checkpoint import load_checkpoint
    from pipeline.train.setup import load_training_images
    from pipeline.train.trainer import Trainer

    layout = JobLayout(job)
    w, h = (int(x) for x in size.split("x"))
    cfg = from_dict(TrainConfig, json.loads(layout.train_config.read_text()))
    scene = load_scene(layout.scene)
    train_views, _ = split_views(scene.views)
    sub = scene.subset(train_views)
    factor = w / (sub.views[0].camera.width // cfg.downscale)
    small = load_training_images(sub.views, cfg.downscale, cfg.colour_space)
    views = [dataclasses.replace(v, camera=v.camera.scaled(w / v.camera.width)) for v in sub.views]
    sub = dataclasses.replace(sub, views=views)
    h, w = views[0].camera.height, views[0].camera.width  # SfM's undistorted size scaled (e.g. 319x239 -> 640x479)
    targets = [F.interpolate(t.permute(2, 0, 1)[None], size=(h, w), mode="bilinear")[0].permute(1, 2, 0)
               for t in small]
    cfg = dataclasses.replace(cfg, downscale=1, log_every=0, eval_every=0, checkpoint_every=0)
    tr = Trainer(sub, targets, cfg)
    state = load_checkpoint(layout.checkpoint)
    state["config"] = json.loads(json.dumps(state["config"]))
    tr.load_state_dict(state)
    tr.iteration = cfg.iterations // 2  # mid-run: densification on, the medium on (when the mode has one)
    for _ in range(3):  # warm-up (kernels loaded, allocator settled)
        tr.step()
    with collecting() as sec:
        t0 = time.perf_counter()
        for _ in range(steps):
            with _section("step"):
                tr.step()
        wall = time.perf_counter() - t0
    # SSIM and the medium nets alone, forward + backward, on this size's tensors (their backward is inside
    # autograd's and not separable there)
    out = tr.render(0, 0, "RGB+ED")
    J = out.image.detach().requires_grad_(True)

    def timed(fn, n: int = 10) -> float:
        fn()
        t = time.perf_counter()
        for _ in range(n):
            fn()
        return (time.perf_counter() - t) / n * 1000

    ssim_ms = timed(lambda: (1 - ssim(J, targets[0])).backward())
    medium_ms = None
    if tr.medium is not None:
        alpha, depth = out.alpha.detach(), out.depth.detach()

        def medium_fb():
            loss = sum(tr.medium.losses(0, J, alpha, depth, targets[0]).values())
            loss.backward()

        medium_ms = timed(medium_fb)
    ms = {k: v / steps * 1000 for k, v in sec.items() if not k.endswith("#")}
    return {"size": size, "steps": steps, "n_gaussians": int(tr.gaussians["means"].shape[0]), "mode": cfg.mode,
            "step_ms": wall / steps * 1000, "sections_ms": ms, "ssim_fwd_bwd_ms": ssim_ms,
            "medium_losses_fwd_bwd_ms": medium_ms, "upscale_of_job": factor,
            "threads": torch.get_num_threads()}


def _section(name: str):
    from pipeline.profiling import section

    return section(name)


# -- printing ----------------------------------------------------------------------------------------------------

STAGE_ORDER = ("ingest", "sfm", "classify", "train", "evaluate", "restore", "export")


def _stage_table(runs: dict[str, list[dict]]) -> list[str]:
    names = list(runs)
    lines = ["| stage | " + " | ".join(f"{n} (s)" for n in names) + (" | ratio |" if len(names) == 2 else " |"),
             "|---" * (len(names) + 1 + (len(names) == 2)) + "|"]

    def med(n: str, get) -> float:
        vals = [get(r) for r in runs[n]]
        vals = [v for v in vals if v is not None]
        return statistics.median(vals) if vals else float("nan")

    rows = [(s, lambda r, s=s: r["stages_s"].get(s)) for s in STAGE_ORDER]
    rows += [("  of train: probe", lambda r: r["probe_s"]), ("  of train: steps", lambda r: r["train_steps_s"]),
             ("job (run_job)", lambda r: r["wall_s"]), ("process (with imports)", lambda r: r["process_s"])]
    for label, get in rows:
        vals = [med(n, get) for n in names]
        ratio = f" | {vals[0] / vals[1]:.2f} |" if len(names) == 2 and vals[1] else " |"
        lines.append(f"| {label} | " + " | ".join(f"{v:.1f}" for v in vals) + ratio)
    for key in ("test_psnr", "mode", "iterations", "n_gaussians", "peak_rss_mb"):
        lines.append(f"| {key} | " + " | ".join(", ".join(str(round(r[key], 2)) if isinstance(r[key], float)
                                                            else str(r[key]) for r in runs[n]) for n in names)
                     + (" | |" if len(names) == 2 else " |"))
    return lines


def _round_table(runs: dict[str, list[dict]], first_warm: int = 1) -> list[str]:
    """Each round's job times and their ratio, then each checkout's spread over the warm rounds (``first_warm``
    on: 1 when round 0 compiled the loss graphs).

    The machine's speed drifts (±30 % within an hour here); a ratio is only as good as the spread beside it.
    """
    a, b = list(runs)
    lines = [f"| round | {a} (s) | {b} (s) | ratio |", "|---|---|---|---|"]
    for r, (x, y) in enumerate(zip(runs[a], runs[b])):
        lines.append(f"| {r} | {x['wall_s']:.1f} | {y['wall_s']:.1f} | {x['wall_s'] / y['wall_s']:.3f} |")
    warm = {n: [r["wall_s"] for r in runs[n][first_warm:]] for n in (a, b)}
    if warm[a] and warm[b]:
        ma, mb = statistics.fmean(warm[a]), statistics.fmean(warm[b])
        lines.append(f"| warm mean | {ma:.1f} | {mb:.1f} | {ma / mb:.3f} |")
    spreads = [f"{n} {100 * (max(w) / min(w) - 1):.1f} %" for n, w in warm.items() if len(w) >= 2]
    if spreads:
        lines.append(f"\nspread of the warm rounds (max/min − 1): {', '.join(spreads)}; above ~3 % the machine "
                     "drifted during the run, and the ratio carries that drift")
    return lines


def _profile_table(p: dict) -> list[str]:
    s = p["sections_ms"]
    step = s.get("step", p["step_ms"])
    inner = ["render", "losses", "backward", "optimizer", "densify"]
    rows = [("render (forward)", s.get("render", 0)),
            ("  projection fwd (numba)", s.get("raster: project fwd", 0)),
            ("  compositing fwd (numba, with binning)", s.get("raster: composite fwd", 0)),
            ("    of it: binning", s.get("raster: bin (in composite fwd)", 0)),
            ("losses (forward)", s.get("losses", 0)),
            ("  L1 + SSIM fwd (before the medium)", s.get("losses: photometric fwd", 0)),
            ("  medium nets + terms fwd (with it)", s.get("losses: medium nets + terms fwd", 0)),
            ("backward", s.get("backward", 0)),
            ("  compositing bwd (numba)", s.get("raster: composite bwd", 0)),
            ("  projection bwd (numba)", s.get("raster: project bwd", 0)),
            ("  rest of backward (SSIM, medium, activations)", s.get("backward", 0) - s.get("raster: composite bwd", 0)
             - s.get("raster: project bwd", 0)),
            ("optimizer (Adam + medium step)", s.get("optimizer", 0)),
            ("densification", s.get("densify", 0)),
            ("Python overhead (step − sections)", step - sum(s.get(k, 0) for k in inner)),
            ("**step**", step)]
    lines = [f"{p['size']}, {p['n_gaussians']} Gaussians, mode {p['mode']}, {p['steps']} steps, "
             f"torch threads {p['threads']}", "| part | ms/step | share |", "|---|---|---|"]
    lines += [f"| {k} | {v:.1f} | {100 * v / step:.0f} % |" for k, v in rows]
    lines.append(f"| SSIM alone, fwd+bwd | {p['ssim_fwd_bwd_ms']:.1f} | |")
    if p["medium_losses_fwd_bwd_ms"] is not None:
        lines.append(f"| medium nets + losses alone, fwd+bwd | {p['medium_losses_fwd_bwd_ms']:.1f} | |")
    return lines


# -- main ----------------------------------------------------------------------------------------------------------

def main() -> None:
    from pipeline.job.options import JOB_MODES  # every checkout since the re-layout (#12) has it

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="320x240", help="the generated scene's size (the job's training size)")
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--out", type=Path, default=Path("/tmp/dualphys-job"))
    ap.add_argument("--compare", type=Path, default=None, help="another checkout to run the same job with")
    ap.add_argument("--rounds", type=int, default=1, help="jobs per checkout (alternating order)")
    ap.add_argument("--profile-sizes", nargs="*", default=["320x240", "640x480"])
    ap.add_argument("--profile-steps", type=int, default=60)
    ap.add_argument("--no-numba", action="store_true", help="skip the fresh-cache compile measurement")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--keep-graphs", action="store_true",
                    help="keep the compiled loss graphs an earlier run left under --out: every round is warm")
    ap.add_argument("--mode", default="auto", choices=list(JOB_MODES),
                    help="the jobs' --mode: a fixed mode compares checkouts like for like (no probe, same model)")
    ap.add_argument("--child-job", nargs=2, metavar=("JOB", "IMAGES"), help=argparse.SUPPRESS)
    ap.add_argument("--child-numba", metavar="SIZE", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child_job:
        return _child_job(Path(args.child_job[0]), Path(args.child_job[1]), args.mode)
    if args.child_numba:
        return _child_numba(args.child_numba)

    from pipeline.config import SynthConfig
    from pipeline.synth.procedural import generate_scene
    from pipeline.synth.water import TRUE_WATER_FILE

    w, h = (int(x) for x in args.size.split("x"))
    scene = args.out / f"scene_{args.views}_{args.size}"
    if not (scene / TRUE_WATER_FILE).exists():
        generate_scene(SynthConfig(views=args.views, width=w, height=h, preset="medium", seed=0), scene)
    # inductor's cache for the compiled loss graphs (pipeline.ops.jit), emptied now: round 0 of a checkout that
    # compiles pays the compile (a fresh install's first job at this image size), later rounds load it
    graphs = args.out / "inductor-cache"
    if not args.keep_graphs:
        subprocess.run(["rm", "-rf", str(graphs)], check=True)
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(graphs)
    checkouts = {"this": OURS} | ({"compare": args.compare.resolve()} if args.compare else {})
    for name, path in checkouts.items():  # fill each checkout's kernel cache first: the jobs time a warm install
        warm = _run_child(path, ["--child-numba", args.size])
        print(f"{name}: kernel cache {'was empty, compiled' if warm['first_s'] > 20 else 'warm'} "
              f"(first fwd+bwd {warm['first_s']:.1f} s)", flush=True)
    runs: dict[str, list[dict]] = {n: [] for n in checkouts}
    for r in range(args.rounds):
        order = list(checkouts) if r % 2 == 0 else list(checkouts)[::-1]
        for name in order:
            job = args.out / f"job_{name}_{r}"
            subprocess.run(["rm", "-rf", str(job)], check=True)
            res = _run_child(checkouts[name], ["--child-job", str(job), str(scene / "images"), "--mode", args.mode])
            runs[name].append(res)
            print(f"{name} round {r}: {json.dumps({k: v for k, v in res.items() if k != 'sections'})}", flush=True)
    print(f"\n## The job: {args.views} generated views at {args.size}, --preset fast, mode {args.mode}\n")
    print("\n".join(_stage_table(runs)))
    if len(runs) == 2:
        print("\n" + "\n".join(_round_table(runs, 0 if args.keep_graphs else 1)))
    sec = runs["this"][-1]["sections"]
    n = max(1.0, sec.get("step#", 0.0))
    print(f"\nthis checkout, the job's own steps ({int(n)} incl. the probe's): "
          + ", ".join(f"{k} {v / n * 1000:.1f} ms" for k, v in sorted(sec.items(), key=lambda kv: -kv[1])
                      if not k.endswith("#")))
    profiles = []
    for size in args.profile_sizes:
        p = step_profile(args.out / "job_this_0", size, args.profile_steps)
        profiles.append(p)
        print(f"\n## Training step at {size}\n")
        print("\n".join(_profile_table(p)))
    numba = None
    if not args.no_numba:
        with tempfile.TemporaryDirectory() as cache:
            env = {"NUMBA_CACHE_DIR": cache}
            cold = _run_child(OURS, ["--child-numba", args.size], env)
            warm = _run_child(OURS, ["--child-numba", args.size], env)
        numba = {"fresh_first_s": cold["first_s"], "fresh_second_s": cold["second_s"],
                 "cached_first_s": warm["first_s"], "fresh_process_s": cold["process_s"],
                 "cached_process_s": warm["process_s"]}
        print(f"\n## numba: first fwd+bwd on an empty cache {cold['first_s']:.1f} s (then {cold['second_s']:.2f} s); "
              f"a new process with the cache filled {warm['first_s']:.2f} s; whole process {cold['process_s']:.1f} s "
              f"vs {warm['process_s']:.1f} s")
    if args.json:
        print(json.dumps({"runs": runs, "profiles": profiles, "numba": numba}))


if __name__ == "__main__":
    main()
