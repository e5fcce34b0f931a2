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


def _distortion(text: str) -> tuple[float, float]:
    try:
        k1, k2 = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"distortion must look like -0.15,0.02 (k1,k2), got {text!r}") from None
    return k1, k2


def _positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


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
        photo = PhotoSynthConfig(views=args.views, width=w, height=h, preset=args.preset, seed=args.seed,
                                 distortion=args.distortion, water_space=args.water_space)
        try:
            out = generate_photo_scene(photo, args.out)
        except (TextureFolderError, ValueError) as e:
            print(f"dualphys synth: {e}", file=sys.stderr)
            return 1
        views, preset = photo.views, photo.preset
    else:
        from pipeline.config import SynthConfig
        from pipeline.synth.procedural import generate_scene

        cfg = SynthConfig(views=args.views, width=w, height=h, preset=args.preset, seed=args.seed, path=args.path,
                          distortion=args.distortion, water_space=args.water_space)
        try:
            out = generate_scene(cfg, args.out)
        except ValueError as e:
            print(f"dualphys synth: {e}", file=sys.stderr)
            return 1
        views, preset = cfg.views, cfg.preset
    print(json.dumps({"out": str(out), "family": args.family, "views": views, "preset": preset,
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
    from pipeline.evaluate.metrics import per_metre
    from pipeline.job.layout import JobLayout
    from pipeline.job.options import JobOptions, StageContext
    from pipeline.job.runner import run_job
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
          f"(p={water['probabilities'][water['water_type']]:.2f}); held-out PSNR with water "
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


def _fail(command: str, message: str) -> int:
    print(f"dualphys {command}: {message}", file=sys.stderr)
    return 1


def cmd_run(args: argparse.Namespace) -> int:
    """The whole job in this process, with progress bars; finished stages (matching markers) are skipped."""
    from pipeline.job.layout import JobLayout
    from pipeline.job.options import JobOptions, StageContext
    from pipeline.job.progress import StageProgress
    from pipeline.job.runner import run_job
    from pipeline.job.table import STAGES

    src = Path(args.input)
    if not src.exists():
        return _fail("run", f"{src} does not exist: give a folder of images or a zip/tar archive of them")
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
    from pipeline.evaluate.rerender import RenderError, render_job
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


def cmd_serve(args: argparse.Namespace) -> int:
    from service.embedded import serve

    try:
        serve(args.host, args.port, args.data_dir, redis_url=args.redis_url, api_keys_file=args.api_keys_file,
              worker_concurrency=args.workers, beat=not args.no_beat, log_level=args.log_level)
    except (RuntimeError, ValueError, OSError) as e:  # no Redis, unreadable keys: a message, not a traceback
        print(f"dualphys serve: {e}", file=sys.stderr)
        return 1
    return 0


# ---------------------------------------------------------------- client of a remote service (service/client/)

SERVER_ENV, KEY_ENV = "DUALPHYS_SERVER", "DUALPHYS_KEY"  # no Settings field is named server or key (tested)
DEFAULT_SERVER = "http://127.0.0.1:8000"  # where `dualphys serve` listens by default
JOB_EXIT = {"done": 0, "failed": 3, "cancelled": 4}


def _server(args: argparse.Namespace) -> str:
    return args.server or os.environ.get(SERVER_ENV) or DEFAULT_SERVER


def _connect(args: argparse.Namespace):
    """A ServiceClient from --server/--key or the environment; None (after the message) when it cannot be made."""
    try:
        from service.client.remote import ServiceClient
    except ImportError as e:  # httpx missing: the client extra is not installed
        _fail(args.command, f"the client needs httpx ({e}); pip install 'dualphys[client]'")
        return None
    key = args.key or os.environ.get(KEY_ENV, "")
    if not key:
        _fail(args.command, f"no API key: pass --key or set {KEY_ENV}")
        return None
    return ServiceClient(_server(args), key, timeout=args.timeout)


def _client_error(args: argparse.Namespace, e, job_id: str | None = None) -> int:
    """A ClientError as one line on stderr, exit 1: what went wrong and what to check (never the key)."""
    server = _server(args)
    if e.status == 401:
        msg = f"the server refused the API key ({e.code}: {e.message}); check --key or {KEY_ENV}"
    elif e.code == "connection_failed":
        msg = f"cannot connect to {server}: is the service running there? (--server or {SERVER_ENV})"
    elif e.code == "job_not_found" and job_id:
        msg = f"no job {job_id} on {server} for this key ({e.code})"
    else:
        msg = f"{e.message} ({e.code}{f', HTTP {e.status}' if e.status else ''})"
    return _fail(args.command, msg)


def _job_line(job: dict) -> dict:
    keep = ("id", "state", "stage", "progress", "message", "error")
    return {k: job.get(k) for k in keep}


def _wait(args: argparse.Namespace, client, job_id: str) -> int:
    """Poll with a progress bar until the job ends; exit 0 done, 3 failed, 4 cancelled."""
    from service.client.progress import JobBar
    from service.client.watch import wait_job

    bar = JobBar(job_id)
    try:
        job = wait_job(client, job_id, interval_s=args.interval, on_update=bar)
    except KeyboardInterrupt:
        bar.close()
        return _fail(args.command, f"stopped waiting; job {job_id} goes on (dualphys status {job_id} --wait)")
    bar.close()
    print(json.dumps(_job_line(job)))
    if job["state"] != "done":
        err = job.get("error") or {}
        why = f": {err.get('stage')} {err.get('code')}: {err.get('message')}" if err else ""
        print(f"dualphys {args.command}: job {job_id} {job['state']}{why}", file=sys.stderr)
    return JOB_EXIT[job["state"]]


def cmd_submit(args: argparse.Namespace) -> int:
    """A folder (zipped while it uploads) or an archive (sent as is) becomes a job on the server."""
    from service.client.progress import byte_bar
    from service.client.remote import ClientError
    from service.client.zipping import archive_content_type, file_stream, folder_entries, zip_stream

    src: Path = args.path
    if src.is_dir():
        entries = folder_entries(src)
        if not entries:
            return _fail("submit", f"{src} holds no files to send")
        total, length = sum(e.size for e in entries), None  # zipped while sent: chunked, its size unknown ahead
        filename, ctype = f"{src.resolve().name}.zip", "application/zip"

        def body(on_read):
            return zip_stream(entries, on_read)
    elif src.is_file():
        ctype = archive_content_type(src)
        if ctype is None:
            return _fail("submit", f"{src} is not a folder or a .zip/.tar(.gz/.bz2/.xz) archive")
        total = length = src.stat().st_size
        filename = src.name

        def body(on_read):
            return file_stream(src, on_read)
    else:
        return _fail("submit", f"{src} does not exist: give a folder of images or a zip/tar archive of them")
    client = _connect(args)
    if client is None:
        return 1
    options = {"preset": args.preset, "mode": args.mode, "iterations": args.iterations, "max_width": args.max_width,
               "seed": args.seed, "metric_scale": args.metric_scale, "colour_space": args.colour_space,
               "restore_format": args.format, "max_gain": args.max_gain}
    with client:
        try:
            client.check()
        except ClientError as e:
            return _client_error(args, e)
        bar = byte_bar(total, f"upload {filename}")
        try:
            job = client.submit(body(bar.update), filename=filename, content_type=ctype, length=length, options=options,
                                idempotency_key=args.idempotency_key)
        except ClientError as e:
            bar.close()
            if e.status == 0 and e.code != "connection_failed":  # the body went out; the server may have the job
                print(f"dualphys submit: the server may still have created the job: see `dualphys jobs` before "
                      f"sending again{'' if args.idempotency_key else ' (--idempotency-key makes a repeat safe)'}",
                      file=sys.stderr)
            return _client_error(args, e)
        bar.close()
        print(f"job {job['id']} {job['state']} ({job['ingest']['images'] if job.get('ingest') else '?'} images)",
              file=sys.stderr)
        if not args.wait:
            print(json.dumps(_job_line(job)))
            return 0
        try:
            return _wait(args, client, job["id"])
        except ClientError as e:
            return _client_error(args, e, job["id"])


def cmd_status(args: argparse.Namespace) -> int:
    from service.client.remote import ClientError

    client = _connect(args)
    if client is None:
        return 1
    with client:
        try:
            if args.wait:
                return _wait(args, client, args.job)
            job = client.job(args.job)
        except ClientError as e:
            return _client_error(args, e, args.job)
    print(json.dumps(job if args.full else _job_line(job)))
    return 0


def cmd_jobs(args: argparse.Namespace) -> int:
    from service.client.remote import ClientError

    client = _connect(args)
    if client is None:
        return 1
    with client:
        try:
            jobs = client.jobs(status=args.status, limit=args.limit)
        except ClientError as e:
            return _client_error(args, e)
    if args.json:
        print(json.dumps([_job_line(j) for j in jobs]))
        return 0
    print(f"{'id':<34} {'state':<10} {'progress':>8}  {'stage':<9} {'created (UTC)':<19}  source")
    for j in jobs:
        created = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(j["created_at"]))
        source = (j.get("source") or {}).get("filename") or (j.get("source") or {}).get("kind") or ""
        print(f"{j['id']:<34} {j['state']:<10} {j['progress']:7.1f}%  {j.get('stage') or '-':<9} {created:<19}  "
              f"{source}")
    return 0


def cmd_download(args: argparse.Namespace) -> int:
    """The job's artifacts into --out, resumable and verified; or --bundle: everything as one zip."""
    from service.client.download import download_bundle, download_job
    from service.client.progress import byte_bar
    from service.client.remote import ClientError

    out: Path = args.out or Path(args.job)
    client = _connect(args)
    if client is None:
        return 1
    bar = None
    with client:
        try:
            if args.bundle:
                bar = byte_bar(None, f"{args.job}.zip")
                n = download_bundle(client, args.job, out / f"{args.job}.zip", bar.update)
                bar.close()
                print(json.dumps({"bundle": str(out / f"{args.job}.zip"), "bytes": n}))
                return 0

            def plan(chosen) -> None:
                nonlocal bar
                bar = byte_bar(sum(a.size for a in chosen), f"download {args.job}")

            report = download_job(client, args.job, out, args.only, on_bytes=lambda n: bar.update(n), on_plan=plan)
        except ClientError as e:
            if bar is not None:
                bar.close()
            return _client_error(args, e, args.job)
        except KeyboardInterrupt:
            if bar is not None:
                bar.close()
            return _fail("download", "interrupted; run the same command again to resume (finished files are kept, "
                                     "a partial one continues where it stopped)")
    bar.close()
    resumed = [f.path for f in report.files if f.resumed_from]
    print(f"{len(report.files)} files ({report.total} bytes) in {out}, all matching their sha256; fetched "
          f"{report.fetched} bytes, {sum(f.skipped for f in report.files)} already there, {len(resumed)} resumed",
          file=sys.stderr)
    print(json.dumps({"out": str(out), "files": len(report.files), "bytes": report.total, "fetched": report.fetched,
                      "skipped": sum(f.skipped for f in report.files), "resumed": resumed}))
    return 0


def cmd_cancel(args: argparse.Namespace) -> int:
    from service.client.remote import ClientError

    client = _connect(args)
    if client is None:
        return 1
    with client:
        try:
            job = client.cancel(args.job)
            if args.wait:
                return _wait(args, client, args.job)
        except ClientError as e:
            return _client_error(args, e, args.job)
    print(json.dumps(_job_line(job)))
    return 0


def _client_parent() -> argparse.ArgumentParser:
    """--server, --key and --timeout, shared by the client commands."""
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("server")
    g.add_argument("--server", default=None,
                   help=f"the service's base URL (default: ${SERVER_ENV}, else {DEFAULT_SERVER})")
    g.add_argument("--key", default=None,
                   help=f"API key (default: ${KEY_ENV}; the variable keeps it out of the process list)")
    g.add_argument("--timeout", type=float, default=60.0, help="seconds to connect and per read/write (default: 60)")
    return p


def _add_client_commands(sub) -> None:
    from pipeline.job.options import COLOUR_SPACES, JOB_MODES, RESTORE_FORMATS

    parent = _client_parent()
    wait_help = "poll with a progress bar until the job ends: exit 0 done, 3 failed, 4 cancelled"

    s = sub.add_parser("submit", parents=[parent], help="send a folder or archive to a dualphys service as a job",
                       description="Send a folder of images (zipped while it uploads) or a zip/tar archive (as is) to "
                                   "a dualphys service. Options left out take the server's defaults.")
    s.add_argument("path", type=Path, help="a folder of images or a .zip/.tar(.gz/.bz2/.xz) archive of them")
    s.add_argument("--wait", action="store_true", help=wait_help)
    s.add_argument("--interval", type=float, default=2.0, help="seconds between polls with --wait (default: 2)")
    s.add_argument("--preset", default=None, choices=["fast", "balanced", "paper"])
    s.add_argument("--mode", default=None, choices=list(JOB_MODES))
    s.add_argument("--iterations", type=_positive, default=None, help="override the preset's iteration count")
    s.add_argument("--max-width", type=_positive, default=None, help="train wider images at an integer downscale")
    s.add_argument("--seed", type=int, default=None)
    s.add_argument("--metric-scale", type=float, default=None, help="metres per scene unit")
    s.add_argument("--colour-space", default=None, choices=list(COLOUR_SPACES))
    s.add_argument("--format", default=None, choices=list(RESTORE_FORMATS), help="the restored photos' format")
    s.add_argument("--max-gain", type=float, default=None, help="cap on the restoration's per-channel gain 1/A")
    s.add_argument("--idempotency-key", default=None,
                   help="repeating the command with the same key and archive returns the first job")
    s.set_defaults(func=cmd_submit)

    s = sub.add_parser("status", parents=[parent], help="a remote job's state and progress")
    s.add_argument("job")
    s.add_argument("--wait", action="store_true", help=wait_help)
    s.add_argument("--interval", type=float, default=2.0, help="seconds between polls with --wait (default: 2)")
    s.add_argument("--full", action="store_true", help="the whole status record (stages, timings, runs)")
    s.set_defaults(func=cmd_status)

    s = sub.add_parser("jobs", parents=[parent], help="list your jobs on a dualphys service, newest first")
    s.add_argument("--status", default=None, choices=["queued", "running", "done", "failed", "cancelled"])
    s.add_argument("--limit", type=_positive, default=None, help="at most this many (default: all)")
    s.add_argument("--json", action="store_true", help="JSON instead of a table")
    s.set_defaults(func=cmd_jobs)

    s = sub.add_parser("download", parents=[parent], help="download a remote job's results, verified and resumable")
    s.add_argument("job")
    s.add_argument("--out", type=Path, default=None, help="folder for the results (default: ./<job id>)")
    s.add_argument("--only", action="append", default=[], metavar="PATTERN",
                   help="only these artifacts (repeatable): a glob over the path ('*.ply', 'output/restored/*'); "
                        "without '/' it also matches a file or folder name ('report.json', 'restored')")
    s.add_argument("--bundle", action="store_true", help="everything as one zip, <out>/<job>.zip (not resumable)")
    s.set_defaults(func=cmd_download)

    s = sub.add_parser("cancel", parents=[parent], help="cancel a remote job")
    s.add_argument("job")
    s.add_argument("--wait", action="store_true", help="wait until it has stopped (exit 4 when cancelled)")
    s.add_argument("--interval", type=float, default=1.0, help="seconds between polls with --wait (default: 1)")
    s.set_defaults(func=cmd_cancel)


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
    s.add_argument("--water-space", default="srgb", choices=["srgb", "linear"],
                   help="srgb: water applied to J as written; linear: to sRGB-decoded J, re-encoded after")
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
    s.add_argument("input", type=Path, help="a folder of images or a zip/tar archive of them")
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

    _add_client_commands(sub)
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
