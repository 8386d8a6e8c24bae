"""Benchmark of the OpenCL radix sort and of bin_and_sort.

Prints the device, the sizes and the median wall time (ms, after warm-up, queue finished) of
  * radix_sort_pairs on 1M and 4M random (uint64 key, int32 value) pairs sorted on 44 bits
    (tile ids of a 640 x 512 frame above 32 depth bits), next to numpy's stable argsort of the
    same keys (plus the gather of values) in the same run;
  * bin_and_sort end to end for 100k Gaussians with random rects of 1-3 tiles per side on a
    40 x 32 tile grid (640 x 512 pixels).

Each size uses the device's default configuration for that many keys (ops/sort.py default_config:
on a GPU it depends on the count); the flags lay their values over it.

    python benchmarks/bench_sort.py [--device SPEC] [--repeat 7] [--sizes 1000000 4000000]
                               [--radix-bits 8 --wg 16 --items-max 16384 --groups-per-cu 8]
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

from endowave_cl.ops.binning import bin_and_sort  # noqa: E402
from endowave_cl.ops.sort import SortConfig, default_config, radix_sort_pairs  # noqa: E402
from endowave_cl.runtime import get_runtime  # noqa: E402

SORT_BITS = 44  # 32 depth bits + 12 tile-id bits (sizes of the task's 640 x 512 frame)


def median_ms(fn, repeat, warmup=2):
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def random_keys(rng, n, n_tiles=1280):
    tiles = rng.integers(0, n_tiles, n).astype(np.uint64)
    depth = rng.uniform(0.1, 10.0, n).astype(np.float32).view(np.uint32).astype(np.uint64)
    return (tiles << np.uint64(32)) | depth


def random_scene(rng, n, tiles_x, tiles_y):
    x0 = rng.integers(0, tiles_x, n)
    y0 = rng.integers(0, tiles_y, n)
    x1 = np.minimum(x0 + rng.integers(1, 4, n), tiles_x)
    y1 = np.minimum(y0 + rng.integers(1, 4, n), tiles_y)
    rect = np.stack([x0, y0, x1, y1], 1).astype(np.int32)
    tiles_touched = ((x1 - x0) * (y1 - y0)).astype(np.int32)
    radius = np.full(n, 20, np.int32)
    depth = rng.uniform(0.1, 10.0, n).astype(np.float32)
    return rect, depth, radius, tiles_touched


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1_000_000, 4_000_000])
    ap.add_argument("--radix-bits", type=int, default=None)
    ap.add_argument("--wg", type=int, default=None)
    ap.add_argument("--items-min", type=int, default=None)
    ap.add_argument("--items-max", type=int, default=None)
    ap.add_argument("--groups-per-cu", type=int, default=None)
    ap.add_argument("--no-numpy", action="store_true")
    ap.add_argument("--no-binning", action="store_true")
    a = ap.parse_args(argv)

    rt = get_runtime(a.device)
    q = rt.queue
    flags = (a.radix_bits, a.wg, a.items_min, a.items_max, a.groups_per_cu)

    def config_for(n):
        """The device's default for n keys (the sort's own choice) with the flags given laid over it."""
        base = default_config(rt, n)
        if not any(flags):
            return base
        return SortConfig(radix_bits=a.radix_bits or base.radix_bits, wg=a.wg or base.wg,
                          items_min=a.items_min or base.items_min, items_max=a.items_max or base.items_max,
                          groups_per_cu=a.groups_per_cu or base.groups_per_cu)

    print(f"device: {rt.describe()}")
    print(f"sort config: {'the flags over ' if any(flags) else ''}the device's default for each size; "
          f"median of {a.repeat} runs after 2 warm-up runs")
    print(f"host load average (1 min) at start: {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    rng = np.random.default_rng(0)

    for n in a.sizes:
        keys = random_keys(rng, n)
        vals = np.arange(n, dtype=np.int32)
        dk, dv = cla.to_device(q, keys), cla.to_device(q, vals)

        cfg = config_for(n)

        def run():
            radix_sort_pairs(rt, dk, dv, SORT_BITS, cfg)
            q.finish()

        ms = median_ms(run, a.repeat)
        line = (f"radix_sort_pairs n={n:>9,d} bits={SORT_BITS}: {ms:8.2f} ms "
                f"({n / ms / 1e3:6.1f} Mkeys/s; {cfg})")
        if not a.no_numpy:
            def np_sort():
                order = np.argsort(keys, kind="stable")
                return keys[order], vals[order]
            line += f"   numpy argsort(stable)+gather: {median_ms(np_sort, max(3, a.repeat // 2), 1):8.2f} ms"
        print(line, flush=True)

    if not a.no_binning:
        n_g, tiles_x, tiles_y = 100_000, 40, 32
        rect, depth, radius, tt = random_scene(rng, n_g, tiles_x, tiles_y)
        dev = [cla.to_device(q, x) for x in (rect, depth, radius, tt)]
        m = int(tt.sum())
        cfg = config_for(m)

        def run_bin():
            bin_and_sort(rt, *dev, tiles_x * 16, tiles_y * 16, sort_config=cfg)
            q.finish()

        ms = median_ms(run_bin, a.repeat)
        print(f"bin_and_sort {n_g:,d} Gaussians, 1-3 tiles per side, {tiles_x}x{tiles_y} tiles "
              f"({tiles_x * 16}x{tiles_y * 16} px), M={m:,d} entries: {ms:8.2f} ms ({cfg})")


if __name__ == "__main__":
    main()
