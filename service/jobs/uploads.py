"""Receiving an upload without letting Starlette spool it: the request body is streamed straight into the job
folder with a byte counter (Starlette's own multipart handling writes the whole file to TMPDIR first and has no
size cap; docs/DECISIONS.md, "Numbers behind code comments").

Two shapes are accepted on ``POST /v1/jobs``:

- ``multipart/form-data`` with one file part named ``archive`` and plain fields for the options (a file part
  under any other name, ``file`` included, is refused with 400 ``unexpected_file``: one documented name);
- a raw body (``application/zip``, ``application/x-tar``, ``application/gzip``, ``application/octet-stream``, ...)
  with the options in the query string.

A declared ``Content-Length`` over the cap is refused before reading; a body that grows past the cap while
streaming is refused as soon as it does. In both cases a modest excess is read and discarded first, so that an
ordinary HTTP client (which sends its whole body before reading) gets the 413 instead of a reset connection.
"""

from __future__ import annotations

import hashlib
import unicodedata
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

FILE_FIELDS = ("archive",)
RAW_TYPES = frozenset({"application/zip", "application/x-zip-compressed", "application/x-tar", "application/gzip",
                       "application/x-gzip", "application/x-bzip2", "application/x-xz", "application/octet-stream"})
MAX_FIELDS = 32
MAX_FIELD_BYTES = 1024
MULTIPART_OVERHEAD = 64 << 10  # boundaries, part headers and option fields on top of the archive itself
DRAIN_LIMIT = 64 << 20  # at most this much of a refused body is read (and discarded) before answering


class UploadError(Exception):
    """A refused upload: HTTP status, stable code, message."""

    def __init__(self, status: int, code: str, message: str):
        super().__init__(message)
        self.status = status
        self.code = code


@dataclass
class ReceivedUpload:
    path: Path
    bytes: int
    sha256: str
    filename: str | None
    fields: dict[str, str] = field(default_factory=dict)


def _too_large(max_bytes: int) -> UploadError:
    return UploadError(413, "upload_too_large", f"the upload is larger than the limit of {max_bytes} bytes")


def check_declared_length(content_length: str | None, max_bytes: int) -> int | None:
    """Validate Content-Length before reading anything (413 when it announces too much)."""
    if content_length is None:
        return None
    try:
        n = int(content_length)
    except ValueError as e:
        raise UploadError(400, "bad_content_length", "Content-Length is not a number") from e
    if n > max_bytes + MULTIPART_OVERHEAD:
        raise _too_large(max_bytes)
    return n


def drain_allowed(received: int, max_bytes: int) -> bool:
    """Keep reading (and discarding) a refused body while it is at most this much over the cap."""
    return received <= max_bytes + MULTIPART_OVERHEAD + min(max_bytes, DRAIN_LIMIT)


class _FileSink:
    def __init__(self, dest: Path, max_bytes: int):
        self.dest, self.max_bytes = dest, max_bytes
        self.bytes = 0
        self._hash = hashlib.sha256()
        self._out = None

    def open(self) -> None:
        self.dest.parent.mkdir(parents=True, exist_ok=True)
        self._out = open(self.dest, "xb")

    def write(self, data: bytes) -> None:
        self.bytes += len(data)
        if self.bytes > self.max_bytes:
            raise _too_large(self.max_bytes)
        assert self._out is not None
        self._out.write(data)
        self._hash.update(data)

    def close(self) -> None:
        if self._out is not None:
            self._out.close()
            self._out = None

    @property
    def sha256(self) -> str:
        return self._hash.hexdigest()


