"""The ``dualphys`` command: its parser and the dispatch to the sub-commands.

The pipeline's sub-commands (synth, sfm, demo, run, render, ablate, train-classifier, warmup) live in
cli/pipeline_commands.py, which imports torch: it is imported when one of them runs, after the thread settings
below are in place, so the remote client (``pip install 'dualphys[client]'``, no torch) parses and runs its
commands without it. ``dualphys run``'s job flags come from ``JobOptions``' fields (cli/job_flags.py).

Exit codes: 0 success, 1 a pipeline error the user can act on (message on stderr), 2 bad command line. The
client commands (submit, status, jobs, download, cancel: a remote service) use 1 for a refused key, a missing
job, an unreachable server or any other refused request, and with ``--wait`` 3 when the job failed and 4 when it
was cancelled.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from cli.job_flags import add_job_flags
from pipeline.cli_args import positive as _positive
from pipeline.job.options import RESTORE_FORMATS, JobOptions
from service.client.cli import add_client_commands

_JOB_DEFAULTS = JobOptions()  # dualphys render's --max-gain and --format default as a job's do


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


def _latlon(text: str) -> tuple[float, float]:
    lat, lon = _pair(text, "GPS origin", "-9.5988,143.7811 (lat,lon degrees)")
    if not (-80 <= lat <= 84 and -180 <= lon <= 180):
        raise argparse.ArgumentTypeError(f"GPS origin must be a UTM latitude (-80..84) and a longitude, got {text!r}")
    return lat, lon


def _fraction(text: str) -> float:
    try:
        f = float(text)
    except ValueError:
        f = -1.0
    if not 0 <= f < 1:
        raise argparse.ArgumentTypeError(f"a fraction in [0, 1) is needed, got {text!r}")
    return f


def _pipeline_command(args: argparse.Namespace) -> int:
    """Run the pipeline sub-command ``args.command`` (cli/pipeline_commands.py)."""
    # lazy: the client install has no torch, which these commands import (and only after _prepare_runtime)
    from cli.pipeline_commands import COMMANDS

    return COMMANDS[args.command](args)


def cmd_serve(args: argparse.Namespace) -> int:
    """The API, a worker and beat on this machine (service/embedded.py)."""
    # lazy: the client install has no service extra (uvicorn, redis, FastAPI), which serve imports
    from service.embedded import serve

    try:
        serve(args.host, args.port, args.data_dir, redis_url=args.redis_url, api_keys_file=args.api_keys_file,
              worker_concurrency=args.workers, beat=not args.no_beat, log_level=args.log_level)
    except (RuntimeError, ValueError, OSError) as e:  # no Redis, unreadable keys: a message, not a traceback
        print(f"dualphys serve: {e}", file=sys.stderr)
        return 1
    return 0


def _add_synth(sub) -> None:
    """dualphys synth: a generated scene and its flags (the procedural and the photo family)."""
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
    s.add_argument("--gps", type=_latlon, default=None, metavar="LAT,LON",
                   help="photo family: latitude,longitude (degrees) of the world origin; each photo's EXIF and "
                        "records.csv then carry its GPS position (world x east, y north, UTM metres; "
                        "pipeline.synth.geo); e.g. --gps=-9.5988,143.7811 (default: no GPS)")
    s.add_argument("--altimeter-noise", type=float, default=None, metavar="F",
                   help="photo family: relative std of the altimeter's error in EXIF SubjectDistance (default "
                        "0.02; 0 = exact; negative = no altimeter tag)")
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
    s.set_defaults(func=_pipeline_command)


def _add_sfm(sub) -> None:
    s = sub.add_parser("sfm", help="structure from motion: images -> posed PINHOLE cameras + sparse points")
    s.add_argument("images", type=Path)
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--matcher", default="auto", choices=["auto", "exhaustive", "sequential"])
    s.set_defaults(func=_pipeline_command)


def _add_train_classifier(sub) -> None:
    s = sub.add_parser("train-classifier", help="retrain the water-type classifier on generated scenes")
    s.add_argument("--out", type=Path, default=None, help="weights file (default: the shipped one)")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=_pipeline_command)


def _add_serve(sub) -> None:
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


def _add_demo(sub) -> None:
    s = sub.add_parser("demo", help="generate a scene and run the pipeline on it end to end")
    s.add_argument("--out", type=Path, default=Path("demo-out"))
    s.add_argument("--iterations", type=int, default=1500, help="training iterations (CPU budget)")
    s.set_defaults(func=_pipeline_command)


def _add_run(sub) -> None:
    """dualphys run: the input, the job folder and the job's options."""
    s = sub.add_parser("run", help="run a whole job (ingest, sfm, classify, train, evaluate, restore, export) in "
                                   "this process; re-running resumes")
    s.add_argument("input", type=Path,
                   help="a folder of images (and videos), a zip/tar archive of them, or one video (MP4/MOV)")
    s.add_argument("--out", required=True, type=Path, help="the job folder (created; reused to resume)")
    add_job_flags(s)  # --preset, --mode, ... from JobOptions' fields (cli/job_flags.py)
    s.set_defaults(func=_pipeline_command)


def _add_render(sub) -> None:
    s = sub.add_parser("render", help="render a trained job's views (restored, with water, maps) and novel views")
    s.add_argument("job", type=Path, help="a job folder that `dualphys run` trained")
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--views", default="all", help="all | none | comma-separated view names (with or without "
                                                  "extension)")
    s.add_argument("--what", default="restored,with_water",
                   help="comma-separated: photos (the job's input photos de-watered at full resolution, with "
                        "their confidence maps), restored, with_water, depth, attenuation, backscatter (the "
                        "model's renders at the training resolution)")
    s.add_argument("--max-gain", type=float, default=_JOB_DEFAULTS.max_gain,
                   help="photos: cap on the per-channel gain 1/A")
    s.add_argument("--format", default=_JOB_DEFAULTS.restore_format, choices=list(RESTORE_FORMATS),
                   help="photos: auto (as each input: 8-bit JPEG or PNG) | tiff16")
    s.add_argument("--orbit", type=int, default=0, metavar="N",
                   help="also render N novel views on a smooth path through the job's cameras")
    s.set_defaults(func=_pipeline_command)


def _add_ablate(sub) -> None:
    s = sub.add_parser("ablate", help="the paper's Table 2 (module and loss ablations) on a generated scene")
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--iterations", type=_positive, default=1500, help="training iterations per row")
    s.add_argument("--views", type=_positive, default=16)
    s.add_argument("--size", type=_size, default=(160, 120), help="WxH, e.g. 160x120")
    s.add_argument("--water", default="medium", choices=["clear", "medium", "turbid"])
    s.add_argument("--rows", default="paper", choices=["paper", "leave-one-out"])
    s.add_argument("--only", default="", help="comma-separated row names to run (default: the whole set)")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=_pipeline_command)


def _add_warmup(sub) -> None:
    s = sub.add_parser("warmup", help="compile the rasterizer's and the restorer's numba kernels into their "
                                      "cache (a fresh install's first job otherwise spends minutes on it)")
    s.set_defaults(func=_pipeline_command)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dualphys",
                                description="Underwater Gaussian splatting with the water modelled out.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)
    for add in (_add_synth, _add_sfm, _add_train_classifier, _add_serve, _add_demo, _add_run, _add_render,
                _add_ablate, _add_warmup):  # the order of --help's list
        add(sub)
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
