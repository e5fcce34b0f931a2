"""The pipeline's ``dualphys`` sub-commands (synth, sfm, demo, run, render, ablate, train-classifier, warmup): each
takes the parsed flags (cli/main.py builds the parser), calls one pipeline function and prints what it did, the
last line JSON. This module imports torch (through the pipeline), so cli/main.py imports it only when one of
these runs, after the thread settings are in place; the client install never loads it.

Exit codes: 0 success, 1 a pipeline error the user can act on (message on stderr), 2 flags that contradict.
"""


from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from collections.abc import Callable
from importlib import resources
from pathlib import Path

from cli.job_flags import job_options
from pipeline.config import SynthConfig
from pipeline.evaluate.ablate import AblationConfig, format_table, run_ablation, select_rows
from pipeline.export.rerender import RenderError, render_job
from pipeline.job.layout import JobLayout
from pipeline.job.options import JobOptions, StageContext
from pipeline.job.progress import StageProgress
from pipeline.job.runner import run_job
from pipeline.job.table import STAGES
from pipeline.ops.metrics import per_metre
from pipeline.ops.ssim_cpu import compile_ssim_kernels
from pipeline.restore.warmup import compile_restore_kernels
from pipeline.scene.align import align_to_reference
from pipeline.scene.loader import SceneLayoutError, load_scene
from pipeline.sfm.config import SfmConfig
from pipeline.sfm.recipe import SfmError, run_sfm
from pipeline.splat.warmup import compile_kernels
from pipeline.synth.defocus import defocus_scene
from pipeline.synth.exposure import expose_scene, fall_off_scene
from pipeline.synth.photo import PhotoSynthConfig, generate_photo_scene
from pipeline.synth.photo_texture import TextureFolderError
from pipeline.synth.procedural import generate_scene
from pipeline.synth.survey_records import stamp_scene
from pipeline.synth.water import WATER_PRESETS
from pipeline.water import train_classifier
from pipeline.water.classifier import SHIPPED_WEIGHTS

log = logging.getLogger("dualphys")


def _fail(command: str, message: str) -> int:
    """``dualphys <command>: <message>`` on stderr; exit code 1."""
    print(f"dualphys {command}: {message}", file=sys.stderr)
    return 1


def cmd_synth(args: argparse.Namespace) -> int:
    """A generated scene with its truth: the procedural family or the photo family, then the camera effects."""
    w, h = args.size
    t0 = time.perf_counter()
    if args.family == "photo":
        if args.path != "survey":
            print("dualphys synth: --path applies to the procedural family only (the photo family flies its "
                  "own lawnmower + oblique survey)", file=sys.stderr)
            return 2
        chosen = {k: v for k, v in (("altitude_range", args.altitude), ("oblique_fraction", args.oblique),
                                  ("gps_origin", args.gps), ("altimeter_noise", args.altimeter_noise))
                if v is not None}
        photo = PhotoSynthConfig(views=args.views, width=w, height=h, preset=args.preset, seed=args.seed,
                                 distortion=args.distortion, water_space=args.water_space, **chosen)
        try:
            out = generate_photo_scene(photo, args.out)
        except (TextureFolderError, ValueError) as e:
            print(f"dualphys synth: {e}", file=sys.stderr)
            return 1
        views, preset = photo.views, photo.preset
    else:
        if any(v is not None for v in (args.altitude, args.oblique, args.gps, args.altimeter_noise)):
            print("dualphys synth: --altitude, --oblique, --gps and --altimeter-noise apply to the photo family "
                  "only", file=sys.stderr)
            return 2
        cfg = SynthConfig(views=args.views, width=w, height=h, preset=args.preset, seed=args.seed, path=args.path,
                          distortion=args.distortion, water_space=args.water_space)
        try:
            out = generate_scene(cfg, args.out)
        except ValueError as e:
            print(f"dualphys synth: {e}", file=sys.stderr)
            return 1
        views, preset = cfg.views, cfg.preset
    extra = {}
    if args.defocus > 0:
        extra = {"defocus_px": args.defocus, "focus_m": round(defocus_scene(out, args.defocus), 3)}
    if args.exposure > 0 or args.white_balance > 0:
        expose_scene(out, args.exposure, args.white_balance, args.seed)
        extra.update(exposure=args.exposure, white_balance=args.white_balance)
    if args.fall_off > 0:
        fall_off_scene(out, args.fall_off)
        extra.update(fall_off=args.fall_off)
    if extra and args.family == "photo":
        stamp_scene(out)  # the camera effects rewrote images/ without the survey records' EXIF
    print(json.dumps({"out": str(out), "family": args.family, "views": views, "preset": preset, **extra,
                      "seconds": round(time.perf_counter() - t0, 2)}))
    return 0


