"""SfM registration on the real surveys: registered / total, models, dropped frames and time per set.

    python bench/sfm_real.py [--sets aims-erub-mt81,...] [--out DIR] [--json FILE]

Sets: the four real surveys in /work/shared/data/real (``aims-*`` half-size frames, ``ruie-*``) and the RUIE
sets' first 12 frames in name order (``ruie-*:12``, copied to a temporary folder). One thread, seeded: the
recipe's defaults (``SfmConfig()``).
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
SETS = ("aims-erub-mt81", "aims-ugar-mt3a", "ruie-A188-A206", "ruie-B571-B597", "ruie-A188-A206:12",
        "ruie-B571-B597:12")  # fmt: skip


def stage_set(spec: str, tmp: Path) -> Path:
    """The image folder of ``spec`` (``name`` or ``name:N`` = its first N frames in name order)."""
    name, _, n = spec.partition(":")
    src = REAL / name / "images"
    if not n:
        return src
    dst = tmp / spec.replace(":", "_")
    dst.mkdir(parents=True)
    for p in sorted(src.iterdir())[: int(n)]:
        shutil.copy(p, dst / p.name)
    return dst


def main() -> None:
    from pipeline.sfm.config import SfmConfig
    from pipeline.sfm.recipe import SfmError, run_sfm

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default=",".join(SETS))
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    rows = []
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        for spec in args.sets.split(","):
            images = stage_set(spec, tmp)
            t = time.perf_counter()
            try:
                s = run_sfm(images, tmp / ("out_" + spec.replace(":", "_")), SfmConfig()).to_dict()
            except SfmError as e:
                s = {"error": str(e)}
            s["wall_s"] = time.perf_counter() - t
            s["set"] = spec
            rows.append(s)
            logging.info("RESULT %s", json.dumps(s))
    print("| set | registered / total | models | dropped | SfM s |")
    print("|---|---|---|---|---|")
    for s in rows:
        if "error" in s:
            print(f"| {s['set']} | error: {s['error'][:60]} | | | {s['wall_s']:.1f} |")
            continue
        print(f"| {s['set']} | {s['registered']} / {s['total']} | {1 + len(s['other_models'])} | "
              f"{', '.join(s['unregistered']) or '-'} | {s['wall_s']:.1f} |")  # fmt: skip
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
