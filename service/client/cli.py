"""The ``dualphys`` sub-commands that talk to a remote service: submit, status, jobs, download, cancel.

Each maps its flags onto one call of :class:`service.client.remote.ServiceClient`. That module, the only one
needing httpx (the ``client`` extra), is imported when a command connects, so the rest of the CLI works without
the extra. Exit codes: 0 success, 1 a refused key, a
missing job, an unreachable server or any other refused request, 2 bad command line, and with ``--wait`` 3 when
the job failed and 4 when it was cancelled.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from pipeline.cli_args import positive as _positive
from pipeline.job.options import COLOUR_SPACES, JOB_MODES, RESTORE_FORMATS
from service.client.download import download_bundle, download_job
from service.client.errors import ClientError
from service.client.progress import JobBar, byte_bar
from service.client.watch import wait_job
from service.client.zipping import archive_content_type, file_stream, folder_entries, zip_stream

SERVER_ENV, KEY_ENV = "DUALPHYS_SERVER", "DUALPHYS_KEY"  # no Settings field is named server or key (tested)
DEFAULT_SERVER = "http://127.0.0.1:8000"  # where `dualphys serve` listens by default
JOB_EXIT = {"done": 0, "failed": 3, "cancelled": 4}


def _fail(command: str, message: str) -> int:
    """``dualphys <command>: <message>`` on stderr; exit code 1."""
    print(f"dualphys {command}: {message}", file=sys.stderr)
    return 1


def _server(args: argparse.Namespace) -> str:
    return args.server or os.environ.get(SERVER_ENV) or DEFAULT_SERVER


def _connect(args: argparse.Namespace):
    """A ServiceClient from --server/--key or the environment; None (after the message) when it cannot be made."""
    try:
        from service.client.remote import ServiceClient  # lazy: httpx is the optional client extra
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
               "restore_format": args.format, "max_gain": args.max_gain, "ortho": args.ortho,
               "ortho_gsd": args.ortho_gsd, "telemetry": args.telemetry, "scale_bar": args.scale_bar}
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


def _run(args: argparse.Namespace, job_id: str | None, body) -> int:
    """Connect, run ``body(client)`` (returns the exit code) and turn a refused request into its message."""
    client = _connect(args)
    if client is None:
        return 1
    with client:
        try:
            return body(client)
        except ClientError as e:
            return _client_error(args, e, job_id)


def cmd_status(args: argparse.Namespace) -> int:
    def body(client) -> int:
        if args.wait:
            return _wait(args, client, args.job)
        job = client.job(args.job)
        print(json.dumps(job if args.full else _job_line(job)))
        return 0

    return _run(args, args.job, body)


def cmd_jobs(args: argparse.Namespace) -> int:
    def body(client) -> int:
        jobs = client.jobs(status=args.status, limit=args.limit)
        if args.json:
            print(json.dumps([_job_line(j) for j in jobs]))
            return 0
        print(f"{'id':<34} {'state':<10} {'progress':>8}  {'stage':<9} {'created (UTC)':<19}  source")
        for j in jobs:
            created = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(j["created_at"]))
            source = (j.get("source") or {}).get("filename") or (j.get("source") or {}).get("kind") or ""
            print(f"{j['id']:<34} {j['state']:<10} {j['progress']:7.1f}%  {j.get('stage') or '-':<9} "
                  f"{created:<19}  {source}")
        return 0

    return _run(args, None, body)


def cmd_download(args: argparse.Namespace) -> int:
    """The job's artifacts into --out, resumable and verified; or --bundle: everything as one zip."""
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
    def body(client) -> int:
        job = client.cancel(args.job)
        if args.wait:
            return _wait(args, client, args.job)
        print(json.dumps(_job_line(job)))
        return 0

    return _run(args, args.job, body)


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


def add_client_commands(sub) -> None:
    """The client sub-commands (submit, status, jobs, download, cancel) on the ``dualphys`` parser."""
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
    s.add_argument("--ortho", default=None, action=argparse.BooleanOptionalAction,
                   help="make the orthomosaics and elevation model (--no-ortho: skip them)")
    s.add_argument("--ortho-gsd", type=float, default=None, help="the products' ground resolution, metres per pixel")
    s.add_argument("--telemetry", default=None, help="the name of a per-frame CSV inside the folder or archive")
    s.add_argument("--scale-bar", default=None, help="known lengths: 'PHOTO:X1,Y1:X2,Y2:METRES', several joined by ';'")
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
                   help="only these artifacts (repeatable): a glob over the artifact's path (GET "
                        "/v1/jobs/JOB/artifacts lists them), e.g. '*.ply'; without '/' it also matches a file or "
                        "folder name, or a file name without its extension: 'restored' (the restored photos and "
                        "renders), 'survey' (the survey stage's result and the orthomosaics, DEM and previews)")
    s.add_argument("--bundle", action="store_true", help="everything as one zip, <out>/<job>.zip (not resumable)")
    s.set_defaults(func=cmd_download)

    s = sub.add_parser("cancel", parents=[parent], help="cancel a remote job")
    s.add_argument("job")
    s.add_argument("--wait", action="store_true", help="wait until it has stopped (exit 4 when cancelled)")
    s.add_argument("--interval", type=float, default=1.0, help="seconds between polls with --wait (default: 1)")
    s.set_defaults(func=cmd_cancel)
