"""The truth-free colour-consistency score (pipeline/evaluate/consistency.py) on generated scenes: restorations
formed from each scene's true water (J = (I − B)/A at the true depth, no training), with β halved and doubled,
and the photos themselves. Prints one row per scene: the share of the photos' change with distance that each
leaves (lower is better; the true water must be lowest). Scenes are folders written by ``dualphys synth``.

    python bench/consistency.py SCENE [SCENE ...] [--json]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from pipeline.restore.consistency_truth import UNCAPPED, scene_consistency

log = logging.getLogger("bench.consistency")


def _share(res: dict) -> str:
    """The share, or why there is none in a word (a channel saturated or flattened: "refused")."""
    return f"{res['share']:.3f}" if res["defined"] else "refused"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--max-gain", type=float, default=UNCAPPED, help="the restorations' gain cap (default: none)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
    rows = {}
    log.info("%-28s %7s %6s %9s %9s %8s %8s  %s", "scene", "points", "range", "photo", "true", "β/2", "2β",
             "per channel (photo | true)")
    for root in args.scenes:
        res = scene_consistency(root, max_gain=args.max_gain)
        rows[str(root)] = res
        p, t = res["photo"], res["x1"]
        log.info("%-28s %7d %5.2fx %9.3f %9s %8s %8s  %s | %s", root.name, p["n_points"], p["range_ratio"],
                 p["photo_score"], *(_share(res[k]) for k in ("x1", "x0.5", "x2")),
                 [round(x, 3) for x in p["photo"]["score"]],
                 [round(x, 3) for x in t["restored"]["score"]] if t["restored"] else None)
    if args.json:
        sys.stdout.write(json.dumps(rows) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
