"""Helpers shared by the service tests (imported by conftest.py and the test modules)."""

from __future__ import annotations

import io
import logging
import os
import signal
import socket
import subprocess
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import httpx
import redis

REPO = Path(__file__).resolve().parents[2]
REDIS_URL = "redis://127.0.0.1:6379/15"
KEYS = {"alice": "alice-key-0123456789abcdef", "bob": "bob-key-0123456789abcdef"}
HOOK_SECRETS = {"alice": "alice-webhook-secret-0123456789"}  # bob has none: he cannot set a callback_url
MAX_UPLOAD = 4 << 20
MAX_ENTRIES = 200
SCENE = {"views": 12, "width": 160, "height": 120, "preset": "medium", "seed": 0}

log = logging.getLogger(__name__)

# numbers the tests report at the end of the run (p99 latency ...); printed by conftest
METRICS: dict[str, str] = {}


def wait_for(what: str, predicate: Callable[[], object], timeout: float, interval: float = 0.2):
    """Poll ``predicate`` until it returns something truthy; fail with ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = predicate()
        if last:
            return last
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what} (last: {last!r})")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def zip_bytes(entries: dict[str, bytes], method: int = zipfile.ZIP_STORED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as z:
        for name, data in entries.items():
            z.writestr(name, data)
    return buf.getvalue()


def auth(owner: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {KEYS[owner]}"}


def delete_prefix(client: redis.Redis, prefix: str) -> None:
    for k in client.scan_iter(match=f"{prefix}:*", count=1000):
        client.delete(k)


def small_jpegs(n: int, seed: int = 0, size: tuple[int, int] = (24, 32)) -> list[bytes]:
    """Tiny valid JPEGs (random texture): enough for ingest, not for SfM."""
    import tempfile

    import numpy as np

    from pipeline.scene.images import write_image

    out = []
    with tempfile.TemporaryDirectory() as d:
        for i in range(n):
            rng = np.random.default_rng(seed + i)
            p = Path(d) / f"{i}.jpg"
            write_image(p, (rng.random((*size, 3)) * 255).astype(np.uint8))
            out.append(p.read_bytes())
    return out


def small_video(frames: int = 40, seed: int = 0) -> bytes:
    """A short H.264 MP4 (128x96, 10 fps) panning 4 px a frame over a smooth random texture: a few keyframes."""
    import tempfile

    import numpy as np

    from pipeline.synth.video import encode_video

    rng = np.random.default_rng(seed)
    tex = rng.random((28, 32 + frames, 3))
    tex = np.repeat(np.repeat(tex, 4, 0), 4, 1)  # 4 px blocks: structure the codec keeps
    with tempfile.TemporaryDirectory() as d:
        p = encode_video(((tex[8:104, 4 * i:4 * i + 128] * 255).astype(np.uint8) for i in range(frames)),
                         Path(d) / "v.mp4", 10)
        return p.read_bytes()


def make_settings(data_dir: Path, prefix: str, **over):
    from service.core.settings import load_settings

    base = dict(api_keys={v: k for k, v in KEYS.items()}, data_dir=data_dir, redis_url=REDIS_URL,
                redis_prefix=prefix, max_upload_bytes=MAX_UPLOAD, archive_max_entries=MAX_ENTRIES, min_free_bytes=0,
                survey_roots=[data_dir / "surveys-root"], survey_min_interval_s=1, lock_ttl_s=5, lock_retry_s=1)
    return load_settings(**{**base, **over})



class PrivateRedis:
    """A redis-server of a test's own on a free 127.0.0.1 port (never the shared one), to stop and restart.
    ``appendonly``: persistence in an append-only file (``appendfsync always``); else none at all, so a restart
    loses every key, as a Redis without persistence does."""

    def __init__(self, folder: Path, appendonly: bool):
        self.folder, self.appendonly, self.port = folder, appendonly, free_port()
        self.proc: subprocess.Popen | None = None
        folder.mkdir(parents=True, exist_ok=True)

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        args = ["redis-server", "--bind", "127.0.0.1", "--port", str(self.port), "--dir", str(self.folder),
                "--save", "", "--appendonly", "yes" if self.appendonly else "no"]
        if self.appendonly:
            args += ["--appendfsync", "always"]
        log_file = open(self.folder / "redis.log", "ab")
        self.proc = subprocess.Popen(args, stdout=log_file, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     start_new_session=True)
        log_file.close()
        client = redis.Redis(port=self.port, socket_connect_timeout=1)

        def up() -> bool:
            assert self.proc.poll() is None, (self.folder / "redis.log").read_text()[-2000:]
            try:
                return bool(client.ping())
            except redis.RedisError:
                return False

        wait_for("the private redis-server", up, timeout=20, interval=0.05)
        client.close()

    def stop(self) -> None:
        """SIGTERM: a clean shutdown (the append-only file is complete; without persistence everything is lost)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(timeout=20)

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=10)