def cmd_sfm(args: argparse.Namespace) -> int:
    """Posed cameras and sparse points of a folder of images."""
    cfg = SfmConfig(matcher=args.matcher)
    try:
        summary = run_sfm(args.images, args.out, cfg)
    except SfmError as e:
        print(f"dualphys sfm: {e}", file=sys.stderr)
        return 1
    print(json.dumps(dataclasses.asdict(summary), default=str))
    return 0


def _db(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f} dB"


def cmd_demo(args: argparse.Namespace) -> int:
    """Generate a scene with known water and run the job on it end to end."""
    out = Path(args.out)
    t0 = time.perf_counter()
    synth = SynthConfig(views=24, width=240, height=180, preset="medium", seed=0)
    scene_dir = generate_scene(synth, out / "scene")
    print(f"[1/3] synthetic '{synth.preset}' underwater scene: {synth.views} views {synth.width}x{synth.height} "
          f"-> {scene_dir} ({time.perf_counter() - t0:.0f} s)")
    last = {"stage": ""}

    def progress(stage: str, fraction: float, message: str) -> None:
        if stage != last["stage"] or fraction >= 1.0:
            print(f"      {stage}: {message}", flush=True)
            last["stage"] = stage

    # the physics in the space the generated water was applied in (the generator's default: sRGB values)
    opts = JobOptions(source=str(scene_dir / "images"), mode="dualphys", iterations=args.iterations,
                      colour_space=synth.water_space)
    job = JobLayout(out / "job")
    res = run_job(job.root, opts, StageContext(on_progress=progress))
    print(f"[2/3] job done in {time.perf_counter() - t0:.0f} s -> {job.root}")
    sfm, water, train = res["sfm"], res["classify"], res["train"]
    errs = align_to_reference(load_scene(job.scene), load_scene(scene_dir))
    coef = train.get("medium", {})
    truth = WATER_PRESETS[synth.preset]
    print(f"[3/3] SfM {sfm['registered']}/{sfm['total']} registered ({sfm['mean_reproj_error_px']:.2f} px; "
          f"cameras within {errs['rot_err_deg_mean']:.2f} deg / {100 * errs['center_err_rel_mean']:.2f} % of "
          f"the path of the truth); water classified '{water['water_type']}' "
          f"(closest {water.get('closest', water['water_type'])}, "
          f"p={max(water['probabilities'].values()):.2f}); held-out PSNR with water "
          f"{_db(res['evaluate']['metrics']['test']['psnr'])}; {train['n_gaussians']} Gaussians")
    rest = res["evaluate"].get("restoration")
    if rest:
        print(f"      restored J against the true clean images (held-out views): PSNR {_db(rest['restored']['psnr'])}, "
              f"SSIM {rest['restored']['ssim']:.3f} (the photos themselves: {_db(rest['input']['psnr'])})")
        if rest.get("seen"):
            seen = rest["seen"]
            print(f"      over the {100 * seen['fraction']:.0f} % of pixels a training view saw: restored J "
                  f"{_db(seen['restored_psnr'])} (the photos: {_db(seen['input_psnr'])})")
    photos = ((res.get("restore") or {}).get("truth") or {}).get("test")
    if photos:
        print(f"      your photos de-watered ({job.restored.name}/, full resolution) against the truth (held-out): "
              f"{_db(photos['restored_psnr'])} (the model's J render carried into the photos: "
              f"{_db(photos['render_psnr'])}; the photos themselves: {_db(photos['photo_psnr'])})")
    if coef:
        # SfM scenes have no metric scale: one scene unit is errs['scale'] metres (similarity to the truth).
        metric = per_metre(coef["beta_D"], errs["scale"])
        print("      recovered beta_D (1/m, via the alignment's scale): "
              + ", ".join(f"{c} {m:.3f} (true {t:.3f})" for c, m, t in zip("RGB", metric, truth.beta_D)))
    print(f"      outputs: {job.output} ({job.ply.name}; {job.restored.name} and {job.confidence.name}: your photos "
          f"de-watered at full resolution; {job.renders.name}: the model's views)")
    print(f"      report: {job.report_html.resolve()}")
    summary = {"scene": str(scene_dir), "job": str(job.root), "alignment": errs, "results": res,
               "seconds": round(time.perf_counter() - t0, 1)}
    (out / "demo.json").write_text(json.dumps(summary, indent=2, default=str))
    print(json.dumps({"demo": str(out / "demo.json"), "ply": str(job.ply), "report": str(job.report_html)}))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    """The whole job in this process, with progress bars; finished stages (matching markers) are skipped."""
    src = Path(args.input)
    if not src.exists():
        return _fail("run", f"{src} does not exist: give a folder of images, a zip/tar archive of them or a video")
    opts = job_options(args, src.resolve())
    out = Path(args.out)
    if not args.verbose:  # the bars say where the job is; the stages' log lines would tear them apart
        logging.getLogger().setLevel(logging.WARNING)
    bar = StageProgress(STAGES)
    t0 = time.perf_counter()
    try:
        res = run_job(out, opts, StageContext(on_progress=bar))
    except KeyboardInterrupt:
        bar.close()
        return _fail("run", "interrupted; run the same command again to resume from the unfinished stage")
    except Exception as e:  # every pipeline failure: a message, not a traceback (-v logs it)
        bar.close()
        log.debug("job failed", exc_info=True)
        stage = bar.stage or "job"
        return _fail("run", f"{stage} failed: {e} (finished stages are kept; -v shows the traceback)")
    bar.close()
    train = res.get("train", {})
    test = res.get("evaluate", {}).get("metrics", {}).get("test", {})
    selection = JobLayout(out).selection
    print(f"done in {time.perf_counter() - t0:.0f} s; skipped (already done): {', '.join(bar.skipped) or 'none'}")
    if selection.exists():
        sel = json.loads(selection.read_text())
        print(f"mode auto chose {sel['chosen']}: {sel['reason']}")
    psnr = "n/a" if test.get("psnr") is None else f"{test['psnr']:.2f} dB"
    print(f"mode {train.get('mode', opts.mode)}, {train.get('n_gaussians', '?')} Gaussians; held-out PSNR with "
          f"water {psnr}; outputs in {JobLayout(out).output}")
    quality = train.get("quality") or {}
    if quality:
        pc = quality.get("point_coverage_min")
        print(f"model quality: training views covered at least {100 * quality['coverage_min']:.1f} % of pixels"
              + (f", {100 * pc:.1f} % of their sparse points" if pc is not None else "")
              + f"; {quality['n_gaussians']} Gaussians of a budget of {quality['budget']}")
        for w in quality.get("warnings", []):
            print(f"warning: {w}", file=sys.stderr)
    print(json.dumps({"job": str(out), "skipped": bar.skipped, "mode": train.get("mode"),
                      "test_psnr": test.get("psnr"), "report": str(JobLayout(out).report_html),
                      "seconds": round(time.perf_counter() - t0, 1)}))
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    """Restored / with-water (or any exported) images of a trained job, for its views and novel ones."""
    views: str | list[str] = args.views
    if args.views not in ("all", "none"):
        views = [n.strip() for n in args.views.split(",") if n.strip()]
    elif args.views == "none":
        views = []
    what = [w.strip() for w in args.what.split(",") if w.strip()]
    try:
        counts = render_job(args.job, args.out, views, what, novel=args.orbit, max_gain=args.max_gain,
                            fmt=args.format)
    except (RenderError, SceneLayoutError, ValueError) as e:
        return _fail("render", str(e))
    print(json.dumps({"out": str(args.out), **counts}, default=str))
    return 0


