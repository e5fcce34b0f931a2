"""Rasterizer benchmark: fwd+bwd time of the ``cpu`` backend against the ``torch`` reference, in the same run.

    python bench/raster.py [--json] [--repeats 5]

Scene: the cpu backend's measurement scene (``pipeline.splat.random_scene``), opacities uniform in
[0.05, 0.95], L1 loss against a random image, full backward to means, quats, scales, opacities, colours.
Projection is included in both backends' times; SH is not (the colours are plain RGB, as in those measurements).
Reference cases estimated above ``--ref-max-pairs`` (pixel, Gaussian) pairs are skipped (each would take tens of
seconds and several GB) and listed. Per-case peak RSS comes from VmHWM, reset before each case.
With ``--json`` the last stdout line is one JSON object. Other jobs on the machine inflate wall times (2 to 4x
measured on our shared 2-core machines); the process-CPU column is much less sensitive to them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time

SIZES = ((160, 120), (320, 240), (640, 480))
COUNTS = (5_000, 50_000, 200_000)


def _peak_rss_mib(reset: bool = False) -> float:
    """Peak RSS since the last reset (Linux VmHWM); resetting needs /proc/self/clear_refs."""
    if reset:
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")
        except OSError:
            pass
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _estimate_pixel_pairs(scene) -> float:
    """Expected (pixel, Gaussian) pairs with alpha >= 1/255: sum of the cut-off ellipses' areas (image-clipped)."""
    import torch

    from pipeline.splat.project import project_gaussians

    p = project_gaussians(
        scene.means, scene.quats, scene.scales, scene.opacities, scene.viewmats, scene.Ks, scene.width, scene.height
    )
    vis = (p.radii > 0).all(-1)
    a, b, c = p.conics[vis].double().unbind(-1)
    thr = torch.log(255.0 * scene.opacities.double())[None].expand_as(vis)[vis].clamp_min(0)
    area = math.pi * 2.0 * thr / torch.sqrt((a * c - b * b).clamp_min(1e-12))
    return float(area.clamp_max(scene.width * scene.height).sum())


def _time_backend(scene, backend: str, repeats: int, warmup: int) -> tuple[float, float, float, float]:
    """Median forward and backward wall seconds, min fwd+bwd wall seconds, median process CPU seconds (all
    threads) per fwd+bwd. With other jobs on the machine, wall time tracks our share of the cores; CPU seconds
    divided by the core count is what a quiet machine would show."""
    import torch

    from pipeline.splat.rasterize import rasterize

    target = torch.rand(1, scene.height, scene.width, 3, generator=torch.Generator().manual_seed(0))
    fwd, bwd, tot, cpu = [], [], [], []
    for i in range(warmup + repeats):
        params = [p.detach().clone().requires_grad_() for p in scene.params()]
        c0 = time.process_time()
        t0 = time.perf_counter()
        img, alpha, _ = rasterize(*params, scene.viewmats, scene.Ks, scene.width, scene.height, backend=backend)
        loss = (img - target).abs().mean()
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        c1 = time.process_time()
        if i >= warmup:
            fwd.append(t1 - t0)
            bwd.append(t2 - t1)
            tot.append(t2 - t0)
            cpu.append(c1 - c0)
    return statistics.median(fwd), statistics.median(bwd), min(tot), statistics.median(cpu)


