"""A local folder kept in step with a key prefix of the object store: pull what changed there, push what
changed here, in both directions only what changed.

"Changed" is decided by an index in the folder (``.sync.json``): per file the object's ETag and the local
size and mtime (ns) when the two were last known equal. Pull downloads an object whose ETag differs from the
index's (or whose local copy was touched since); push uploads a file whose size or mtime differs from the index's.
A file the index knows that is gone on the other side is deleted (a stage that removes a file, a marker cleared
for a re-run). Files whose name starts with ``.`` (temp files of atomic writes, caches, the index) or ends with
``.tmp`` (the trainer's checkpoint being written) never travel; a marker (``.stages/*.json``) is pushed after
every other file of the same push, so a host that sees the marker finds the outputs it vouches for.

One writer at a time per folder: the job's run lock (one runner) and the manifest mutex (API and workers)
serialise the pushes; the lock here only keeps one process's threads apart.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

from pipeline.job.layout import JobLayout
from pipeline.job.markers import atomic_write_text

from .objects import ObjectStore

log = logging.getLogger(__name__)

INDEX_NAME = ".sync.json"
_JOB = JobLayout(Path("job"))
MARKERS_DIR = _JOB.relative(_JOB.markers)  # the completion markers' folder


def travels(rel: str) -> bool:
    """Whether the file ``rel`` (POSIX, relative to the folder) is synced at all."""
    parts = rel.split("/")
    name = parts[-1]
    if name.startswith(".") or name.endswith(".tmp"):
        return False
    return all(not p.startswith(".") or p == MARKERS_DIR for p in parts[:-1])


class FolderMirror:
    def __init__(self, objects: ObjectStore, prefix: str, root: Path,
                 include: Callable[[str], bool] = lambda rel: True):
        """``prefix``: the names' common start (``jobs/<id>/``); ``include``: which files this mirror syncs
        (besides :func:`travels`; the API's mirror leaves out what only stages read)."""
        self.objects, self.prefix, self.root, self.include = objects, prefix, Path(root), include
        self.lock = threading.Lock()

    def _wanted(self, rel: str) -> bool:
        return travels(rel) and self.include(rel)

    # ---- index
    def _load(self) -> dict[str, dict]:
        try:
            return json.loads((self.root / INDEX_NAME).read_text())
        except (OSError, ValueError):
            return {}

    def _save(self, index: dict[str, dict]) -> None:
        atomic_write_text(self.root / INDEX_NAME, json.dumps(index, sort_keys=True))

    def _same_as_indexed(self, rel: str, entry: dict | None) -> bool:
        if entry is None:
            return False
        try:
            st = (self.root / rel).stat()
        except OSError:
            return False
        return st.st_size == entry["size"] and st.st_mtime_ns == entry["mtime_ns"]

    # ---- pull
    def pull(self, only: Callable[[str], bool] | None = None) -> tuple[int, int]:
        """Bring the folder up to the store's state (for files ``only`` accepts); returns (downloaded, deleted)."""
        with self.lock:
            t0 = time.perf_counter()
            remote = {n[len(self.prefix):]: o for n, o in self.objects.list(self.prefix).items()}
            if not remote and not self.root.exists():
                return 0, 0  # nothing there, nothing here: no folder made
            index = self._load()
            got = gone = 0
            for rel, obj in sorted(remote.items()):
                if not self._wanted(rel) or (only is not None and not only(rel)):
                    continue
                entry = index.get(rel)
                if entry is not None and entry["etag"] == obj.etag and self._same_as_indexed(rel, entry):
                    continue
                path = self.root / rel
                self.objects.get_file(self.prefix + rel, path)
                st = path.stat()
                index[rel] = {"etag": obj.etag, "size": st.st_size, "mtime_ns": st.st_mtime_ns}
                got += 1
            for rel in [r for r in index if r not in remote and (only is None or only(r))]:
                (self.root / rel).unlink(missing_ok=True)
                del index[rel]
                gone += 1
            if got or gone:
                self._save(index)
                log.info("pulled %s: %d files, %d deleted in %.2f s", self.prefix, got, gone, time.perf_counter() - t0)
            return got, gone

    # ---- push
    def _local_files(self) -> list[str]:
        out = []
        if not self.root.is_dir():
            return out
        for dirpath, dirnames, filenames in os.walk(self.root):
            base = Path(dirpath).relative_to(self.root).as_posix()
            dirnames[:] = [d for d in dirnames if not d.startswith(".") or d == MARKERS_DIR]
            for f in filenames:
                rel = f if base == "." else f"{base}/{f}"
                if self._wanted(rel):
                    out.append(rel)
        return out

    def push(self, only: Callable[[str], bool] | None = None) -> tuple[int, int]:
        """Upload what changed here since the last pull or push (markers last); returns (uploaded, deleted)."""
        with self.lock:
            index = self._load()
            files = [r for r in self._local_files() if only is None or only(r)]
            files.sort(key=lambda r: (r.startswith(MARKERS_DIR + "/"), r))
            sent = 0
            for rel in files:
                entry = index.get(rel)
                if self._same_as_indexed(rel, entry):
                    continue
                path = self.root / rel
                try:
                    st = path.stat()  # before the upload: a file that grows meanwhile goes up again next time
                    etag = self.objects.put_file(self.prefix + rel, path)
                except FileNotFoundError:  # removed while we walked
                    continue
                index[rel] = {"etag": etag, "size": st.st_size, "mtime_ns": st.st_mtime_ns}
                sent += 1
            present = set(files)
            gone = [r for r in index if r not in present and (only is None or only(r))
                    and not (self.root / r).exists()]
            if gone:
                self.objects.delete([self.prefix + r for r in gone])
                for r in gone:
                    del index[r]
            if sent or gone:
                self._save(index)
                log.debug("pushed %s: %d files, %d deleted", self.prefix, sent, len(gone))
            return sent, len(gone)
