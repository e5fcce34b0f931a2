"""Restoring one 27 MP original (issue 14): seconds and peak memory per frame, file read and write included.

The frame (6000x4500, SIMPLE_RADIAL k = −0.1, render 400x300 with a tilted seabed, a rock step and open water;
``pipeline/restore/synthetic.py``) is generated into a JPEG by a child process, so the RSS high-water mark
(``resource.getrusage``) of this process is the restorer's alone. Also times the slow twins (exact lens map,
reference guided filter, reference dewater) on a small crop against the fast path on the same crop.

    python bench/restore.py [--width 6000 --height 4500] [--json]
    python bench/restore.py --filter    # the guided filter's radius / eps sweep (docs/DECISIONS.md)
    python bench/restore.py --compare DIR [--rounds 3]   # alternating rounds against the code in DIR (ratio)
    python bench/restore.py --cold [--width 640 --height 480 --photos 4 --bits 8]
        # first restores on an empty numba cache, and after pipeline.restore.warmup in an earlier process
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _write_frame(path: str, width: int, height: int) -> None:
    """Child process: write the synthetic photo as a JPEG (q95), band by band."""
    import OpenImageIO as oiio

    from pipeline.restore.synthetic import SynthFrame

    fr = SynthFrame(width, height, factor=width // 400, k1=-0.1)
    spec = oiio.ImageSpec(width, height, 3, oiio.UINT8)
    spec.attribute("Make", "BenchCam")
    spec.attribute("Compression", "jpeg:95")
    out = oiio.ImageOutput.create(path)
    out.open(path, spec)
    for y0 in range(0, height, 500):
        I, _, _ = fr.photo_rows(y0, min(height, y0 + 500))
        out.write_scanlines(y0, min(height, y0 + 500), 0, (I * 255 + 0.5).astype(np.uint8))
    out.close()


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def frame_bench(width: int, height: int) -> dict:
    from pipeline.restore.frame import RestoreOptions, restore_file
    from pipeline.restore.synthetic import SynthFrame

    fr = SynthFrame(width, height, factor=width // 400, k1=-0.1)
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "frame.jpg"
        p = mp.get_context("spawn").Process(target=_write_frame, args=(str(src), width, height))
        p.start()
        p.join()
        view = fr.render(prior=True)  # as the restore stage: the model's J as the prior, its weight calibrated
        _warm(tmp)
        rss0 = _rss_mb()
        t = time.perf_counter()
        res = restore_file(src, fr.lens, view, Path(tmp) / "out", RestoreOptions())
        seconds = time.perf_counter() - t
        return {"frame": f"{width}x{height}", "seconds": round(seconds, 2), "peak_rss_mb": round(_rss_mb()),
                "rss_before_mb": round(rss0), "surface_fraction": round(res.surface_pixels / (width * height), 3),
                "clipped": res.clipped, "output_mb": round(res.paths["J"].stat().st_size / 2**20, 1),
                "prior_weight": res.lam2}


def _frame_child(src: str, out: str, width: int, height: int, dump: bool) -> dict:
    """In a child process (whose PYTHONPATH picks the code): warm the kernels, restore ``src`` into ``out``, time
    it; with ``dump``, also save the restored photo and confidence of the same frame restored in memory
    (``J.npy``, ``confidence.npy``). The child of :func:`compare`."""
    import pipeline
    from pipeline.restore.frame import RestoreOptions, restore_array, restore_file
    from pipeline.restore.synthetic import SynthFrame

    fr = SynthFrame(width, height, factor=width // 400, k1=-0.1)
    view = fr.render(prior=True)
    _warm(out)
    t = time.perf_counter()
    restore_file(Path(src), fr.lens, view, Path(out), RestoreOptions())
    res = {"seconds": round(time.perf_counter() - t, 3), "peak_rss_mb": round(_rss_mb()),
           "code": str(Path(pipeline.__file__).parent.parent)}
    if dump:  # the pixels before encoding (a JPEG's quantisation spreads a 1/255 change over its 8x8 block)
        import OpenImageIO as oiio

        photo = oiio.ImageBuf(src).get_pixels(oiio.UINT8)[..., :3]
        arr = restore_array(photo, fr.lens, view)
        np.save(Path(out) / "J.npy", arr.J)
        np.save(Path(out) / "confidence.npy", arr.confidence)
    return res


def compare(other: str, width: int, height: int, rounds: int) -> dict:
    """Alternating rounds of the code in ``other`` (a tree holding ``pipeline/``, e.g. main's) and this tree on
    one generated frame, each restore in a fresh process; the ratio per round (other / this: > 1 is faster here)
    and how far the two trees' restored photo and confidence map differ (max |Δ| of 255)."""
    import OpenImageIO as oiio

    here = str(Path(__file__).resolve().parent.parent)
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "frame.jpg"
        p = mp.get_context("spawn").Process(target=_write_frame, args=(str(src), width, height))
        p.start()
        p.join()
        runs: dict[str, list] = {"other": [], "this": []}
        for k in range(rounds):
            for name, tree in (("other", other), ("this", here)):
                out = Path(tmp) / f"{name}{k}"
                env = dict(os.environ, PYTHONPATH=tree)
                r = subprocess.run([sys.executable, __file__, "--frame-child", str(src), str(out), str(width),
                                    str(height), str(int(k == 0))], env=env, check=True, capture_output=True,
                                   text=True)
                runs[name].append(json.loads(r.stdout.strip().splitlines()[-1]))
        diff = {}
        for what, name in (("J", "J.npy"), ("confidence", "confidence.npy"), ("J_jpeg", "frame.jpg"),
                           ("confidence_png", "frame_confidence.png")):
            if name.endswith(".npy"):
                a, b = (np.load(Path(tmp) / f"{t}0" / name).astype(np.float64) for t in ("other", "this"))
                if what == "confidence":
                    a, b = a * 255, b * 255
            else:
                a, b = (oiio.ImageBuf(str(Path(tmp) / f"{t}0" / name)).get_pixels(oiio.UINT8).astype(np.float64)
                        for t in ("other", "this"))
            d = np.abs(a - b)
            diff[what] = {"max": round(float(d.max()), 3), "share_over_1": float((d > 1).mean())}
        return {"frame": f"{width}x{height}", "other": other, "other_s": [x["seconds"] for x in runs["other"]],
                "this_s": [x["seconds"] for x in runs["this"]],
                "ratio": [round(a["seconds"] / b["seconds"], 2) for a, b in zip(runs["other"], runs["this"])],
                "other_rss_mb": [x["peak_rss_mb"] for x in runs["other"]],
                "this_rss_mb": [x["peak_rss_mb"] for x in runs["this"]],
                "diff_of_255": diff, "load_after": round(os.getloadavg()[0], 2)}


def _warm(tmp: str) -> None:
    """Compile or load every kernel once on a tiny frame (not timed)."""
    from pipeline.restore.frame import restore_array
    from pipeline.restore.synthetic import SynthFrame

    fr = SynthFrame(160, 120, factor=8)
    I, _, _ = fr.photo_rows(0, 120)
    restore_array((I * 255).astype(np.uint8), fr.lens, fr.render(prior=True))


def twin_bench() -> dict:
    """Fast path vs slow twins on a 200x150 crop (the reference guided filter is O(r²) per pixel in Python)."""
    from pipeline.restore.dewater import dewater, dewater_reference
    from pipeline.restore.guided import fast_guided_filter, guided_filter_reference
    from pipeline.restore.lens import LensGrid, exact_rays
    from pipeline.restore.synthetic import SynthFrame

    fr = SynthFrame(1600, 1200, factor=8, k1=-0.1)
    out = {}
    t = time.perf_counter()
    grid = LensGrid(fr.lens)
    xn, yn = grid.rays(0, 150)
    fast_lens = time.perf_counter() - t
    t = time.perf_counter()
    exact_rays(fr.lens, 0, 150)
    out["lens_1600x150"] = {"fast_s": round(fast_lens, 4), "slow_s": round(time.perf_counter() - t, 4)}
    rng = np.random.default_rng(0)
    g, p = rng.random((150, 200)).astype(np.float32), rng.random((150, 200)).astype(np.float32)
    fast_guided_filter(g, p, 4, 1e-4, 2)
    t = time.perf_counter()
    fast_guided_filter(g, p, 4, 1e-4, 2)
    f = time.perf_counter() - t
    t = time.perf_counter()
    guided_filter_reference(g, p, 4, 1e-4)
    out["guided_200x150"] = {"fast_s": round(f, 5), "slow_s": round(time.perf_counter() - t, 3)}
    from pipeline.restore.records import MediumMaps

    img = rng.random((150, 200, 3)).astype(np.float32)
    r = rng.uniform(0, 10, (150, 200)).astype(np.float32)
    s = np.ones((150, 200), bool)
    m = fr.medium
    dewater(img, r, s, m.k_A, m.k_B, m.B_inf)
    t = time.perf_counter()
    dewater(img, r, s, m.k_A, m.k_B, m.B_inf)
    f = time.perf_counter() - t
    t = time.perf_counter()
    dewater_reference(img, r, s, MediumMaps(m.k_A, m.k_B, m.B_inf))
    out["dewater_200x150"] = {"fast_s": round(f, 5), "slow_s": round(time.perf_counter() - t, 4)}
    for v in out.values():
        v["ratio"] = round(v["slow_s"] / max(v["fast_s"], 1e-9), 1)
    return out


def filter_sweep() -> list[dict]:
    """Depth error of plain bilinear vs the guided filter near the rock's edge and in flat textured areas."""
    from pipeline.restore._kernels import box_mean, luminance
    from pipeline.restore.guided import fast_guided_filter, fill_invalid
    from pipeline.restore.lens import LensGrid, exact_rays
    from pipeline.restore.sample import sample_maps
    from pipeline.restore.synthetic import SynthFrame

    rows = []
    for factor in (4, 8):
        fr = SynthFrame(1600, 1200, factor=factor, k1=-0.1)
        I, _, surf = fr.photo_rows(0, 1200)
        xn, yn = exact_rays(fr.lens, 0, 1200)
        ztrue, _, rock = fr.depth_at(xn, yn)
        rv = fr.render()
        maps = np.stack([fill_invalid(rv.depth[..., None], rv.alpha >= 0.5)[..., 0], rv.alpha], -1)
        gx, gy = LensGrid(fr.lens).rays(0, 1200)
        vals, inside = sample_maps(maps, gx, gy, rv.camera)
        valid = surf & inside & (vals[..., 1] >= 0.5)
        rk = box_mean(rock.astype(np.float32)[None], 2 * factor)[0]
        sk = box_mean(surf.astype(np.float32)[None], 2 * factor)[0]
        near, flat = valid & (rk > 0) & (rk < 1), valid & ((rk == 0) | (rk == 1)) & (sk == 1)
        L = luminance(I.astype(np.float32), 1.0)

        def row(name, z, factor=factor, near=near, flat=flat, ztrue=ztrue):
            e = np.abs(z - ztrue)
            rows.append({"factor": factor, "filter": name, "edge_mae": round(float(e[near].mean()), 4),
                         "edge_p95": round(float(np.percentile(e[near], 95)), 3),
                         "flat_mae": round(float(e[flat].mean()), 5)})

        row("bilinear", vals[..., 0])
        for rad in (factor // 2, factor):
            for eps in (1e-4, 1e-3, 1e-2):
                s = max(1, rad // 2)
                row(f"guided r{rad} s{s} eps{eps:g}", fast_guided_filter(L, vals[..., 0], rad, eps, s))
    return rows


def _child(what: str, folder: str) -> dict:
    """In a child process: restore every photo of ``folder`` as the restore stage does, or run the warm-up."""
    t0 = time.perf_counter()
    if what == "warmup":
        from pipeline.restore.warmup import compile_restore_kernels

        return {"cases": compile_restore_kernels(), "seconds": round(time.perf_counter() - t0, 2)}
    from pipeline.restore.synthetic import SynthFrame
    from pipeline.restore.views import restore_photo

    imported = time.perf_counter() - t0
    photos = sorted(p for p in Path(folder).iterdir() if p.stem.startswith("photo"))
    meta = json.loads((Path(folder) / "frame.json").read_text())
    fr = SynthFrame(meta["width"], meta["height"], factor=meta["width"] // 80, k1=-0.1)
    view = fr.render(prior=True)
    seconds = []
    for src in photos:
        t = time.perf_counter()
        restore_photo(src, Path(folder) / "restored", Path(folder) / "confidence_maps", fr.lens, view, max_gain=8.0,
                      fmt="auto", space="srgb")
        seconds.append(round(time.perf_counter() - t, 2))
    return {"import_s": round(imported, 2), "photo_s": seconds}


def cold_start(width: int, height: int, photos: int, bits: int) -> dict:
    """The restore of ``photos`` photos (8-bit JPEG or 16-bit PNG, render 80 px wide) in a fresh process on an empty
    numba cache (``NUMBA_CACHE_DIR`` a new folder), then: the warm-up in a fresh process on another empty cache,
    the same restore in a new process on that cache, and the warm-up again (it only loads)."""
    from pipeline.restore.synthetic import SynthFrame
    from pipeline.scene.images import write_image

    fr = SynthFrame(width, height, factor=width // 80, k1=-0.1)
    I, _, _ = fr.photo_rows(0, height)
    out = {"frame": f"{width}x{height} {bits}-bit x {photos}"}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp) / "photos"
        work.mkdir()
        (work / "frame.json").write_text(json.dumps({"width": width, "height": height}))
        top, dtype, ext = (255, np.uint8, ".jpg") if bits == 8 else (65535, np.uint16, ".png")
        for k in range(photos):
            write_image(work / f"photo{k}{ext}", (I * top + 0.5).astype(dtype))

        def child(what: str, cache: str) -> dict:
            env = dict(os.environ, NUMBA_CACHE_DIR=str(Path(tmp) / cache))
            t = time.perf_counter()
            r = subprocess.run([sys.executable, __file__, "--child", what, str(work)], env=env, check=True,
                               capture_output=True, text=True)
            return {**json.loads(r.stdout.strip().splitlines()[-1]), "process_s": round(time.perf_counter() - t, 1)}

        out["restore_empty_cache"] = child("restore", "empty")
        out["warmup_empty_cache"] = child("warmup", "warmed")
        out["restore_after_warmup"] = child("restore", "warmed")
        out["warmup_filled_cache"] = child("warmup", "warmed")
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--width", type=int, help="default 6000 (--cold: 640)")
    ap.add_argument("--height", type=int, help="default 4500 (--cold: 480)")
    ap.add_argument("--filter", action="store_true")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--cold", action="store_true")
    ap.add_argument("--photos", type=int, default=4)
    ap.add_argument("--bits", type=int, default=8, choices=(8, 16))
    ap.add_argument("--compare", metavar="DIR", help="alternate rounds against the code in DIR (holds pipeline/)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--frame-child", nargs=5, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(_child(*a.child)))
        return
    if a.frame_child:
        src, out, w, h, dump = a.frame_child
        print(json.dumps(_frame_child(src, out, int(w), int(h), dump == "1")))
        return
    if a.compare:
        print(json.dumps(compare(a.compare, a.width or 6000, a.height or 4500, a.rounds), indent=None if a.json
                         else 2))
        return
    if a.cold:
        res = cold_start(a.width or 640, a.height or 480, a.photos, a.bits)
        print(json.dumps(res, indent=None if a.json else 2))
    elif a.filter:
        res = filter_sweep()
        for r in res:
            print(r)
    else:
        res = {"frame": frame_bench(a.width or 6000, a.height or 4500), "twins": twin_bench()}
        print(json.dumps(res, indent=None if a.json else 2))
    if a.json and a.filter:
        print(json.dumps(res))


if __name__ == "__main__":
    main()
