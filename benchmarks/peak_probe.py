#!/usr/bin/env python
"""Measured peaks of an OpenCL device: memory bandwidth and single-precision arithmetic.

  * bandwidth: a streaming copy (b = a: 8 bytes per float moved) and a STREAM triad
    (a = b + s c: 12 bytes per float) over arrays far larger than the caches (--mib each);
  * arithmetic: FMA chains on float16 vectors, CHAINS independent chains per work-item so that the
    FMA latency is hidden (2 flops per lane per FMA).

Each figure is the best of --runs timed runs after one warm-up (a peak, not a typical value), with
the device, the sizes and the machine's load average.  --json PATH writes them for
benchmarks/perf_table.py (research/PERFORMANCE.md), which places every kernel against these peaks.

    python benchmarks/peak_probe.py [--device SPEC] [--mib 256] [--runs 5] [--json peaks.json]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

SRC = r"""
__kernel void copy(__global const float4 *a, __global float4 *b) {
    const size_t i = get_global_id(0);
    b[i] = a[i];
}
__kernel void triad(__global float4 *a, __global const float4 *b, __global const float4 *c, const float s) {
    const size_t i = get_global_id(0);
    a[i] = b[i] + s * c[i];
}
/* CHAINS independent FMA chains of float16, ITERS steps each: 2 * 16 * CHAINS * ITERS flops */
__kernel void fma_chains(__global float *out, const float m, const float k) {
    const size_t i = get_global_id(0);
    float16 x[CHAINS];
    for (int c = 0; c < CHAINS; c++) x[c] = (float16)((float)i * 1e-9f + (float)c);
    for (int it = 0; it < ITERS; it++)
        for (int c = 0; c < CHAINS; c++) x[c] = x[c] * m + k;   /* contracted to an FMA (builtin fma is a call on PoCL) */
    float16 s = x[0];
    for (int c = 1; c < CHAINS; c++) s += x[c];
    out[i] = s.s0 + s.s1 + s.s2 + s.s3 + s.s4 + s.s5 + s.s6 + s.s7
           + s.s8 + s.s9 + s.sa + s.sb + s.sc + s.sd + s.se + s.sf;
}
"""
CHAINS, ITERS = 8, 2048


def load_average() -> str:
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def best_ms(fn, runs):
    fn()
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1e3)
    return min(ts)


def measure(rt, mib: int = 256, runs: int = 5) -> dict:
    import pyopencl as cl
    import pyopencl.array as cla
    q = rt.queue
    prg = cl.Program(rt.ctx, SRC).build(options=[f"-DCHAINS={CHAINS}", f"-DITERS={ITERS}", "-cl-mad-enable"])
    k_copy, k_triad, k_fma = (cl.Kernel(prg, name) for name in ("copy", "triad", "fma_chains"))
    n = (mib << 20) // 4
    n4 = n // 4
    a = cla.zeros(q, n, np.float32)
    b = cla.to_device(q, np.ones(n, np.float32))
    c = cla.to_device(q, np.full(n, 2.0, np.float32))

    def copy():
        k_copy(q, (n4,), None, b.data, a.data)   # a = b
        q.finish()

    def triad():
        k_triad(q, (n4,), None, a.data, b.data, c.data, np.float32(3.0))
        q.finish()

    copy_ms = best_ms(copy, runs)
    triad_ms = best_ms(triad, runs)
    got = float(a[:4].get()[0])
    if got != 7.0:
        raise RuntimeError(f"triad computed {got}, expected 7")
    items = 64 * max(1, rt.compute_units) * 16
    out = cla.empty(q, items, np.float32)

    def fma():
        k_fma(q, (items,), None, out.data, np.float32(0.999), np.float32(1e-3))
        q.finish()

    fma_ms = best_ms(fma, runs)
    flops = 2.0 * 16 * CHAINS * ITERS * items
    return {
        "device": rt.describe(), "host": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "load_before": load_average(),
        "array_mib": mib,
        "copy_gbs": 2 * n * 4 / copy_ms / 1e6, "triad_gbs": 3 * n * 4 / triad_ms / 1e6,
        "fma_gflops": flops / fma_ms / 1e6,
        "copy_ms": copy_ms, "triad_ms": triad_ms, "fma_ms": fma_ms,
        "runs": runs,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--mib", type=int, default=256, help="size of each array (MiB)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--json", default=None, help="write the figures to this file")
    args = ap.parse_args(argv)
    from endowave_cl.runtime import get_runtime
    rt = get_runtime(args.device)
    r = measure(rt, args.mib, args.runs)
    r["load_after"] = load_average()
    print(f"device: {r['device']}")
    print(f"host: {r['host']}; load average before {r['load_before']}, after {r['load_after']}")
    print(f"sizes: {args.mib} MiB per array, FMA: {CHAINS} chains x {ITERS} steps of float16; "
          f"best of {args.runs} runs after one warm-up")
    print(f"  copy   {r['copy_gbs']:8.1f} GB/s   ({r['copy_ms']:.1f} ms)")
    print(f"  triad  {r['triad_gbs']:8.1f} GB/s   ({r['triad_ms']:.1f} ms)")
    print(f"  fma    {r['fma_gflops']:8.1f} GFLOP/s ({r['fma_ms']:.1f} ms)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(r, f, indent=1)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
