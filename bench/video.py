"""A generated survey video through ingest and SfM (issue 16, item 1): frames rendered along a transect
(``pipeline/synth/video.py``), encoded with PyAV, ingested as an upload (keyframes), then ``run_sfm``.

Prints one table row per stage: seconds, frames decoded, keyframes kept and why, registered keyframes and the
reprojection error. Long by nature (the ray caster renders ~0.4 s a frame at 160x120 on one core).

    python bench/video.py [--frames 160 --width 240 --height 180 --step 0.05] [--json]
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from collections import Counter
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=160)
    ap.add_argument("--width", type=int, default=240)
    ap.add_argument("--height", type=int, default=180)
    ap.add_argument("--fps", type=int, default=10)
    ap.add_argument("--step", type=float, default=0.05, help="metres flown per frame")
    ap.add_argument("--out", type=Path, default=None, help="keep the video and job here (default: a temp folder)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)

    import torch

    from pipeline.config import SfmConfig, SynthConfig
    from pipeline.ingest.intake import ingest
    from pipeline.job.layout import JobLayout
    from pipeline.sfm.recipe import run_sfm
    from pipeline.synth.video import VideoSynthConfig, generate_video

    torch.set_num_threads(1)  # the ray caster's torch ops: threads fight the other jobs on a shared machine
    root = args.out or Path(tempfile.mkdtemp(prefix="bench-video-"))
    (root / "upload").mkdir(parents=True, exist_ok=True)
    cfg = VideoSynthConfig(scene=SynthConfig(width=args.width, height=args.height, supersample=1, views=80),
                           frames=args.frames, fps=args.fps, step=args.step)
    rows = {}
    t = time.perf_counter()
    video = generate_video(cfg, root / "upload" / "transect.mp4")
    rows["render+encode"] = time.perf_counter() - t
    t = time.perf_counter()
    res = ingest(root / "upload", root / "job")
    rows["ingest"] = time.perf_counter() - t
    v = res.videos[0]
    t = time.perf_counter()
    summary = run_sfm(JobLayout(root / "job").images, root / "job" / "scene", SfmConfig())
    rows["sfm"] = time.perf_counter() - t
    out = {
        "frames": v["frames_decoded"], "size": f"{args.width}x{args.height}", "video_bytes": video.stat().st_size,
        "keyframes": len(v["kept"]), "why": dict(Counter(k["why"] for k in v["kept"])), "rejected": v["rejected"],
        "registered": summary.registered, "matcher": summary.matcher,
        "reproj_px": round(summary.mean_reproj_error_px, 3), "points": summary.num_points3D,
        "seconds": {k: round(s, 2) for k, s in rows.items()},
    }
    print(f"{'stage':<14}{'seconds':>9}")
    for k, s in rows.items():
        print(f"{k:<14}{s:>9.2f}")
    print(f"frames decoded {out['frames']}, keyframes kept {out['keyframes']} {out['why']}, rejected "
          f"{out['rejected']}; SfM ({out['matcher']}) registered {out['registered']}/{out['keyframes']}, "
          f"reprojection {out['reproj_px']} px, {out['points']} points")
    if args.json:
        print(json.dumps(out))


if __name__ == "__main__":
    main()
