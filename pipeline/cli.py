"""The ``dualphys`` command. Each sub-command maps its flags onto a typed config and calls one pipeline
function; heavy modules (torch, pycolmap, OpenImageIO) are imported inside the commands, after the thread
settings below are in place.

Exit codes: 0 success, 1 a pipeline error the user can act on (message on stderr), 2 bad command line.
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

log = logging.getLogger("dualphys")


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


def cmd_synth(args: argparse.Namespace) -> int:
    from .config import SynthConfig
    from .scene.synth import generate_scene

    w, h = args.size
    cfg = SynthConfig(views=args.views, width=w, height=h, preset=args.preset, seed=args.seed, path=args.path)
    t0 = time.perf_counter()
    out = generate_scene(cfg, args.out)
    print(json.dumps({"out": str(out), "views": cfg.views, "preset": cfg.preset,
                      "seconds": round(time.perf_counter() - t0, 2)}))
    return 0


def cmd_sfm(args: argparse.Namespace) -> int:
    from .config import SfmConfig
    from .sfm import SfmError, run_sfm

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
    from .config import SynthConfig
    from .job import JobOptions, StageContext, run_job
    from .scene.align import align_to_reference
    from .scene.loader import load_scene
    from .scene.synth import generate_scene
    from .scene.water_model import WATER_PRESETS

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

    opts = JobOptions(source=str(scene_dir / "images"), mode="dualphys", iterations=args.iterations)
    res = run_job(out / "job", opts, StageContext(on_progress=progress))
    print(f"[2/3] job done in {time.perf_counter() - t0:.0f} s -> {out / 'job'}")
    sfm, water, train = res["sfm"], res["classify"], res["train"]
    errs = align_to_reference(load_scene(out / "job" / "scene"), load_scene(scene_dir))
    coef = train.get("medium", {})
    truth = WATER_PRESETS[synth.preset]
    print(f"[3/3] SfM {sfm['registered']}/{sfm['total']} registered ({sfm['mean_reproj_error_px']:.2f} px; "
          f"cameras within {errs['rot_err_deg_mean']:.2f} deg / {100 * errs['center_err_rel_mean']:.2f} % of "
          f"the path of the truth); water classified '{water['water_type']}' "
          f"(p={water['probabilities'][water['water_type']]:.2f}); held-out PSNR with water "
          f"{_db(res['evaluate']['metrics']['test']['psnr'])}; {train['n_gaussians']} Gaussians")
    rest = res["evaluate"].get("restoration")
    if rest:
        print(f"      restored J against the true clean images (held-out views): PSNR {_db(rest['restored']['psnr'])}, "
              f"SSIM {rest['restored']['ssim']:.3f} (the photos themselves: {_db(rest['input']['psnr'])})")
    if coef:
        # SfM scenes have no metric scale: one scene unit is errs['scale'] metres (similarity to the truth).
        metric = [b / errs["scale"] for b in coef["beta_D"]]
        print("      recovered beta_D (1/m, via the alignment's scale): "
              + ", ".join(f"{c} {m:.3f} (true {t:.3f})" for c, m, t in zip("RGB", metric, truth.beta_D)))
    print(f"      outputs: {out / 'job' / 'output'} (reconstruction.ply, restored/, with_water/, attenuation/, "
          f"backscatter/, depth/)")
    print(f"      report: {(out / 'job' / 'output' / 'report.html').resolve()}")
    summary = {"scene": str(scene_dir), "job": str(out / "job"), "alignment": errs, "results": res,
               "seconds": round(time.perf_counter() - t0, 1)}
    (out / "demo.json").write_text(json.dumps(summary, indent=2, default=str))
    print(json.dumps({"demo": str(out / "demo.json"), "ply": str(out / "job" / "output" / "reconstruction.ply"),
                      "report": str(out / "job" / "output" / "report.html")}))
    return 0


def cmd_train_classifier(args: argparse.Namespace) -> int:
    from .water import train_classifier

    out = args.out or Path(__file__).resolve().parent / "data" / "water_classifier.json"  # the shipped weights
    metrics = train_classifier(out, seed=args.seed)
    print(json.dumps(metrics, default=str))
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    from service.embedded import serve

    serve(args.host, args.port, args.data_dir, redis_url=args.redis_url)
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
    s.add_argument("--path", default="survey", choices=["survey", "lawnmower", "forward"])
    s.add_argument("--seed", type=int, default=0)
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

    s = sub.add_parser("serve", help="run the API, a worker and beat locally against a Redis on localhost")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8000)
    s.add_argument("--data-dir", type=Path, default=Path("dualphys-data"))
    s.add_argument("--redis-url", default="redis://127.0.0.1:6379/0")
    s.set_defaults(func=cmd_serve)

    s = sub.add_parser("demo", help="generate a scene and run the pipeline on it end to end")
    s.add_argument("--out", type=Path, default=Path("demo-out"))
    s.add_argument("--iterations", type=int, default=1500, help="training iterations (CPU budget)")
    s.set_defaults(func=cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    _prepare_runtime()
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