class _MultipartReceiver:
    """python-multipart's streaming parser wired to one file sink and a few small text fields."""

    def __init__(self, boundary: bytes, sink: _FileSink):
        self.sink = sink
        self.fields: dict[str, str] = {}
        self.filename: str | None = None
        self.got_file = False
        self._headers: dict[bytes, bytes] = {}
        self._hname = bytearray()
        self._hval = bytearray()
        self._kind: str | None = None  # "file" | "field"
        self._name = ""
        self._value = bytearray()
        self.parser = MultipartParser(boundary, {
            "on_part_begin": self._part_begin, "on_header_field": self._header_field,
            "on_header_value": self._header_value, "on_header_end": self._header_end,
            "on_headers_finished": self._headers_finished, "on_part_data": self._part_data,
            "on_part_end": self._part_end,
        })

    def _part_begin(self) -> None:
        self._headers, self._kind, self._value = {}, None, bytearray()

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self._hname += data[start:end]

    def _header_value(self, data: bytes, start: int, end: int) -> None:
        self._hval += data[start:end]

    def _header_end(self) -> None:
        self._headers[bytes(self._hname).lower()] = bytes(self._hval)
        self._hname, self._hval = bytearray(), bytearray()

    def _headers_finished(self) -> None:
        disp, params = parse_options_header(self._headers.get(b"content-disposition", b""))
        if disp != b"form-data" or b"name" not in params:
            raise UploadError(400, "malformed_multipart", "a multipart part has no form-data name")
        self._name = params[b"name"].decode("utf-8", "replace")
        if b"filename" in params:
            if self._name not in FILE_FIELDS:
                raise UploadError(400, "unexpected_file", f"file part {self._name!r}; send the archive as 'archive'")
            if self.got_file:
                raise UploadError(400, "too_many_files", "send exactly one archive per job")
            self.got_file, self._kind = True, "file"
            self.filename = clean_filename(params[b"filename"].decode("utf-8", "replace"))
            self.sink.open()
        else:
            if len(self.fields) >= MAX_FIELDS:
                raise UploadError(400, "too_many_fields", f"at most {MAX_FIELDS} form fields")
            self._kind = "field"

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        if self._kind == "file":
            self.sink.write(data[start:end])
        else:
            self._value += data[start:end]
            if len(self._value) > MAX_FIELD_BYTES:
                raise UploadError(400, "field_too_large", f"form field {self._name!r} is longer than "
                                                          f"{MAX_FIELD_BYTES} bytes")

    def _part_end(self) -> None:
        if self._kind == "file":
            self.sink.close()
        elif self._kind == "field":
            try:
                self.fields[self._name] = self._value.decode("utf-8")
            except UnicodeDecodeError as e:
                raise UploadError(400, "bad_field", f"form field {self._name!r} is not UTF-8") from e


def clean_filename(name: str) -> str:
    name = unicodedata.normalize("NFC", name.replace("\\", "/").rsplit("/", 1)[-1])
    return "".join(c for c in name if c.isprintable())[:200]


async def receive_upload(chunks: AsyncIterator[bytes], content_type: str, query: dict[str, str], dest: Path,
                         max_bytes: int) -> ReceivedUpload:
    """Stream the body into ``dest`` (created; must not exist). Raises UploadError; on error the caller removes
    the job folder. The body is drained (within limits) before an error is raised, see the module docstring."""
    mime, params = parse_options_header(content_type or "")
    mime_s = mime.decode("latin-1").lower()
    sink = _FileSink(dest, max_bytes)
    error: UploadError | None = None
    received = 0
    if mime_s == "multipart/form-data":
        boundary = params.get(b"boundary")
        if not boundary:
            raise UploadError(400, "malformed_multipart", "multipart/form-data without a boundary")
        receiver = _MultipartReceiver(boundary, sink)
        async for chunk in chunks:
            received += len(chunk)
            if error is None:
                try:
                    receiver.parser.write(chunk)
                except UploadError as e:
                    error = e
                except MultipartParseError as e:
                    error = UploadError(400, "malformed_multipart", f"the multipart body is malformed: {e}")
            if not drain_allowed(received, max_bytes):
                error = error or _too_large(max_bytes)
                break
        sink.close()
        if error is None:
            try:
                receiver.parser.finalize()
            except MultipartParseError as e:
                error = UploadError(400, "malformed_multipart", f"the multipart body is incomplete: {e}")
        if error is None and not receiver.got_file:
            error = UploadError(400, "missing_archive", "no file part named 'archive' in the form")
        if error is not None:
            raise error
        return ReceivedUpload(dest, sink.bytes, sink.sha256, receiver.filename, receiver.fields)
    if mime_s in RAW_TYPES:
        sink.open()
        async for chunk in chunks:
            received += len(chunk)
            if error is None:
                try:
                    sink.write(chunk)
                except UploadError as e:
                    error = e
            if error is not None and not drain_allowed(received, max_bytes):
                break
        sink.close()
        if error is not None:
            raise error
        if sink.bytes == 0:
            raise UploadError(400, "missing_archive", "the request body is empty")
        return ReceivedUpload(dest, sink.bytes, sink.sha256, query.get("filename"), dict(query))
    raise UploadError(415, "unsupported_media_type",
                      "send multipart/form-data with an 'archive' file, or the archive as the raw body")