class RecordingDispatcher:
    """Stands in for service.core.dispatch.Dispatcher: records what would be sent."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, str, str]] = []
        self.webhooks: list[tuple[str, str]] = []  # (job_id, delivery_id)

    def send_stage(self, job_id: str, stage: str, run_id: str) -> str:
        self.sent.append((job_id, stage, run_id))
        return f"task-{len(self.sent)}"

    def send_webhook(self, job_id: str, delivery_id: str, countdown: float | None = None) -> str:
        self.webhooks.append((job_id, delivery_id))
        return f"hook-{len(self.webhooks)}"


# ---------------------------------------------------------------- job helpers


def upload(client: httpx.Client, archive: bytes, filename: str = "set.zip", headers: dict | None = None,
           **fields) -> httpx.Response:
    return client.post("/v1/jobs", files={"archive": (filename, archive, "application/zip")},
                       data={k: str(v) for k, v in fields.items()}, headers=headers or {})


def job_status(client: httpx.Client, job_id: str) -> dict:
    r = client.get(f"/v1/jobs/{job_id}")
    assert r.status_code == 200, r.text
    return r.json()


def wait_job(client: httpx.Client, job_id: str, states: set[str], timeout: float,
             on_poll: Callable[[dict], None] | None = None) -> dict:
    def check():
        s = job_status(client, job_id)
        if on_poll:
            on_poll(s)
        return s if s["state"] in states else None

    return wait_for(f"job {job_id} to reach {sorted(states)}", check, timeout, interval=0.25)


def job_log(client: httpx.Client, job_id: str) -> str:
    text, offset = [], 0
    while True:
        r = client.get(f"/v1/jobs/{job_id}/log", params={"offset": offset})
        assert r.status_code == 200, r.text
        d = r.json()
        text.append(d["text"])
        if d["next_offset"] == offset:
            return "".join(text)
        offset = d["next_offset"]


# ---------------------------------------------------------------- archives zipfile cannot write


def _crc_byte(crc: int, b: int) -> int:
    """One step of the raw CRC-32 register update that PKWARE's traditional encryption uses."""
    import zlib

    return ~zlib.crc32(bytes([b]), ~crc & 0xFFFFFFFF) & 0xFFFFFFFF


def encrypted_zip(entries: dict[str, bytes], password: bytes = b"secret") -> bytes:
    """A stored zip whose entries are encrypted with PKWARE's traditional ("ZipCrypto") scheme, as `zip -P`
    writes it (zipfile reads but cannot write encrypted entries). APPNOTE.TXT 6.1."""
    import struct
    import zlib

    def keys_for() -> list[int]:
        k = [0x12345678, 0x23456789, 0x34567890]
        for c in password:
            update(k, c)
        return k

    def update(k: list[int], c: int) -> None:
        k[0] = _crc_byte(k[0], c)
        k[1] = ((k[1] + (k[0] & 0xFF)) * 134775813 + 1) & 0xFFFFFFFF
        k[2] = _crc_byte(k[2], (k[1] >> 24) & 0xFF)

    def encrypt(data: bytes) -> bytes:
        k = keys_for()
        out = bytearray()
        for p in data:
            t = (k[2] | 2) & 0xFFFF
            out.append(p ^ (((t * (t ^ 1)) >> 8) & 0xFF))
            update(k, p)
        return bytes(out)

    body, central = bytearray(), bytearray()
    for name, data in entries.items():
        crc = zlib.crc32(data)
        enc = encrypt(bytes(11) + bytes([crc >> 24]) + data)
        fname = name.encode()
        offset = len(body)
        fields = (20, 0x1, 0, 0, 0x21, crc, len(enc), len(data), len(fname))
        body += struct.pack("<IHHHHHIIIHH", 0x04034B50, *fields, 0) + fname + enc
        central += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, *fields, 0, 0, 0, 0, 0, offset) + fname
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(entries), len(entries), len(central), len(body), 0)
    return bytes(body + central + end)