def _breakdown(scene, repeats: int) -> dict[str, float]:
    """Wall seconds per stage of the cpu backend (kernels timed by wrapping them; the rest is torch glue)."""
    from pipeline.splat import _cpu_project_kernels as pk
    from pipeline.splat import _cpu_raster_kernels as rk

    stages = [(pk, "project_fwd"), (rk, "bin_and_pack"), (rk, "raster_fwd"), (rk, "raster_bwd"),
              (rk, "reduce_items"), (pk, "project_bwd")]  # fmt: skip
    spent = {name: 0.0 for _, name in stages}
    originals = {name: getattr(mod, name) for mod, name in stages}

    def timed(name, fn):
        def run(*args):
            t = time.perf_counter()
            out = fn(*args)
            spent[name] += time.perf_counter() - t
            return out

        return run

    for mod, name in stages:
        setattr(mod, name, timed(name, originals[name]))
    try:
        t = time.perf_counter()
        _time_backend(scene, "cpu", repeats, 0)
        total = time.perf_counter() - t
    finally:
        for mod, name in stages:
            setattr(mod, name, originals[name])
    out = {name: s / repeats for name, s in spent.items()}
    out["torch glue (autograd, casts, ED/cat, loss)"] = total / repeats - sum(out.values())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="last stdout line: a JSON object")
    parser.add_argument("--repeats", type=int, default=5, help="timed iterations of the cpu backend (median)")
    parser.add_argument("--ref-max-pairs", type=float, default=10e6, help="skip reference cases above this")
    args = parser.parse_args()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch/numba start their pools (notes, sec. 3)

    import numba
    import torch

    from pipeline.splat.random_scene import random_scene

    threads = {"numba": numba.get_num_threads(), "torch": torch.get_num_threads(), "cores": os.cpu_count()}
    print(f"threads: numba {threads['numba']}, torch {threads['torch']}, cores {threads['cores']}; "
          f"numba layer after first use below; OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}")  # fmt: skip
    warm = random_scene(1000, 64, 48)
    t = time.perf_counter()
    _time_backend(warm, "cpu", 1, 0)  # compile, or load the on-disk cache
    print(f"first cpu call (numba compile or cache load): {time.perf_counter() - t:.2f} s; "
          f"threading layer {numba.threading_layer()}")  # fmt: skip

    rows, skipped, result = [], [], {"threads": threads}
    header = f"{'N':>7} {'image':>8} {'pairs/px':>8} {'cpu fwd':>8} {'cpu bwd':>8} {'cpu tot':>8} {'cpu min':>8}" \
             f" {'cpu CPUs':>8} {'cpu MiB':>8} {'torch tot':>9} {'torch MiB':>9} {'speedup':>7}"  # fmt: skip
    print(header)
    for n in COUNTS:
        for w, h in SIZES:
            scene = random_scene(n, w, h, seed=0)
            pairs = _estimate_pixel_pairs(scene)
            _peak_rss_mib(reset=True)
            c_f, c_b, c_min, c_cpu = _time_backend(scene, "cpu", args.repeats, 1)
            c_rss = _peak_rss_mib()
            row = {"n": n, "width": w, "height": h, "pairs_per_px": pairs / (w * h), "cpu_fwd_s": c_f,
                   "cpu_bwd_s": c_b, "cpu_fwd_bwd_s": c_f + c_b, "cpu_fwd_bwd_min_s": c_min,
                   "cpu_fwd_bwd_process_cpu_s": c_cpu, "cpu_peak_rss_mib": c_rss}  # fmt: skip
            if pairs <= args.ref_max_pairs:
                _peak_rss_mib(reset=True)
                small = pairs < 3e6
                t_f, t_b, _, t_cpu = _time_backend(scene, "torch", 3 if small else 1, 1 if small else 0)
                row.update(torch_fwd_bwd_s=t_f + t_b, torch_fwd_bwd_process_cpu_s=t_cpu,
                           torch_peak_rss_mib=_peak_rss_mib())  # fmt: skip
                row["speedup"] = row["torch_fwd_bwd_s"] / row["cpu_fwd_bwd_s"]
            else:
                skipped.append(f"torch {n // 1000}k/{w}x{h} (~{pairs / 1e6:.0f}M pixel pairs)")
            rows.append(row)
            ref = (f"{row['torch_fwd_bwd_s']:9.3f} {row['torch_peak_rss_mib']:9.0f} {row['speedup']:6.1f}x"
                   if "speedup" in row else f"{'skipped':>9} {'':>9} {'':>7}")  # fmt: skip
            print(f"{n:7d} {w:>4}x{h:<3} {row['pairs_per_px']:8.0f} {c_f:8.3f} {c_b:8.3f} {c_f + c_b:8.3f} "
                  f"{c_min:8.3f} {c_cpu:8.3f} {c_rss:8.0f} {ref}", flush=True)  # fmt: skip
            if (n, w) == (50_000, 320):
                result["cpu_fwd_bwd_s_50k_320x240"] = c_f + c_b
                result["cpu_fwd_bwd_min_s_50k_320x240"] = c_min
                result["cpu_fwd_bwd_process_cpu_s_50k_320x240"] = c_cpu
                if "speedup" in row:
                    result["speedup_50k_320x240"] = row["speedup"]
                    result["torch_fwd_bwd_s_50k_320x240"] = row["torch_fwd_bwd_s"]
                result["breakdown_50k_320x240_s"] = _breakdown(scene, args.repeats)
    print("cpu fwd/bwd/tot: median wall s; cpu min: fastest fwd+bwd; cpu CPUs: process CPU seconds per fwd+bwd "
          "(all threads); MiB: peak RSS of the whole process during the case; speedup: torch tot / cpu tot")
    if skipped:
        print("skipped reference cases (would take tens of seconds and several GB each):", "; ".join(skipped))
    print("cpu backend at 50k / 320x240, wall seconds per stage:")
    for name, s in result["breakdown_50k_320x240_s"].items():
        print(f"  {name:42s} {s * 1e3:7.1f} ms")
    result["cases"] = rows
    result["skipped"] = skipped
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
