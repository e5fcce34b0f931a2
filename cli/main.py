"""The ``dualphys`` command. Each sub-command maps its flags onto a typed config and calls one pipeline
function; heavy modules (torch, pycolmap, OpenImageIO) are imported inside the commands, after the thread
settings below are in place.

Exit codes: 0 success, 1 a pipeline error the user can act on (message on stderr), 2 bad command line. The
client commands (submit, status, jobs, download, cancel: a remote service) use 1 for a refused key, a missing
job, an unreachable server or any other refused request, and with ``--wait`` 3 when the job failed and 4 when it
was cancelled.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import time
from pathlib import Path

from pipeline.cli_args import positive as _positive

log = logging.getLogger("dualphys")


def _fail(command: str, message: str) -> int:
    """``dualphys <command>: <message>`` on stderr; exit code 1."""
    print(f"dualphys {command}: {message}", file=sys.stderr)
    return 1


def _prepare_runtime() -> None:
    # Torch's and numba's OpenMP pools fight unless idle threads sleep; must be set before torch loads.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 320x240, got {text!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"size must be at least 8x8, got {text!r}")
    return w, h


def _pair(text: str, what: str, example: str) -> tuple[float, float]:
    """Two numbers written ``a,b``; an argparse error naming ``what`` and an ``example`` otherwise."""
    try:
        a, b = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} must look like {example}, got {text!r}") from None
    return a, b


def _distortion(text: str) -> tuple[float, float]:
    return _pair(text, "distortion", "-0.15,0.02 (k1,k2)")


def _altitude(text: str) -> tuple[float, float]:
    lo, hi = _pair(text, "altitude", "2.4,2.6 (min,max metres)")
    if not 0 < lo <= hi:
        raise argparse.ArgumentTypeError(f"altitude must be 0 < min <= max, got {text!r}")
    return lo, hi


def _fraction(text: str) -> float:
    try:
        f = float(text)
    except ValueError:
        f = -1.0
    if not 0 <= f < 1:
        raise argparse.ArgumentTypeError(f"a fraction in [0, 1) is needed, got {text!r}")
    return f


def cmd_synth(args: argparse.Namespace) -> int:
    w, h = args.size
    t0 = time.perf_counter()
    if args.family == "photo":
        from pipeline.synth.photo import PhotoSynthConfig, generate_photo_scene
        from pipeline.synth.photo_texture import TextureFolderError

        if args.path != "survey":
            print("dualphys synth: --path applies to the procedural family only (the photo family flies its "
                  "own lawnmower + oblique survey)", file=sys.stderr)
            return 2
        path = {k: v for k, v in (("altitude_range", args.altitude), ("oblique_fraction", args.oblique))
                if v is not None}
        photo = PhotoSynthConfig(views=args.views, width=w, height=h, preset=args.preset, seed=args.seed,
                                 distortion=args.distortion, water_space=args.water_space, **path)
        try:
            out = generate_photo_scene(photo, args.out)
        except (TextureFolderError, ValueError) as e:
            print(f"dualphys synth: {e}", file=sys.stderr)
            return 1
        views, preset = photo.views, photo.preset
    else:
        from pipeline.config import SynthConfig
        from pipeline.synth.procedural import generate_scene

        if args.altitude is not None or args.oblique is not None:
            print("dualphys synth: --altitude and --oblique apply to the photo family only", file=sys.stderr)
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
        from pipeline.synth.defocus import defocus_scene

        extra = {"defocus_px": args.defocus, "focus_m": round(defocus_scene(out, args.defocus), 3)}
    if args.exposure > 0 or args.white_balance > 0:
        from pipeline.synth.exposure import expose_scene

        expose_scene(out, args.exposure, args.white_balance, args.seed)
        extra.update(exposure=args.exposure, white_balance=args.white_balance)
    if args.fall_off > 0:
        from pipeline.synth.exposure import fall_off_scene

        fall_off_scene(out, args.fall_off)
        extra.update(fall_off=args.fall_off)
    print(json.dumps({"out": str(out), "family": args.family, "views": views, "preset": preset, **extra,
                      "seconds": round(time.perf_counter() - t0, 2)}))
    return 0


def cmd_sfm(args: argparse.Namespace) -> int:
    from pipeline.config import SfmConfig
    from pipeline.sfm.recipe import SfmError, run_sfm

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
    from pipeline.config import SynthConfig
    from pipeline.job.layout import JobLayout
    from pipeline.job.options import JobOptions, StageContext
    from pipeline.job.runner import run_job
    from pipeline.ops.metrics import per_metre
    from pipeline.scene.align import align_to_reference
    from pipeline.scene.loader import load_scene
    from pipeline.synth.procedural import generate_scene
    from pipeline.synth.water import WATER_PRESETS

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
    from pipeline.job.layout import JobLayout
    from pipeline.job.options import JobOptions, StageContext
    from pipeline.job.progress import StageProgress
    from pipeline.job.runner import run_job
    from pipeline.job.table import STAGES

    src = Path(args.input)
    if not src.exists():
        return _fail("run", f"{src} does not exist: give a folder of images, a zip/tar archive of them or a video")
    opts = JobOptions(source=str(src.resolve()), preset=args.preset, mode=args.mode, max_width=args.max_width,
                      iterations=args.iterations, seed=args.seed, colour_space=args.colour_space,
                      restore_format=args.format, max_gain=args.max_gain)
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
    from pipeline.export.rerender import RenderError, render_job
    from pipeline.scene.loader import SceneLayoutError

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
    from pipeline.evaluate.ablate import AblationConfig, format_table, run_ablation

    w, h = args.size
    only = tuple(n.strip() for n in args.only.split(",") if n.strip()) if args.only else ()
    cfg = AblationConfig(views=args.views, width=w, height=h, water=args.water, iterations=args.iterations,
                         seed=args.seed, rows=args.rows, only=only)
    try:
        from pipeline.evaluate.ablate import select_rows

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
    from pipeline.water import train_classifier

    out = args.out or Path(__file__).resolve().parent / "data" / "water_classifier.json"  # the shipped weights
    metrics = train_classifier(out, seed=args.seed)
    print(json.dumps(metrics, default=str))
    return 0


def cmd_warmup(args: argparse.Namespace) -> int:
    from pipeline.ops.ssim_cpu import compile_ssim_kernels
    from pipeline.restore.warmup import compile_restore_kernels
    from pipeline.splat.warmup import compile_kernels

    print(json.dumps({"rasterizer": compile_kernels(), "ssim": compile_ssim_kernels(),
                      "restore": compile_restore_kernels()}))
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    from service.embedded import serve

    try:
        serve(args.host, args.port, args.data_dir, redis_url=args.redis_url, api_keys_file=args.api_keys_file,
              worker_concurrency=args.workers, beat=not args.no_beat, log_level=args.log_level)
    except (RuntimeError, ValueError, OSError) as e:  # no Redis, unreadable keys: a message, not a traceback
        print(f"dualphys serve: {e}", file=sys.stderr)
        return 1
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dualphys",
                                description="Underwater Gaussian splatting with the water modelled out.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("synth", help="generate a synthetic underwater scene with ground truth")
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--views", type=int, default=24)
    s.add_argument("--size", type=_size, default=(320, 240), help="WxH, e.g. 320x240")
    s.add_argument("--preset", default="medium", choices=["none", "clear", "medium", "turbid"])
    s.add_argument("--path", default="survey", choices=["survey", "lawnmower", "forward"],
                   help="camera path of the procedural family")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--family", default="procedural", choices=["procedural", "photo"],
                   help="procedural: bright procedural seabed, water per pixel (pipeline.synth.procedural); photo: "
                        "seabed from real photographs, water per supersample (pipeline.synth.photo)")
    s.add_argument("--distortion", type=_distortion, default=(0.0, 0.0), metavar="K1,K2",
                   help="radial lens distortion (COLMAP RADIAL k1,k2), e.g. --distortion=-0.15,0 (with =: a "
                        "leading minus reads as an option otherwise); pinhole companions go to pinhole/ "
                        "(pipeline.synth.lens)")
    s.add_argument("--altitude", type=_altitude, default=None, metavar="MIN,MAX",
                   help="photo family: the lawnmower lines' altitude range in metres (default 1.9,3.2); e.g. "
                        "2.4,2.6 with --oblique 0 is a survey at nearly constant range")
    s.add_argument("--oblique", type=_fraction, default=None, metavar="FRACTION",
                   help="photo family: share of the views in the oblique pass (default 0.25; 0 = none)")
    s.add_argument("--water-space", default="srgb", choices=["srgb", "linear"],
                   help="srgb: water applied to J as written; linear: to sRGB-decoded J, re-encoded after")
    s.add_argument("--defocus", type=float, default=0.0, metavar="PX",
                   help="blur the photos as a lens focused at the median depth does: blur circle PX pixels at "
                        "infinity, sharp at the focus (pipeline.synth.defocus); 0 = sharp")
    s.add_argument("--exposure", type=float, default=0.0, metavar="SPREAD",
                   help="give each photo its own exposure, a gain on linear light within ±SPREAD (e.g. 0.3), "
                        "truth in exposure.json (pipeline.synth.exposure); 0 = fixed")
    s.add_argument("--white-balance", type=float, default=0.0, metavar="SPREAD",
                   help="and its own white balance: a gain per channel within ±SPREAD")
    s.add_argument("--fall-off", type=float, default=0.0, metavar="STRENGTH",
                   help="darken the photos towards one side and the corners as a real camera's vignetting and "
                        "light do (pipeline.synth.exposure.fall_off_field; 0.3: 1.7x over the frame, as AIMS Erub); "
                        "0 = none")
    s.set_defaults(func=cmd_synth)

    s = sub.add_parser("sfm", help="structure from motion: images -> posed PINHOLE cameras + sparse points")
    s.add_argument("images", type=Path)
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--matcher", default="auto", choices=["auto", "exhaustive", "sequential"])
    s.set_defaults(func=cmd_sfm)

    s = sub.add_parser("train-classifier", help="retrain the water-type classifier on generated scenes")
    s.add_argument("--out", type=Path, default=None, help="weights file (default: the shipped one)")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=cmd_train_classifier)

    s = sub.add_parser("serve", help="run the API, a worker and beat locally against a Redis on localhost",
                       description="Run the API, a Celery worker and beat on this machine. Every DUALPHYS_* "
                                   "setting of docs/SERVICE.md applies; a flag given here wins over its variable. "
                                   "Ctrl-C or SIGTERM stops all three.")
    s.add_argument("--host", default="127.0.0.1", help="address the API listens on (default: 127.0.0.1)")
    s.add_argument("--port", type=int, default=8000, help="port the API listens on (default: 8000)")
    s.add_argument("--data-dir", type=Path, default=None,
                   help="job folders, survey state, beat schedule (default: $DUALPHYS_DATA_DIR, else ./dualphys-data)")
    s.add_argument("--redis-url", default=None,
                   help="broker, locks and cache (default: $DUALPHYS_REDIS_URL, else redis://127.0.0.1:6379/0)")
    s.add_argument("--api-keys-file", type=Path, default=None,
                   help='JSON file {"<key>": "<owner>", ...} (default: $DUALPHYS_API_KEYS, else one key for owner '
                        "'local', written to <data-dir>/api-key)")
    s.add_argument("--workers", type=_positive, default=1, help="worker processes running stages (default: 1)")
    s.add_argument("--no-beat", action="store_true", help="run no celery beat: survey folders are not scanned")
    s.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"],
                   help="log level of the API, the worker and beat (default: info)")
    s.set_defaults(func=cmd_serve)

    s = sub.add_parser("demo", help="generate a scene and run the pipeline on it end to end")
    s.add_argument("--out", type=Path, default=Path("demo-out"))
    s.add_argument("--iterations", type=int, default=1500, help="training iterations (CPU budget)")
    s.set_defaults(func=cmd_demo)

    from pipeline.job.options import COLOUR_SPACES, JOB_MODES, RESTORE_FORMATS, JobOptions

    defaults = JobOptions()
    s = sub.add_parser("run", help="run a whole job (ingest, sfm, classify, train, evaluate, restore, export) in "
                                   "this process; re-running resumes")
    s.add_argument("input", type=Path,
                   help="a folder of images (and videos), a zip/tar archive of them, or one video (MP4/MOV)")
    s.add_argument("--out", required=True, type=Path, help="the job folder (created; reused to resume)")
    s.add_argument("--preset", default="fast", choices=["fast", "balanced", "paper"])
    s.add_argument("--mode", default="auto", choices=list(JOB_MODES),
                   help="auto (default): a short probe picks the simplest mode the scene needs")
    s.add_argument("--iterations", type=_positive, default=None, help="override the preset's iteration count")
    s.add_argument("--max-width", type=_positive, default=400, help="train wider images at an integer downscale")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--colour-space", default=defaults.colour_space, choices=list(COLOUR_SPACES),
                   help="where the water physics runs: on the photos' sRGB values or on linear light")
    s.add_argument("--format", default=defaults.restore_format, choices=list(RESTORE_FORMATS),
                   help="the restored photos: auto (each as its input: 8-bit JPEG or PNG) | tiff16")
    s.add_argument("--max-gain", type=float, default=defaults.max_gain,
                   help="cap on the restoration's per-channel gain 1/A")
    s.set_defaults(func=cmd_run)

    s = sub.add_parser("render", help="render a trained job's views (restored, with water, maps) and novel views")
    s.add_argument("job", type=Path, help="a job folder that `dualphys run` trained")
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--views", default="all", help="all | none | comma-separated view names (with or without "
                                                  "extension)")
    s.add_argument("--what", default="restored,with_water",
                   help="comma-separated: photos (the job's input photos de-watered at full resolution, with "
                        "their confidence maps), restored, with_water, depth, attenuation, backscatter (the "
                        "model's renders at the training resolution)")
    s.add_argument("--max-gain", type=float, default=defaults.max_gain,
                   help="photos: cap on the per-channel gain 1/A")
    s.add_argument("--format", default=defaults.restore_format, choices=list(RESTORE_FORMATS),
                   help="photos: auto (as each input: 8-bit JPEG or PNG) | tiff16")
    s.add_argument("--orbit", type=int, default=0, metavar="N",
                   help="also render N novel views on a smooth path through the job's cameras")
    s.set_defaults(func=cmd_render)

    s = sub.add_parser("ablate", help="the paper's Table 2 (module and loss ablations) on a generated scene")
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--iterations", type=_positive, default=1500, help="training iterations per row")
    s.add_argument("--views", type=_positive, default=16)
    s.add_argument("--size", type=_size, default=(160, 120), help="WxH, e.g. 160x120")
    s.add_argument("--water", default="medium", choices=["clear", "medium", "turbid"])
    s.add_argument("--rows", default="paper", choices=["paper", "leave-one-out"])
    s.add_argument("--only", default="", help="comma-separated row names to run (default: the whole set)")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=cmd_ablate)

    s = sub.add_parser("warmup", help="compile the rasterizer's and the restorer's numba kernels into their "
                                      "cache (a fresh install's first job otherwise spends minutes on it)")
    s.set_defaults(func=cmd_warmup)

    from service.client.cli import add_client_commands

    add_client_commands(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    for noisy in ("numba", "matplotlib", "PIL"):  # -v is for our stages: numba alone logs every compiled statement
        logging.getLogger(noisy).setLevel(max(logging.INFO, logging.getLogger(noisy).level))
    _prepare_runtime()
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
