"""The committed viewer bundle (``service/web/static/viewer/``) is the build of the committed sources
(``web/viewer/``): CI never runs npm, so a source change without ``npm run build`` would ship the old viewer."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SOURCES = REPO / "web" / "viewer"
BUILT = REPO / "service" / "web" / "static" / "viewer"


def _source_digest(files: list[str]) -> str:
    """web/viewer/after-build.mjs's digest: ``path\\0bytes\\0`` for each file, sorted by path."""
    h = hashlib.sha256()
    for f in sorted(files):
        h.update(f.encode() + b"\0")
        h.update((SOURCES / f).read_bytes())
        h.update(b"\0")
    return h.hexdigest()


def test_bundle_is_built_from_the_committed_sources():
    info = json.loads((BUILT / "BUILD.json").read_text())
    files = ["package.json", "package-lock.json"] + [f"src/{p.name}" for p in (SOURCES / "src").glob("*.js")]
    assert sorted(info["files"]) == sorted(files), "web/viewer/src changed its files: run `npm run build` there"
    assert info["sources_sha256"] == _source_digest(files), "web/viewer changed since the bundle: `npm run build`"
    lock = json.loads((SOURCES / "package-lock.json").read_text())["packages"]
    for name, version in info["versions"].items():
        assert lock[f"node_modules/{name}"]["version"] == version


def test_bundle_ships_its_licences_and_stays_small():
    js = (BUILT / "viewer.js").read_bytes()
    assert b"DualphysViewer" in js
    assert len(js) < 4_000_000  # 3.14 MB with three 0.187.0 and Spark 2.2.0 (web/viewer/README.md)
    licences = (BUILT / "THIRD_PARTY_LICENSES.txt").read_text()
    assert all(n in licences for n in ("three", "@sparkjsdev/spark", "fflate")) and licences.count("MIT") >= 3
