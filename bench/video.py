"""A generated survey video through ingest and SfM (issue 16, item 1): frames rendered along a transect
(``pipeline/synth/video.py``), encoded with PyAV, ingested as an upload (keyframes), then ``run_sfm``.

Prints one table row per stage: seconds, frames decoded, keyframes kept and why, registered keyframes and the
reprojection error. Long by nature (the ray caster renders ~0.4 s a frame at 160x120 on one core).

    python bench/video.py [--frames 160 --width 240 --height 180 --step 0.05] [--json]
    python bench/video.py --decode 1920x1080 --frames 300   # ingest alone on a camera-size video: seconds and
                                                            # peak memory (VmHWM of a child process)
    python bench/video.py --truth --generate-only --out DIR   # DIR/scene/transect.mp4 with every frame's truth
                                                            # beside it, for `dualphys run DIR/scene/transect.mp4`
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing as mp
import resource
import tempfile
import time
from collections import Counter
from pathlib import Path


def _peak_mb() -> float:
    """This process's RSS high-water mark (VmHWM: starts afresh at exec, unlike ru_maxrss, which keeps the
    forking parent's)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _ingest_child(upload: str, job: str, q) -> None:
    """Child process: ingest alone, so its RSS high-water mark is the ingest's (plus imports)."""
    from pipeline.ingest.intake import ingest

    t = time.perf_counter()
    res = ingest(upload, job)
    q.put((time.perf_counter() - t, res.videos[0]["frames_decoded"], len(res.images),
           _peak_mb()))


def _imports_child(q) -> None:
    import av  # noqa: F401

    import pipeline.ingest.intake  # noqa: F401
    import pipeline.scene.images  # noqa: F401

    q.put(_peak_mb())


def decode_bench(size: str, frames: int, fps: int, root: Path) -> dict:
    """A panning video of ``size`` (a seeded texture, 0.4 % of the width per frame) through ingest, in a child."""
    import numpy as np

    from pipeline.synth.video import encode_video

    w, h = (int(v) for v in size.split("x"))
    rng = np.random.default_rng(0)
    step = max(1, w // 250)
    tex = rng.random((h // 8 + 1, (w + step * frames) // 8 + 2, 3))
    tex = (np.repeat(np.repeat(tex, 8, 0), 8, 1) * 255).astype(np.uint8)
    (root / "clip").mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    video = encode_video((tex[:h, i * step:i * step + w] for i in range(frames)), root / "clip" / "cam.mp4", fps)
    encode_s = time.perf_counter() - t
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_imports_child, args=(q,))
    p.start()
    base_mb = q.get()
    p.join()
    p = ctx.Process(target=_ingest_child, args=(str(root / "clip"), str(root / "job"), q))
    p.start()
    seconds, decoded, kept, peak_mb = q.get()
    p.join()
    return {"size": size, "frames": decoded, "video_mb": round(video.stat().st_size / 2**20, 1),
            "encode_s": round(encode_s, 1), "ingest_s": round(seconds, 2), "fps_decoded": round(decoded / seconds, 1),
            "keyframes": kept, "peak_rss_mb": round(peak_mb), "imports_rss_mb": round(base_mb),
            "one_frame_rgb_mb": round(w * h * 3 / 2**20, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=160)
    ap.add_argument("--width", type=int, default=240)
    ap.add_argument("--height", type=int, default=180)
    ap.add_argument("--fps", type=int, default=10)
    ap.add_argument("--step", type=float, default=0.05, help="metres flown per frame")
    ap.add_argument("--out", type=Path, default=None, help="keep the video and job here (default: a temp folder)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--decode", default=None, metavar="WxH", help="time ingest alone on a panning video this size")
    ap.add_argument("--truth", action="store_true",
                    help="write every frame's truth beside the video (OUT/scene/): a job on the video is scored")
    ap.add_argument("--generate-only", action="store_true", help="stop once the video is written")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if args.decode:
        out = decode_bench(args.decode, args.frames, args.fps,
                           args.out or Path(tempfile.mkdtemp(prefix="bench-decode-")))
        print(" ".join(f"{k}={v}" for k, v in out.items()))
        if args.json:
            print(json.dumps(out))
        return

    import torch

    from pipeline.config import SynthConfig
    from pipeline.ingest.intake import ingest
    from pipeline.job.layout import JobLayout
    from pipeline.sfm.config import SfmConfig
    from pipeline.sfm.recipe import run_sfm
    from pipeline.synth.video import VideoSynthConfig, generate_video

    torch.set_num_threads(1)  # the ray caster's torch ops: threads fight the other jobs on a shared machine
    root = args.out or Path(tempfile.mkdtemp(prefix="bench-video-"))
    folder = root / ("scene" if args.truth else "clip")  # the truth makes the video's folder a generated scene
    folder.mkdir(parents=True, exist_ok=True)
    cfg = VideoSynthConfig(scene=SynthConfig(width=args.width, height=args.height, supersample=1, views=80),
                           frames=args.frames, fps=args.fps, step=args.step)
    rows = {}
    t = time.perf_counter()
    video = generate_video(cfg, folder / "transect.mp4", truth=args.truth)
    rows["render+encode"] = time.perf_counter() - t
    if args.generate_only:
        print(f"wrote {video} ({video.stat().st_size} bytes) in {rows['render+encode']:.1f} s")
        return
    t = time.perf_counter()
    res = ingest(video, root / "job")  # the video alone: its folder may hold the truth's images
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