def cmd_ablate(args: argparse.Namespace) -> int:
    """The paper's Table 2 on a generated scene with ground truth."""
    w, h = args.size
    only = tuple(n.strip() for n in args.only.split(",") if n.strip()) if args.only else ()
    cfg = AblationConfig(views=args.views, width=w, height=h, water=args.water, iterations=args.iterations,
                         seed=args.seed, rows=args.rows, only=only)
    try:
        n = len(select_rows(cfg))
    except ValueError as e:
        return _fail("ablate", str(e))
    print(f"ablation: {n} rows x {cfg.iterations} iterations on a generated '{cfg.water}' scene, {cfg.views} views "
          f"{w}x{h}", file=sys.stderr)
    done = [0]

    def row_done(r) -> None:
        done[0] += 1
        print(f"  [{done[0]}/{n}] {r.name}: PSNR {r.psnr:.2f} dB, restored J {r.restored_psnr:.2f} dB "
              f"({r.seconds:.0f} s)", file=sys.stderr, flush=True)

    report = run_ablation(args.out, cfg, on_row=row_done)
    print(format_table(report["rows"]))
    print(json.dumps({"ablation": str(Path(args.out) / "ablation.json")}))
    return 0


def cmd_train_classifier(args: argparse.Namespace) -> int:
    """Retrain the water-type classifier; without --out, over the shipped weights (pipeline/data)."""
    out = args.out or Path(str(resources.files("pipeline").joinpath("data", SHIPPED_WEIGHTS)))
    metrics = train_classifier(out, seed=args.seed)
    print(json.dumps(metrics, default=str))
    return 0


def cmd_warmup(args: argparse.Namespace) -> int:
    """Compile the numba kernels into their cache."""
    print(json.dumps({"rasterizer": compile_kernels(), "ssim": compile_ssim_kernels(),
                      "restore": compile_restore_kernels()}))
    return 0



# the sub-command name (as cli/main.py's parser spells it) -> its function
COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "synth": cmd_synth, "sfm": cmd_sfm, "demo": cmd_demo, "run": cmd_run, "render": cmd_render,
    "ablate": cmd_ablate, "train-classifier": cmd_train_classifier, "warmup": cmd_warmup,
}
