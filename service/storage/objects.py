"""The object-store client: one bucket, one key prefix, through boto3 (docs/DECISIONS.md, "Object store client").

Everything the service needs of the S3 API is here: put/get a file or bytes, list a prefix with ETags, delete
a prefix. Keys are ``<prefix>/<name>``; names are POSIX paths (``jobs/<id>/train/latest.pt``).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import boto3
from boto3.s3.transfer import TransferConfig
from botocore.config import Config
from botocore.exceptions import ClientError

log = logging.getLogger(__name__)

SINGLE_PUT_MAX = 256 << 20  # above this a file goes up in parts (s3transfer), and its ETag is read back
_TRANSFER = TransferConfig(multipart_threshold=SINGLE_PUT_MAX, multipart_chunksize=64 << 20, max_concurrency=4)


@dataclass(frozen=True)
class RemoteObject:
    name: str  # the key without the store's prefix
    etag: str
    size: int


class ObjectStore:
    def __init__(self, url: str, bucket: str, prefix: str, access_key: str | None, secret_key: str | None,
                 region: str = "us-east-1", timeout_s: float = 60.0, connect_timeout_s: float = 5.0):
        self.bucket, self.prefix = bucket, prefix.strip("/")
        self.client = boto3.session.Session().client(
            "s3", endpoint_url=url, aws_access_key_id=access_key, aws_secret_access_key=secret_key,
            region_name=region,
            config=Config(s3={"addressing_style": "path"}, connect_timeout=connect_timeout_s, read_timeout=timeout_s,
                          retries={"max_attempts": 4, "mode": "standard"}))

    def key(self, name: str) -> str:
        return f"{self.prefix}/{name}" if self.prefix else name

    def ensure_bucket(self) -> None:
        try:
            self.client.head_bucket(Bucket=self.bucket)
        except ClientError:
            self.client.create_bucket(Bucket=self.bucket)

    # ---- objects
    def put_bytes(self, name: str, data: bytes) -> str:
        return self.client.put_object(Bucket=self.bucket, Key=self.key(name), Body=data)["ETag"]

    def get_bytes(self, name: str) -> bytes | None:
        """The object's bytes, None when there is none."""
        try:
            return self.client.get_object(Bucket=self.bucket, Key=self.key(name))["Body"].read()
        except ClientError as e:
            if _missing(e):
                return None
            raise

    def exists(self, name: str) -> bool:
        try:
            self.client.head_object(Bucket=self.bucket, Key=self.key(name))
            return True
        except ClientError as e:
            if _missing(e):
                return False
            raise

    def put_file(self, name: str, path: Path) -> str:
        """Upload ``path``; returns the object's ETag (what ``list`` reports for it)."""
        if os.path.getsize(path) <= SINGLE_PUT_MAX:
            with open(path, "rb") as f:
                return self.client.put_object(Bucket=self.bucket, Key=self.key(name), Body=f)["ETag"]
        self.client.upload_file(str(path), self.bucket, self.key(name), Config=_TRANSFER)
        return self.client.head_object(Bucket=self.bucket, Key=self.key(name))["ETag"]

    def get_file(self, name: str, path: Path) -> None:
        """Download to ``path`` through a temp file in its folder and a rename (a reader never sees half)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.download")
        try:
            self.client.download_file(self.bucket, self.key(name), str(tmp), Config=_TRANSFER)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)

    def list(self, prefix: str) -> dict[str, RemoteObject]:
        """Every object under ``prefix`` (a name ending in ``/``), by name."""
        out = {}
        for page in self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket,
                                                                          Prefix=self.key(prefix)):
            for o in page.get("Contents", []):
                name = o["Key"][len(self.key("")):]
                out[name] = RemoteObject(name, o["ETag"], int(o["Size"]))
        return out

    def folders(self, prefix: str) -> list[str]:
        """The names of the 'folders' directly under ``prefix`` (common prefixes), without the trailing ``/``."""
        out = []
        for page in self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Delimiter="/",
                                                                          Prefix=self.key(prefix)):
            out += [p["Prefix"][len(self.key(prefix)):].rstrip("/") for p in page.get("CommonPrefixes", [])]
        return out

    def delete(self, names: list[str]) -> None:
        for i in range(0, len(names), 1000):
            batch = [{"Key": self.key(n)} for n in names[i:i + 1000]]
            self.client.delete_objects(Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True})

    def delete_prefix(self, prefix: str) -> int:
        names = list(self.list(prefix))
        self.delete(names)
        return len(names)

    def ping(self) -> None:
        self.client.head_bucket(Bucket=self.bucket)


def _missing(e: ClientError) -> bool:
    return e.response.get("Error", {}).get("Code") in ("404", "NoSuchKey", "NotFound")
