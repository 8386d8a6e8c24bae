#!/usr/bin/env python
"""Benchmark the OpenCL renderer: per-stage forward times, FPS, backward, and the torch reference.

N 4D Gaussians (default 100,000) lie on a tissue-like surface that fills a 640x512 view, with
scales such that an average pixel is covered by tens of Gaussians. Prints the median of
--runs timed runs after --warmup runs, the device and the sizes, then renders the same frame with
the dense torch reference compositor once and prints the speed ratio.

    python benchmarks/bench_render.py [--n 100000] [--width 640] [--height 512] [--runs 7] [--device pocl]
"""
from __future__ import annotations

import argparse
import os
import platform
import resource
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from endowave_cl.camera import Camera  # noqa: E402
from endowave_cl.gaussians import Gaussians, num_sh_bases, upload  # noqa: E402
from endowave_cl.render import render, render_backward  # noqa: E402
from endowave_cl.runtime import get_runtime  # noqa: E402

FOCAL = 569.47  # EndoNeRF's focal length at 640x512


def tissue_scene(n: int, width: int, height: int, sigma_px: float, seed: int = 0,
                 sh_degree: int = 3) -> Gaussians:
    """Gaussians on a wavy surface 3.5-4.5 units in front of an identity camera, filling the view,
    with view-dependent colour of degree sh_degree (training with a fixed camera uses 1: sh_degree
    -1 in train/config.py)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-0.05 * width, 1.05 * width, n)
    v = rng.uniform(-0.05 * height, 1.05 * height, n)
    z = 4.0 + 0.3 * np.sin(u / 70.0) * np.cos(v / 55.0) + 0.05 * rng.standard_normal(n)
    x = (u - width / 2) / FOCAL * z
    y = (v - height / 2) / FOCAL * z
    t = rng.uniform(0, 1, n)
    means = np.stack([x, y, z, t], 1)
    s_world = sigma_px * z / FOCAL
    scales = np.log(np.stack([s_world * rng.uniform(0.6, 1.4, n), s_world * rng.uniform(0.6, 1.4, n),
                              0.3 * s_world, np.full(n, 0.3)], 1))
    K = num_sh_bases(sh_degree)
    sh = np.zeros((n, 3, K, 3))
    sh[:, 0, 0, :] = rng.uniform(-1, 1, (n, 3))
    sh[:, :, 1:, :] = 0.05 * rng.standard_normal((n, 3, K - 1, 3))
    ql = np.tile([1.0, 0, 0, 0], (n, 1)) + 0.2 * rng.standard_normal((n, 4))
    qr = np.tile([1.0, 0, 0, 0], (n, 1)) + 0.05 * rng.standard_normal((n, 4))
    return Gaussians(means, scales, ql, qr, rng.uniform(-1, 2, n), sh, rng.uniform(-np.pi, np.pi, (n, 3)))


def cpu_s() -> float:
    """CPU seconds (user + system) of this process, all threads (the OpenCL CPU driver's too)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def median_ms(fn, runs, warmup, cpu=None):
    """Median wall ms of fn over runs after warmup; with a list cpu, the median CPU ms per run is
    appended to it (on a loaded machine the CPU time moves much less than the wall time)."""
    for _ in range(warmup):
        fn()
    ts, cs = [], []
    for _ in range(runs):
        c0, t0 = cpu_s(), time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1e3)
        cs.append((cpu_s() - c0) * 1e3)
    if cpu is not None:
        cpu.append(statistics.median(cs))
    return statistics.median(ts)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--sigma-px", type=float, default=2.5, help="mean screen-space std of a Gaussian (pixels)")
    ap.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3), default=3,
                    help="SH degree of the Gaussians' colour (default 3; training with a fixed camera uses 1)")
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--device", default=None)
    ap.add_argument("--no-reference", action="store_true", help="skip the torch reference timing")
    ap.add_argument("--adjoint-mode", choices=("auto", "deterministic", "atomic"), default="auto",
                    help="rasterize adjoint accumulation (auto: deterministic on CPU devices)")
    args = ap.parse_args(argv)

    rt = get_runtime(args.device)
    cam = Camera(FOCAL * args.width / 640, FOCAL * args.width / 640, args.width / 2, args.height / 2,
                 args.width, args.height)
    g = tissue_scene(args.n, args.width, args.height, args.sigma_px, sh_degree=args.sh_degree)
    params = upload(rt, g)
    t, t2 = 0.5, 0.55

    print(f"device: {rt.describe()}")
    print(f"host: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; load average "
          f"{' '.join(f'{v:.2f}' for v in os.getloadavg())} (1, 5, 15 min)")
    print(f"sizes: N={args.n} Gaussians (SH degree {args.sh_degree}), {args.width}x{args.height}, C=6 channels, "
          f"median of {args.runs} runs after {args.warmup} warm-up")

    # per-stage (with a sync after each stage)
    stages = {}
    for i in range(args.warmup + args.runs):
        out = render(rt, params, cam, t, t2, timed=True)
        if i >= args.warmup:
            for k, v in out.timings.items():
                stages.setdefault(k, []).append(v)
    n_vis = int((out.proj.radius.get() > 0).sum())
    print(f"visible Gaussians: {n_vis}, tile-Gaussian pairs: {out.n_isect}, "
          f"mean pairs per tile: {out.n_isect / max(1, out.tile_ranges.shape[0]):.1f}")
    alpha = out.alpha.get()
    print(f"mean alpha: {alpha.mean():.3f}")
    for k in ("project", "bin_sort", "rasterize", "total"):
        print(f"  forward {k:10s} {statistics.median(stages[k]):8.2f} ms")

    def fwd():
        render(rt, params, cam, t, t2)
        rt.queue.finish()
    fwd_cpu = []
    fwd_ms = median_ms(fwd, args.runs, args.warmup, fwd_cpu)
    print(f"forward (no per-stage syncs): {fwd_ms:.2f} ms = {1000 / fwd_ms:.1f} FPS; CPU time {fwd_cpu[0]:.1f} ms "
          f"(all threads; / {os.cpu_count()} cores = {fwd_cpu[0] / (os.cpu_count() or 1):.1f} ms)")

    # backward
    import pyopencl.array as cla
    rng = np.random.default_rng(1)
    v_feat = cla.to_device(rt.queue, rng.standard_normal((args.height, args.width, 6)).astype(np.float32) * 1e-3)
    bwd_stage = {}
    det = {"auto": None, "deterministic": True, "atomic": False}[args.adjoint_mode]
    print(f"adjoint mode: {args.adjoint_mode}")

    def bwd():
        o = render(rt, params, cam, t, t2)
        rt.queue.finish()
        t0 = time.perf_counter()
        render_backward(rt, params, o, v_feat, timed=True, deterministic=det)
        rt.queue.finish()
        bwd_stage.setdefault("rasterize_bwd", []).append(o.timings["rasterize_bwd"])
        bwd_stage.setdefault("project_bwd", []).append(o.timings["project_bwd"])
        bwd_stage.setdefault("backward", []).append((time.perf_counter() - t0) * 1e3)
    both_cpu = []
    median_ms(bwd, args.runs, args.warmup, both_cpu)
    for k in ("rasterize_bwd", "project_bwd", "backward"):
        print(f"  backward {k:13s} {statistics.median(bwd_stage[k][args.warmup:]):8.2f} ms")
    b = statistics.median(bwd_stage["backward"][args.warmup:])
    print(f"forward + backward: {fwd_ms + b:.2f} ms; backward / forward = {b / fwd_ms:.2f}; load average now "
          f"{' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    bcpu = both_cpu[0] - fwd_cpu[0]
    print(f"CPU time (all threads): forward {fwd_cpu[0]:.1f} ms, backward {bcpu:.1f} ms, forward + backward "
          f"{both_cpu[0]:.1f} ms; backward / forward = {bcpu / fwd_cpu[0]:.2f}")

    if not args.no_reference:
        import torch

        from endowave_cl.reference.rasterize import rasterize_dense_ref
        p = out.proj
        tens = [torch.from_numpy(a.get()) for a in (p.means2d, p.conic, p.opac, p.features, p.depth, p.rect)]
        torch.set_num_threads(os.cpu_count() or 1)
        t0 = time.perf_counter()
        with torch.no_grad():
            ref_out, ref_alpha, _, _ = rasterize_dense_ref(*tens, args.width, args.height)
        ref_ms = (time.perf_counter() - t0) * 1e3
        kern_ms = statistics.median(stages["rasterize"])
        err = float(np.abs(ref_out.numpy() - out.features.get()).max())
        print(f"torch dense reference compositor: {ref_ms:.0f} ms (one run) vs OpenCL rasterize {kern_ms:.2f} ms: "
              f"{ref_ms / kern_ms:.1f}x; vs the whole OpenCL forward {ref_ms / fwd_ms:.1f}x; max |diff| {err:.2e}")


if __name__ == "__main__":
    main()
