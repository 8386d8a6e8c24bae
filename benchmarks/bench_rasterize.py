"""Benchmark of the tile rasterizer (forward and adjoint) on a synthetic scene.

    python benchmarks/bench_rasterize.py [--width 640 --height 512 --n 100000 --runs 7 --check]
                                    [--variants scalar,vector]

Synthetic inputs: N screen-space Gaussians spread over the view (2D standard deviations 1..7 px,
i.e. 3-sigma radii of a few to ~20 px), opacities 0.05..0.6, C = 6 features; the sorted list is
built with the numpy binning reference.  Prints the median of --runs timed runs after one warm-up,
with the device and the sizes, for each kernel variant of --variants in the same run (set through
$ENDOWAVE_RASTER_VARIANT, see endowave_cl/ops/rasterize.py; default: both).  --check compares the forward output with the dense torch
reference (tens of seconds) and the run time of that reference.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pyopencl.array as cla  # noqa: E402

from endowave_cl.ops.rasterize import ENV_VARIANT, VARIANTS, raster_variant, rasterize, rasterize_bwd  # noqa: E402
from endowave_cl.reference.binning import (bin_gaussians_ref, sort_pairs_ref, tile_grid,  # noqa: E402
                                           tile_ranges_ref)
from endowave_cl.runtime import get_runtime  # noqa: E402
from endowave_cl.layout import TILE  # noqa: E402


def synthetic_scene(n, width, height, C=6, seed=0, sigma=(0.5, 6.5), opac=(0.05, 0.6)):
    rng = np.random.default_rng(seed)
    means2d = np.stack([rng.uniform(0, width, n), rng.uniform(0, height, n)], 1)
    s = np.exp(rng.uniform(np.log(sigma[0]), np.log(sigma[1]), (n, 2)))  # log-uniform: many small
    th = rng.uniform(0, np.pi, n)
    c, si = np.cos(th), np.sin(th)
    # cov = R diag(s^2) R^T + 0.3 I (the EWA low-pass), written out for 2 x 2
    cxx = c * c * s[:, 0] ** 2 + si * si * s[:, 1] ** 2 + 0.3
    cyy = si * si * s[:, 0] ** 2 + c * c * s[:, 1] ** 2 + 0.3
    cxy = c * si * (s[:, 0] ** 2 - s[:, 1] ** 2)
    det = cxx * cyy - cxy * cxy
    conic = np.stack([cyy / det, -cxy / det, cxx / det], 1)
    mid = 0.5 * (cxx + cyy)
    lam = mid + np.sqrt(np.maximum(0.1, mid * mid - det))
    radius = np.ceil(3 * np.sqrt(lam)).astype(np.int32)
    tiles_x, tiles_y = tile_grid(width, height)
    rect = np.stack([np.floor((means2d[:, 0] - radius) / TILE), np.floor((means2d[:, 1] - radius) / TILE),
                     np.ceil((means2d[:, 0] + radius) / TILE), np.ceil((means2d[:, 1] + radius) / TILE)], 1)
    rect = np.clip(rect, 0, [tiles_x, tiles_y, tiles_x, tiles_y]).astype(np.int32)
    depth = rng.uniform(0.5, 5.0, n).astype(np.float32)
    keys, vals = bin_gaussians_ref(rect, depth, radius, tiles_x)
    skeys, svals = sort_pairs_ref(keys, vals)
    return dict(means2d=means2d.astype(np.float32), conic=conic.astype(np.float32),
                opac=rng.uniform(*opac, n).astype(np.float32),
                features=rng.uniform(0, 1, (n, C)).astype(np.float32), depth=depth, rect=rect,
                sorted_values=svals.astype(np.int32), tile_ranges=tile_ranges_ref(skeys, tiles_x * tiles_y))


CPU_TIMES = {}


def timed(rt, fn, runs, name=None):
    """(median, min) wall seconds; also records the median process CPU seconds (all threads,
    PoCL's included) under name: on a shared machine that is steadier than wall time."""
    fn()
    rt.queue.finish()
    ts, cs = [], []
    for _ in range(runs):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        rt.queue.finish()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    if name:
        CPU_TIMES[name] = statistics.median(cs)
    return statistics.median(ts), min(ts)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--device", default=None)
    ap.add_argument("--check", action="store_true", help="compare with the dense torch reference")
    ap.add_argument("--variants", default=",".join(VARIANTS),
                    help="comma-separated rasterizer variants to time (scalar, vector)")
    a = ap.parse_args(argv)
    variants = [v.strip() for v in a.variants.split(",") if v.strip()]

    rt = get_runtime(a.device)
    W, H = a.width, a.height
    t0 = time.perf_counter()
    sc = synthetic_scene(a.n, W, H)
    t_build = time.perf_counter() - t0
    ref = None
    if a.check:   # before any kernel runs: PoCL's worker threads would compete with torch's
        from endowave_cl.reference.rasterize import rasterize_dense_ref
        import torch
        t0 = time.perf_counter()
        with torch.no_grad():
            ref = rasterize_dense_ref(sc["means2d"], sc["conic"], sc["opac"], sc["features"],
                                      sc["depth"], sc["rect"], W, H)
        ref = (*ref, time.perf_counter() - t0)
    q = rt.queue
    dev = [cla.to_device(q, sc[k]) for k in ("means2d", "conic", "opac", "features", "sorted_values",
                                             "tile_ranges")]
    res = rasterize(rt, *dev, W, H)
    last = res.last.get()
    M = len(sc["sorted_values"])
    lens = sc["tile_ranges"][:, 1] - sc["tile_ranges"][:, 0]
    print(f"device: {rt.describe()}; default variant here: {raster_variant(rt)}")
    print(f"image {W}x{H}, N={a.n} Gaussians, C=6, M={M} tile entries "
          f"(per tile: mean {lens.mean():.0f}, max {lens.max()}), "
          f"last (one past the last contributor): mean {last.mean():.1f}; "
          f"mean final alpha {res.alpha.get().mean():.3f}; scene built in {t_build:.1f} s")

    rng = np.random.default_rng(1)
    v_out = cla.to_device(q, rng.standard_normal((H, W, 6)).astype(np.float32))
    v_alpha = cla.to_device(q, rng.standard_normal((H, W)).astype(np.float32))
    det = (cla.to_device(q, sc["rect"]), cla.to_device(q, sc["depth"]))
    saved = os.environ.get(ENV_VARIANT)
    for variant in variants:
        os.environ[ENV_VARIANT] = variant
        assert raster_variant(rt) == variant
        vres = rasterize(rt, *dev, W, H)
        same = (np.array_equal(vres.last.get(), last)
                and np.abs(vres.out.get() - res.out.get()).max() <= 1e-4)
        fwd_med, fwd_min = timed(rt, lambda: rasterize(rt, *dev, W, H), a.runs, f"{variant} forward")
        print(f"[{variant}] rasterize forward:  median {fwd_med * 1e3:.1f} ms  (min {fwd_min * 1e3:.1f} ms, "
              f"{a.runs} runs); same result as the default variant: {same}")
        bwd_med, bwd_min = timed(rt, lambda: rasterize_bwd(rt, *dev, W, H, vres, v_out, v_alpha), a.runs,
                                 f"{variant} backward")
        print(f"[{variant}] rasterize backward: median {bwd_med * 1e3:.1f} ms  (min {bwd_min * 1e3:.1f} ms, "
              f"{a.runs} runs), {bwd_med / fwd_med:.2f}x the forward")
        det_med, det_min = timed(rt, lambda: rasterize_bwd(rt, *dev, W, H, vres, v_out, v_alpha,
                                                           deterministic=det),
                                 a.runs, f"{variant} backward deterministic")
        print(f"[{variant}] rasterize backward, deterministic mode: median {det_med * 1e3:.1f} ms  "
              f"(min {det_min * 1e3:.1f} ms)")
    if saved is None:
        os.environ.pop(ENV_VARIANT, None)
    else:
        os.environ[ENV_VARIANT] = saved

    print(f"load average now {os.getloadavg()[0]:.1f}; median process CPU time per run (all threads): "
          + "; ".join(f"{k} {v * 1e3:.0f} ms" for k, v in CPU_TIMES.items())
          + f"  (/ {rt.compute_units} compute units = the wall time on an idle machine, at best)")
    if ref is not None:
        out, alpha, T, lst, t_ref = ref
        diff = np.abs(res.out.get() - out.numpy()).max(-1)
        err, err999 = diff.max(), np.quantile(diff, 0.999)
        err_t = np.abs(res.T_final.get() - T.numpy()).max()
        same_last = (res.last.get() == lst.numpy()).mean()
        print(f"dense torch reference (float32): {t_ref:.1f} s; |out - ref|: max {err:.2e}, 99.9th percentile "
              f"{err999:.2e}; max |T_final - ref| = {err_t:.2e}; last equal on {100 * same_last:.3f}% of pixels "
              f"(isolated large differences are expected where an alpha lies within an ulp of 1/255 and "
              f"one side keeps the pair while the other skips it)")

if __name__ == "__main__":
    main()
