#!/usr/bin/env python
"""Benchmark the rational-wavelet transform, its adjoint and the loss (OpenCL kernels), with the
pure-torch implementation in the same run for comparison.

    python benchmarks/bench_wavelet.py [--height 512 --width 640 --channels 3 --q 2 --levels 2 --runs 10]

Prints the median wall time (ms) of --runs runs after --warmup runs, per operation, and the device.
OpenCL timings include a queue.finish() so they cover the kernels, not just their enqueueing.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def bench(fn, runs, warmup):
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts), min(ts)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--channels", type=int, default=3)
    ap.add_argument("--q", type=int, default=None, help="default: WaveletConfig().q")
    ap.add_argument("--levels", type=int, default=2)
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--device", default=None, help="OpenCL device spec (see endowave-cl devices)")
    ap.add_argument("--no-torch", action="store_true")
    args = ap.parse_args(argv)

    import pyopencl.array as cla
    import torch
    from endowave_cl.runtime import get_runtime
    from endowave_cl.wavelet import ops
    from endowave_cl.reference.wavelet import decompose_ref, wavelet_loss_ref
    from endowave_cl.wavelet.config import WaveletConfig, wavelet_loss_and_grad

    cfg = WaveletConfig(levels=args.levels) if args.q is None else WaveletConfig(q=args.q, levels=args.levels)
    rt = get_runtime(args.device)
    H, W, C = args.height, args.width, args.channels
    rng = np.random.default_rng(0)
    r = rng.random((H, W, C)).astype(np.float32)
    t = rng.random((H, W, C)).astype(np.float32)
    m = (rng.random((H, W)) > 0.1).astype(np.float32)
    rd, td, md = (cla.to_device(rt.queue, a) for a in (r, t, m))
    coeffs = ops.decompose(rt, rd, cfg.q, cfg.levels)
    v_coeffs = [{b: v.copy() for b, v in lv.items()} for lv in coeffs]
    rt.finish()

    def cl_transform():
        ops.decompose(rt, rd, cfg.q, cfg.levels)
        rt.finish()

    def cl_adjoint():
        ops.decompose_bwd(rt, v_coeffs, (H, W, C), cfg.q)
        rt.finish()

    def cl_loss():
        wavelet_loss_and_grad(rt, rd, td, md, cfg)  # reads the loss back: synchronous
        rt.finish()

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs; "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"device: {rt.describe()}")
    print(f"host: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__} "
          f"({torch.get_num_threads()} threads)")
    print(f"image {H}x{W}x{C} (H x W x C), q={cfg.q} (a={cfg.a:.4g}), levels={cfg.levels}, "
          f"filter taps={2 * __import__('endowave_cl.wavelet.filters', fromlist=['x']).support_radius(cfg.q) + 1}, "
          f"median of {args.runs} runs after {args.warmup} warm-up")
    rows = [("opencl  transform (2-level decompose)", cl_transform),
            ("opencl  adjoint (decompose_bwd)", cl_adjoint),
            ("opencl  loss + gradient (wavelet_loss_and_grad, masked)", cl_loss)]
    if not args.no_torch:
        rr = torch.tensor(r, requires_grad=True)
        tt, mm = torch.tensor(t), torch.tensor(m)
        x = torch.tensor(r)

        def th_transform():
            with torch.no_grad():
                decompose_ref(x, cfg.q, cfg.levels)

        def th_loss():
            with torch.no_grad():
                wavelet_loss_ref(x, tt, mm, cfg)

        def th_loss_grad():
            rr.grad = None
            wavelet_loss_ref(rr, tt, mm, cfg).backward()

        rows += [("torch   transform (decompose_ref)", th_transform),
                 ("torch   loss forward", th_loss),
                 ("torch   loss + gradient (autograd)", th_loss_grad)]
    for name, fn in rows:
        med, best = bench(fn, args.runs, args.warmup)
        print(f"{name:58s} median {med:9.2f} ms   min {best:9.2f} ms")


if __name__ == "__main__":
    main()
