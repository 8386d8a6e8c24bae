#!/usr/bin/env python
"""Before / after of kernel files in one process: the same ops (this checkout's host code) on the
same inputs, with the kernels built from two cl/ directories, alternating run by run.

    python benchmarks/bench_kernels_ab.py --old /tmp/before/cl [--new cl] [--what adam,raster_bwd,...]
                                     [--runs 30] [--downscale 2] [--gaussians 100000]

On a shared machine whose load moves from one minute to the next (this project's 2-core VM: the
same command 15-40% apart between rounds), separate runs of old and new code cannot show a 5%
change.  Here every run of the old kernels is next to a run of the new ones (order ABBA ABBA ...),
and the figure is the median of the per-pair ratios new / old of each kernel's OpenCL event time
(and of the wall and CPU time of the whole op); the first results of both are compared bit for
bit.  The inputs are those of a real training step: a Trainer on the shared pulling frames (else
a synthetic scene) at --downscale, --gaussians new Gaussians, a few steps in, frame 7's render,
losses and gradients.

--what: adam (DeviceAdam.step), project (project4d), project_bwd (project4d_bwd with the SH gradient
as factors), raster (rasterize: prep + rasterize_vec), raster_bwd (the deterministic adjoint: the
kernel, entry_of, gather), losses (Trainer.losses_and_gradient: image terms, SSIM, wavelet).
--old-adam-sh-per-item N: the old adam.cl's Gaussians per work-item of the factored sh group (1
before the tenth pass; the host code launches for the new kernel's count otherwise).
The old directory must be launch-compatible with this checkout's host code (same kernel names and
arguments); its includes are its own (the build's -I).
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

SHARED_SCENE = Path(__file__).resolve().parents[2] / "shared" / "data" / "endonerf" / "pulling_soft_tissues"
WHATS = ("adam", "project", "project_bwd", "raster", "raster_bwd", "losses")


def cpu_s():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old", required=True, help="the old kernels' directory (e.g. a worktree's cl/)")
    ap.add_argument("--new", default=None, help="the new kernels' directory (default: this checkout's cl/)")
    ap.add_argument("--what", default=",".join(WHATS))
    ap.add_argument("--runs", type=int, default=30, help="runs of each side after 2 of warm-up")
    ap.add_argument("--scene", default=str(SHARED_SCENE))
    ap.add_argument("--downscale", type=float, default=2.0)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--old-adam-sh-per-item", type=int, default=None)
    ap.add_argument("--device", default=None)
    args = ap.parse_args(argv)

    import numpy as np
    import pyopencl.array as cla
    import endowave_cl.ops.adam as adam_mod
    from endowave_cl.data.scene import load_scene
    from endowave_cl.ops.adam import DeviceAdam
    from endowave_cl.ops.project import project4d, project4d_bwd
    from endowave_cl.ops.rasterize import rasterize, rasterize_bwd
    from endowave_cl.render import render, render_backward
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.config import TrainConfig
    from endowave_cl.train.trainer import Trainer
    from kernel_events import kernel_ms, profile_launches

    rt = get_runtime(args.device)
    events = profile_launches(rt)   # before the first pool allocation
    new_dir = Path(args.new) if args.new else rt.kdir
    sides = {"old": (Path(args.old).resolve(), {}, {}), "new": (new_dir.resolve(), {}, {})}
    gpw_new = adam_mod.sh_gaussians_per_item

    def use(side):
        rt.kdir, rt._programs, rt._kernels = sides[side]   # each side's own built programs
        if side == "old" and args.old_adam_sh_per_item:
            adam_mod.sh_gaussians_per_item = lambda ncoef: args.old_adam_sh_per_item
        else:
            adam_mod.sh_gaussians_per_item = gpw_new

    scene_path = Path(args.scene)
    if not (scene_path / "poses_bounds.npy").is_file():
        from endowave_cl.data.synth import make_synthetic_scene
        scene_path = Path(tempfile.mkdtemp()) / "synthetic_640"
        make_synthetic_scene(scene_path, width=640, height=512, frames=16, seed=0)
    scene = load_scene(scene_path, downscale=args.downscale)
    cfg = TrainConfig(iterations=10**6, init_points=args.gaussians, eval_every=0, checkpoint_every=0,
                      adam_skip_culled=False)
    run_dir = tempfile.TemporaryDirectory()
    use("new")
    tr = Trainer(scene, cfg, run_dir.name, rt, log=lambda s: None, resume=False)
    order = list(scene.train_indices)
    for i in range(3):
        tr.train_step(order[i % len(order)])
    k = order[7 % len(order)]
    frame, tgt = scene.frames[k], tr.targets[k]
    cam = frame.camera
    q = rt.queue
    out = render(rt, tr.params, cam, frame.time, tgt.next_time)
    _, _, v_feat = tr.losses_and_gradient(out, tgt)
    grads = render_backward(rt, tr.params, out, v_feat, sh_factors=True)
    p, b = out.proj, out.binned
    v_alpha = cla.zeros(q, (cam.height, cam.width), np.float32)
    from endowave_cl.ops.rasterize import rasterize_projected_bwd
    v2d = rasterize_projected_bwd(rt, p, b, out.raster, v_feat, v_alpha, cam.width, cam.height, deterministic=True)
    params0 = {n: a.get() for n, a in tr.params.items()}
    moments = tr.adam.state_dict()
    q.finish()
    print(f"device: {rt.describe()}")
    print(f"inputs: {scene_path.name} {cam.width}x{cam.height}, {len(params0['means'])} Gaussians, "
          f"{int((p.radius.get() > 0).sum())} visible, {b.n_isect} tile entries")
    print(f"old kernels {sides['old'][0]}, new {sides['new'][0]}; {args.runs} runs each after 2, "
          f"alternating ABBA; ratios new / old, median over pairs")

    keep = []   # the last outputs stay alive until read (their buffers, the camera's)

    def make(what):
        if what == "adam":
            opts = {}
            for side in sides:
                prm = {n: cla.to_device(q, a) for n, a in params0.items()}
                ad = DeviceAdam(rt, prm, tr.adam.lrs)
                ad.load_state_dict(moments)
                opts[side] = ad
            g = {n[2:]: a for n, a in grads.items()}

            def run(side):
                opts[side].step(g)
                return opts[side].params
            return run
        if what == "project":
            def run(side):
                pr = project4d(rt, tr.params, cam, frame.time, tgt.next_time)
                keep.append(pr)
                return {n: getattr(pr, n) for n in ("means2d", "conic", "depth", "radius", "opac", "features",
                                                     "rect", "tiles_touched", "color_inner")}
            return run
        if what == "project_bwd":
            projs = {}
            for side in sides:
                use(side)
                projs[side] = project4d(rt, tr.params, cam, frame.time, tgt.next_time)

            def run(side):
                gr = project4d_bwd(rt, tr.params, cam, frame.time, tgt.next_time, projs[side], v2d["v_means2d"],
                                   v2d["v_conic"], v2d["v_opac"], v2d["v_features"], sh_factors=True)
                return {n: (a.factors if hasattr(a, "factors") else a) for n, a in gr.items()}
            return run
        rargs = (p.means2d, p.conic, p.opac, p.features, b.sorted_values, b.tile_ranges, cam.width, cam.height)
        if what == "raster":
            def run(side):
                o = rasterize(rt, *rargs)
                keep.append(o)
                return {"out": o.out, "T_final": o.T_final, "last": o.last}
            return run
        if what == "raster_bwd":
            routs = {}
            for side in sides:
                use(side)
                routs[side] = rasterize(rt, *rargs)

            def run(side):
                return rasterize_bwd(rt, *rargs, routs[side], v_feat, v_alpha, deterministic=(p.rect, b.offsets))
            return run
        if what == "losses":
            def run(side):
                _, _, v = tr.losses_and_gradient(out, tgt)
                return {"v_features": v}
            return run
        raise SystemExit(f"--what: one of {', '.join(WHATS)}")

    for what in args.what.split(","):
        run = make(what)
        res = {"old": {}, "new": {}}
        first = {}
        for i in range(2 * (args.runs + 2)):
            side = ("old", "new")[(i % 2) ^ ((i // 2) % 2)]   # ABBA ABBA ...
            use(side)
            q.finish()
            events.clear()
            c0, t0 = cpu_s(), time.perf_counter()
            got = run(side)
            q.finish()
            wall, cpu = time.perf_counter() - t0, cpu_s() - c0
            del keep[:-4]
            if i >= 2 and side not in first:
                first[side] = {n: a.get() for n, a in got.items()}
                if "color_inner" in first[side]:   # never written (nor read) for culled Gaussians
                    first[side]["color_inner"][first[side]["radius"] == 0] = 0.0
            if i >= 4:
                r = res[side]
                for name, ms in kernel_ms(events).items():
                    r.setdefault(name, []).append(ms)
                r.setdefault("(wall)", []).append(wall * 1e3)
                r.setdefault("(cpu, all threads)", []).append(cpu * 1e3)
        same = all(np.array_equal(first["old"][n].view(np.uint32), first["new"][n].view(np.uint32))
                   for n in first["old"])
        print(f"{what}: same bits: {same}; load average {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
        for name, a in res["old"].items():
            bb = res["new"].get(name)
            if not bb:
                continue
            ratios = [y / x for x, y in zip(a, bb) if x > 0]
            print(f"  {name:24s} old {statistics.median(a):7.2f} ms (min {min(a):6.2f})   new "
                  f"{statistics.median(bb):7.2f} ms (min {min(bb):6.2f})   new / old {statistics.median(ratios):.3f}")
    use("new")


if __name__ == "__main__":
    main()
