"""Benchmark of the project4d stage (forward and adjoint).

    python benchmarks/bench_project.py [--n 100000 --width 640 --height 512 --runs 7 --device SPEC]

Scene: Gaussians.random(n) (default SH degree 3, NT = 2, C = 6 with flow) seen by a camera at the
origin looking down +z.  Prints the median (and min) of --runs timed runs after two warm-up runs,
with the device and the sizes.  Each timed run includes the kernel launch and a queue.finish(),
not the upload of the parameters; beside it, the kernel's own time (OpenCL event profiling,
benchmarks/kernel_events.py), which moves less with the host's load.
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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=100000)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--device", default=None)
    args = ap.parse_args(argv)

    import pyopencl.array as cla
    from endowave_cl.camera import Camera
    from endowave_cl.gaussians import Gaussians, upload
    from endowave_cl.ops.project import project4d, project4d_bwd
    from endowave_cl.runtime import get_runtime

    rt = get_runtime(args.device)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from kernel_events import kernel_ms, profile_launches
    events = profile_launches(rt)   # before the first buffer: the pool is bound to the queue
    g = Gaussians.random(args.n, seed=0)
    cam = Camera(0.8 * args.width, 0.8 * args.width, args.width / 2, args.height / 2, args.width, args.height)
    params = upload(rt, g)
    rng = np.random.default_rng(0)
    grads_in = [cla.to_device(rt.queue, rng.standard_normal(s).astype(np.float32))
                for s in ((args.n, 2), (args.n, 3), (args.n,), (args.n, 6))]
    t, t_flow = 0.5, 0.55

    def fwd():
        p = project4d(rt, params, cam, t, t_flow)
        rt.finish()
        return p

    proj = fwd()

    def bwd():
        project4d_bwd(rt, params, cam, t, t_flow, proj, *grads_in)
        rt.finish()

    def timed(fn):
        for _ in range(2):
            fn()
        ts, ks = [], []
        for _ in range(args.runs):
            events.clear()
            t0 = time.perf_counter()
            fn()
            ts.append((time.perf_counter() - t0) * 1e3)
            ks.append(sum(kernel_ms(events).values()))
        return statistics.median(ts), min(ts), statistics.median(ks)

    f_med, f_min, f_k = timed(fwd)
    b_med, b_min, b_k = timed(bwd)
    visible = int((proj.radius.get() > 0).sum())
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs; "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"device: {rt.describe()}")
    print(f"sizes: N = {args.n} Gaussians ({visible} visible at t = {t}), SH degree {g.sh_degree}, "
          f"NT = {g.temporal_freqs}, C = 6, image {args.width} x {args.height}")
    print(f"project4d      forward : median {f_med:8.3f} ms   (min {f_min:.3f}, {args.runs} runs); kernel {f_k:.3f} ms")
    print(f"project4d_bwd  adjoint : median {b_med:8.3f} ms   (min {b_min:.3f}, {args.runs} runs); kernel {b_k:.3f} ms")


if __name__ == "__main__":
    main()
